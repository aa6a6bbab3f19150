"""``latentdrive bench --train``: where a training run's time goes, per input mode, measured in one run.

For each mode it runs the real training loop (:func:`latentdrive.rl.train.learner_steps`:
ε-greedy acting, replay writing, double-DQN updates) on the fast backend and reports:

- learner updates/s: updates on a filled replay alone (sampling included);
- end-to-end agent-transitions/s of the whole loop once learning has started;
- the share of that wall time spent simulating, rendering VelocityMaps (and rewards),
  encoding observations (what replay stores of them: the frozen encoder's code in latent
  modes, the objects reader's vehicle rows), and learning; the rest is
  replay writing, action selection and bookkeeping.

What bounds the learner: each row also counts the convolution and matrix-product
operations of one update (``torch.utils.flop_counter`` over a real update step: forward
and backward on the batch, the target's and the online network's passes on the next
observations; elementwise work such as the optimizer's counts nothing there) and, in
latent modes, of the frozen encoder per observation, and measures, right after, this
machine's rate on a dense fp32 matrix product (1024², the same threads). The learner's
achieved GFLOP/s against that rate says how far a faster implementation could go: at
``dqn.updates_per_transition`` updates per agent-transition, the counted arithmetic
bounds the loop at ``matmul rate / (FLOP per update · updates per transition + FLOP per
encoded observation)`` agent-transitions/s, an upper bound (the acting pass, elementwise
work and the extra encodes at episode ends are left out).

Each mode runs in fp32 and, where the run's ``precision`` resolves to bf16 on the device
(``--set precision=bf16``, or ``auto`` on a CPU with bf16 matrix units), in bf16
too, one after the other in the same process, so their ratio is measured in one run.

``latent`` and ``latent-random`` differ only in the encoder's weights, not in cost, so
without a BNN run the bench measures ``latent`` with an untrained encoder of the default
architecture and says so.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from typing import Any, Protocol

import torch
from torch.utils.flop_counter import FlopCounterMode

from latentdrive.config import merge_overrides, validate
from latentdrive.rl.config import PolicyTrainConfig
from latentdrive.rl.learner import Learner
from latentdrive.rl.policy import build_network, encoder_config
from latentdrive.rl.train import learner_steps
from latentdrive.runtime import resolve_device, resolve_precision, torch_settings
from latentdrive.vec import make_vec

__all__ = ["Together", "TrainBenchRow", "bench_config", "bench_training", "format_train_bench", "matmul_gflops"]

#: The authors' public runs: ~4.5 h per 4,000 episodes, about 5 env steps/s per run (ANCHORS.md).
AUTHORS_ENV_STEPS_PER_S = 5.0


@dataclass(frozen=True)
class TrainBenchRow:
    mode: str
    device: str
    trainable_parameters: int
    updates_per_s: float
    transitions_per_s: float
    env_steps_per_s: float
    simulate: float
    render: float
    encode: float
    learn: float
    #: Over repeated runs of this mode: how many, and the slowest and fastest
    #: agent-transitions/s (the row's other numbers are those of the median run).
    runs: int = 1
    transitions_per_s_min: float | None = None
    transitions_per_s_max: float | None = None
    #: The compute precision of the forward passes: 'fp32' or 'bf16'.
    precision: str = "fp32"
    #: Floating-point operations of one learner update (counted), and this machine's dense
    #: fp32 matrix-product rate measured right after the mode (GFLOP/s).
    gflop_per_update: float = float("nan")
    matmul_gflops: float = float("nan")
    updates_per_transition: float = float("nan")
    #: Latent modes: the frozen encoder's FLOP per observation (GFLOP); it encodes about
    #: one new observation per agent-transition. 0 in the other modes.
    gflop_per_encode: float = 0.0

    @property
    def learner_gflops(self) -> float:
        """What the learner achieved: FLOP per update times updates/s, GFLOP/s."""
        return self.gflop_per_update * self.updates_per_s

    @property
    def learning_cap(self) -> float:
        """Agent-transitions/s that learning alone would allow at the matrix product's rate."""
        return self.matmul_gflops / (self.gflop_per_update * self.updates_per_transition)

    @property
    def arithmetic_cap(self) -> float:
        """Agent-transitions/s that learning and encoding together would allow at the matrix
        product's rate: an upper bound, counting one encoded observation per agent-transition
        (episode ends encode a few more)."""
        per_transition = self.gflop_per_update * self.updates_per_transition + self.gflop_per_encode
        return self.matmul_gflops / per_transition

    @property
    def other(self) -> float:
        return max(0.0, 1.0 - self.simulate - self.render - self.encode - self.learn)

    def as_dict(self) -> dict[str, Any]:
        return {**asdict(self), "other": self.other}


