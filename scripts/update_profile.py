"""Where one learner update's time goes on a CUDA device: sampling, the update itself,
deterministic algorithms on and off, and torch.profiler's busiest operations.

    python scripts/update_profile.py            # raw and latent-random, fp32 and bf16

Needs CUDA (it times with device synchronizations). It builds the learner with the
settings ``latentdrive bench --train`` uses (16 envs, the default DQN; here of roundabout
and merge rather than all five scenarios),
fills 600 agent-transitions, then times 60 calls of each: ``Learner.update_step`` (sample
and update), the replay's ``sample`` alone, and ``update`` on one fixed batch, in
milliseconds per call. With deterministic algorithms and bf16 (``auto``'s choice on CUDA
when it was measured; fp32 now) it also prints the profiler's tables of 20 update steps, by host (CPU) time and by device time: a device
that computes for a fraction of the host's time is bound by the host's launches.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable

import torch

from latentdrive.rl.bench import bench_config
from latentdrive.rl.dqn import update
from latentdrive.rl.learner import Learner
from latentdrive.rl.policy import build_network, encoder_config
from latentdrive.rl.train import learner_steps
from latentdrive.runtime import resolve_device, resolve_precision, torch_settings
from latentdrive.vec import make_vec


def timed(fn: Callable[[], object], n: int, device: torch.device) -> float:
    """Milliseconds per call of ``fn``, after 5 untimed calls, between device synchronizations."""
    for _ in range(5):
        fn()
    torch.cuda.synchronize(device)
    t0 = time.perf_counter()
    for _ in range(n):
        fn()
    torch.cuda.synchronize(device)
    return (time.perf_counter() - t0) / n * 1e3


def profile_mode(mode: str, deterministic: bool, precision: str) -> None:
    cfg = bench_config(mode, ["roundabout", "merge"], 16, overrides={"precision": precision})
    device = resolve_device(cfg.device)
    with torch_settings(deterministic, device, 1, resolve_precision(cfg.precision, device)):
        net = build_network(cfg, encoder_config(cfg)).to(device)
        vec = make_vec(list(cfg.scenarios), cfg.envs, backend=cfg.backend, observation=cfg.observation.model_dump())
        learner = Learner(cfg, net, device, cfg.envs * vec.n_av)
        steps = learner_steps(learner, vec, seed=0)
        while learner.transitions < 600:
            next(steps)
        d = cfg.dqn
        batch = learner.replay.sample(learner.rng, d.batch_size, device)
        t_step = timed(learner.update_step, 60, device)
        t_sample = timed(lambda: learner.replay.sample(learner.rng, d.batch_size, device), 60, device)
        t_update = timed(lambda: update(learner.net, learner.target, learner.optimizer, batch, d, learner.dtype),
                         60, device)
        print(f"{mode:14s} deterministic={deterministic!s:5s} {precision}: update_step {t_step:.2f} ms, "
              f"sample {t_sample:.2f} ms, update on a fixed batch {t_update:.2f} ms", flush=True)
        if deterministic and precision == "bf16":
            from torch.profiler import ProfilerActivity, profile

            with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
                for _ in range(20):
                    learner.update_step()
                torch.cuda.synchronize(device)
            for key in ("self_cpu_time_total", "self_cuda_time_total"):
                print(prof.key_averages().table(sort_by=key, row_limit=12, max_name_column_width=48), flush=True)
        vec.close()


def main() -> int:
    if not torch.cuda.is_available():
        print("update_profile: needs a CUDA device (none found)", file=sys.stderr)
        return 2
    for mode in ("raw", "latent-random"):
        for deterministic in (True, False):
            for precision in ("fp32", "bf16"):
                profile_mode(mode, deterministic, precision)
    return 0


if __name__ == "__main__":
    sys.exit(main())
