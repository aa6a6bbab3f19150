"""Run a study graph's unfinished steps as Ray tasks on an existing cluster.

The same scheduling loop as local mode (:func:`~latentdrive.experiments.executor.run_graph`)
and the same step keys, so an interrupted driver resumes with the same command, and a
study started locally can finish on a cluster (or the reverse). Every node must see the
study folder at the same path (a shared filesystem); a step whose inputs are missing on
its node fails with a one-line error naming the path.

Each step is one task, asking for its kind's CPUs and, when the cluster has GPUs, a share
of one for the kinds that use it. Ray reuses worker processes (a fresh one per step cost
seconds of imports each); each step resets the process's peak-memory mark, so it still
records its own peak. A task whose worker dies (a killed process, a lost node) is retried by
Ray up to ``retries`` times; an error raised by the step itself is not retried (it would
fail the same way) and is reported with the step's name.

Ray is an optional dependency (``pip install latentdrive[ray]``); only this module imports it.
"""

from __future__ import annotations

import socket
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from latentdrive.errors import LatentDriveError
from latentdrive.experiments.executor import (
    StepKind,
    StepRecords,
    check_kinds,
    execute_step,
    run_graph,
)
from latentdrive.experiments.graph import Graph, Step, StepRecord

__all__ = ["check_ray_address", "run_ray"]


class _RayRunner:
    def __init__(self, ray: Any, retries: int, gpu_fraction: float) -> None:
        self.ray = ray
        res = ray.cluster_resources()
        self.slots = max(1, int(res.get("CPU", 1)))
        self.has_gpu = res.get("GPU", 0) > 0
        self.retries, self.gpu_fraction = retries, gpu_fraction
        self.remote = ray.remote(execute_step)

    def submit(self, kind: StepKind, step: Step, key: str, inputs: Mapping[str, Path], folder: Path,
               records: StepRecords) -> Any:
        gpus = self.gpu_fraction if self.has_gpu and kind.wants_gpu(step) else 0
        return self.remote.options(num_cpus=kind.cpus, num_gpus=gpus, max_retries=self.retries,
                                   retry_exceptions=False, name=step.name).remote(
            kind, step, key, inputs, folder, records)

    def wait(self, handles: Sequence[Any]) -> list[Any]:
        done, _ = self.ray.wait(list(handles), num_returns=1)
        return list(done)

    def result(self, handle: Any) -> StepRecord:
        from ray.exceptions import RayTaskError

        try:
            rec: StepRecord = self.ray.get(handle)
        except RayTaskError as exc:
            # The step's own exception, not Ray's multi-line wrapper around it.
            raise (exc.cause if exc.cause is not None else exc) from None
        return rec


def check_ray_address(address: str) -> None:
    """Refuse an address whose host does not resolve: Ray itself retries such a name for minutes."""
    if address in ("auto", "local"):
        return
    host = address.split("://", 1)[-1].rsplit(":", 1)[0].strip("[]")
    try:
        socket.getaddrinfo(host, None)
    except (socket.gaierror, UnicodeError) as exc:
        raise LatentDriveError(f"--ray {address}: cannot resolve host {host!r} ({exc})") from None


def run_ray(graph: Graph, out: Path, kinds: Mapping[str, StepKind], address: str, *, retries: int = 2,
            gpu_fraction: float = 1.0, progress: bool = True, local_cpus: int | None = None,
            runtime_env: dict[str, Any] | None = None,
            on_done: Callable[[StepRecord], None] | None = None) -> dict[str, StepRecord]:
    """Run every unfinished step of ``graph`` on the Ray cluster at ``address``.

    ``address`` is what ``ray.init`` takes (``auto`` finds the cluster this machine
    joined with ``ray start``; ``ray://host:10001`` or ``host:6379`` name one), or
    ``local`` to start a private single-machine instance with ``local_cpus`` CPUs (all
    by default). ``gpu_fraction`` is the share
    of a GPU a training step asks for (several small policies fit on one GPU);
    ``runtime_env`` is passed to ``ray.init`` (e.g. environment variables for the workers);
    ``on_done`` is called with each step's record as it finishes.
    """
    try:
        import ray
    except ImportError:
        raise LatentDriveError("--ray needs Ray: pip install 'latentdrive[ray]'") from None
    if not 0 < gpu_fraction <= 1:
        raise LatentDriveError(f"--gpu-fraction must be in (0, 1], got {gpu_fraction}")
    check_kinds(graph, kinds)
    check_ray_address(address)
    started = not ray.is_initialized()
    if started:
        try:
            if address == "local":
                ray.init(num_cpus=local_cpus, include_dashboard=False, log_to_driver=False, runtime_env=runtime_env)
            else:
                ray.init(address=address, log_to_driver=False, runtime_env=runtime_env)
        except ConnectionError as exc:
            raise LatentDriveError(f"--ray {address}: no Ray cluster there ({str(exc).splitlines()[0]})") from None
    try:
        return run_graph(graph, out, kinds, _RayRunner(ray, retries, gpu_fraction), progress=progress, on_done=on_done)
    finally:
        if started:
            ray.shutdown()