class Together(Protocol):
    """Processes measured together (:mod:`latentdrive.rl.bench_shared`): their timed loops
    start together and all stop when the first one is done, so each is timed against the
    same load."""

    def start(self) -> None:
        """Wait until every process is ready to time."""

    def over(self) -> bool:
        """Whether another process has ended its timed loop."""

    def end(self) -> None:
        """This process has ended its timed loop."""


def _bench_mode(cfg: PolicyTrainConfig, transitions: int, updates: int,
                together: Together | None = None) -> TrainBenchRow:
    device = resolve_device(cfg.device)
    with torch_settings(True, device, cfg.threads, resolve_precision(cfg.precision, device)):
        net = build_network(cfg, encoder_config(cfg)).to(device)
        vec = make_vec(list(cfg.scenarios), cfg.envs, backend=cfg.backend, observation=cfg.observation.model_dump())
        learner = Learner(cfg, net, device, cfg.envs * vec.n_av)
        steps = learner_steps(learner, vec, seed=0)
        while learner.transitions < cfg.dqn.learning_starts:  # fill the replay first
            next(steps)
        for _ in range(10):  # warm up the learner and the kernels
            next(steps)
        if together is not None:
            together.start()
        t_sim0, t_obs0 = vec.timings["simulate"], vec.timings["observe"]
        enc0, learn0, tr0, vsteps = learner.cache.seconds, learner.learn_seconds, learner.transitions, 0
        t0 = time.perf_counter()
        while learner.transitions - tr0 < transitions and not (together is not None and together.over()):
            next(steps)
            vsteps += 1
        wall = time.perf_counter() - t0
        if together is not None:
            together.end()
        done = learner.transitions - tr0
        share = {
            "simulate": (vec.timings["simulate"] - t_sim0) / wall, "render": (vec.timings["observe"] - t_obs0) / wall,
            "encode": (learner.cache.seconds - enc0) / wall, "learn": (learner.learn_seconds - learn0) / wall,
        }
        t0 = time.perf_counter()
        for _ in range(updates):
            learner.update_step()
        ups = updates / (time.perf_counter() - t0)
        with FlopCounterMode(display=False) as counter:
            learner.update_step()
        encode = 0.0
        if net.stores_features:
            one = torch.zeros(8, *cfg.observation.shape, device=device)
            with FlopCounterMode(display=False) as enc_counter:
                net.features(one)
            encode = enc_counter.get_total_flops() / 8 / 1e9
        vec.close()
        matmul = matmul_gflops(device)
    return TrainBenchRow(mode=cfg.mode, device=str(device), trainable_parameters=net.parameter_count()["trainable"],
                         precision="bf16" if learner.dtype == torch.bfloat16 else "fp32", updates_per_s=ups, transitions_per_s=done / wall, env_steps_per_s=vsteps * cfg.envs / wall,
                         simulate=share["simulate"], render=share["render"], encode=share["encode"], learn=share["learn"],
                         gflop_per_update=counter.get_total_flops() / 1e9, matmul_gflops=matmul,
                         updates_per_transition=cfg.dqn.updates_per_transition, gflop_per_encode=encode)


def matmul_gflops(device: torch.device, n: int = 1024, repeat: int = 10) -> float:
    """This device's rate on an ``n × n`` fp32 matrix product (GFLOP/s, 2n³ per product),
    at the current thread count: a practical ceiling for dense arithmetic here."""
    a = torch.rand(n, n, device=device)
    b = torch.rand(n, n, device=device)
    for _ in range(2):
        a @ b
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    t0 = time.perf_counter()
    for _ in range(repeat):
        a @ b
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    return 2 * n**3 * repeat / (time.perf_counter() - t0) / 1e9


def bench_config(mode: str, scenarios: Sequence[str], envs: int, bnn: str | None = None,
                 overrides: dict[str, Any] | None = None) -> PolicyTrainConfig:
    """The training run that ``bench --train`` measures for ``mode`` (validated: a bad
    override fails here, before any work): ``latent`` without a BNN run measures
    ``latent-random``, an encoder of the same cost."""
    data: dict[str, Any] = {"mode": mode, "scenarios": list(scenarios), "envs": envs, "steps": 10**9,
                            "dqn": {"learning_starts": 500}}
    if mode == "latent":
        data["bnn"] = bnn
        if not bnn:
            data["mode"] = "latent-random"
    return validate(PolicyTrainConfig, merge_overrides(data, overrides or {}))


def bench_training(modes: Sequence[str], scenarios: Sequence[str], *, transitions: int = 2000, updates: int = 50,
                   envs: int = 16, bnn: str | None = None, overrides: dict[str, Any] | None = None,
                   progress: Callable[[str], None] | None = None, repeat: int = 1,
                   together: Together | None = None) -> list[TrainBenchRow]:
    """One row per mode and precision (fp32, and the run's precision where it resolves to
    bf16); with ``repeat`` > 1 each runs that many times and its row is the median run,
    with the range of agent-transitions/s beside it. With ``together`` each timed loop
    starts and stops with those of other processes (:mod:`latentdrive.rl.bench_shared`)."""
    if repeat < 1:
        raise ValueError(f"repeat must be at least 1, got {repeat}")
    rows = []
    for mode in modes:
        chosen = bench_config(mode, scenarios, envs, bnn, overrides)
        precisions = ["fp32"]
        if resolve_precision(chosen.precision, resolve_device(chosen.device)) == torch.bfloat16:
            precisions.append("bf16")
        for precision in precisions:
            cfg = chosen.replace(precision=precision)
            runs = []
            for _ in range(repeat):
                runs.append(_bench_mode(cfg, transitions, updates, together))
                if progress:
                    progress(f"  {mode} {precision}: {runs[-1].transitions_per_s:.0f} agent-transitions/s")
            rates = sorted(r.transitions_per_s for r in runs)
            # The median run (the lower middle one for an even count) speaks for the mode.
            row = next(r for r in runs if r.transitions_per_s == rates[(len(rates) - 1) // 2])
            rows.append(TrainBenchRow(**{**asdict(row), "mode": mode if bnn or mode != "latent" else "latent (untrained encoder)",
                                         "runs": repeat, "transitions_per_s_min": rates[0],
                                         "transitions_per_s_max": rates[-1]}))
    return rows


def format_train_bench(rows: list[TrainBenchRow], envs: int, threads: int) -> str:
    head = (f"training loop on the fast backend, {envs} envs, torch threads {threads}; shares of end-to-end wall time\n"
            f"{'mode':<28}{'device':>7}{'prec':>6}{'params':>10}{'updates/s':>11}{'agent-tr/s':>12}{'env steps/s':>13}"
            f"{'vs authors':>12}{'sim':>6}{'render':>8}{'encode':>8}{'learn':>7}{'other':>7}")
    lines = [head]
    for r in rows:
        lines.append(
            f"{r.mode:<28}{r.device:>7}{r.precision:>6}{r.trainable_parameters:>10}{r.updates_per_s:>11.1f}{r.transitions_per_s:>12.0f}"
            f"{r.env_steps_per_s:>13.0f}{r.env_steps_per_s / AUTHORS_ENV_STEPS_PER_S:>11.0f}x"
            f"{100 * r.simulate:>5.0f}%{100 * r.render:>7.0f}%{100 * r.encode:>7.0f}%{100 * r.learn:>6.0f}%{100 * r.other:>6.0f}%")
    fp32 = {r.mode: r for r in rows if r.precision == "fp32"}
    for r in rows:
        base = fp32.get(r.mode)
        if r.precision != "fp32" and base is not None:
            lines.append(f"{r.mode}: {r.precision} over fp32 in this run: agent-transitions/s "
                         f"{r.transitions_per_s / base.transitions_per_s:.2f}x, updates/s "
                         f"{r.updates_per_s / base.updates_per_s:.2f}x")
    if not any(r.precision != "fp32" for r in rows):
        lines.append("precision: fp32 only (the run's precision resolves to fp32 on this device; "
                     "--set precision=bf16 measures bf16 beside it)")
    for r in rows:
        lines.append(f"{r.mode} ({r.precision}): {r.gflop_per_update:.3g} GFLOP per update, {r.learner_gflops:.0f} GFLOP/s "
                     f"achieved, {r.learner_gflops / r.matmul_gflops:.0%} of a 1024² fp32 matrix product here "
                     f"({r.matmul_gflops:.0f} GFLOP/s); at {r.updates_per_transition:g} updates per agent-transition, "
                     f"learning at that rate would allow at most {r.learning_cap:.0f} agent-transitions/s"
                     + (f"; with the encoder's {r.gflop_per_encode:.3f} GFLOP per observation, learning and "
                        f"encoding at that rate at most {r.arithmetic_cap:.0f}" if r.gflop_per_encode else ""))
    for r in rows:
        if r.runs > 1:
            lines.append(f"{r.mode}: the median of {r.runs} runs; agent-transitions/s ranged "
                         f"{r.transitions_per_s_min:.0f}-{r.transitions_per_s_max:.0f}")
    lines.append(f"'vs authors': env steps/s over the authors' ~{AUTHORS_ENV_STEPS_PER_S:g} env steps/s per run "
                 "(4,000 episodes in ~4.5 h on a GPU node).")
    return "\n".join(lines)
