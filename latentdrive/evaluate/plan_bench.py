"""The cost of a lookahead planner decision against one simulated step, in one run.

For each scenario, ``envs`` environments are driven by the planner for ``decisions``
vector steps (after one untimed step that loads the compiled kernels); the planner's time per environment-decision and the simulator's own time
per environment-step (the same rollout, ``DrivingVecEnv.timings``) are reported, with
their ratio. The ratio is roughly the number of branch-steps a decision simulates
(rounds × AVs × candidates × (depth + tail)), less what batching saves.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass

import numpy as np
from numpy.typing import NDArray

from latentdrive.evaluate.planner import PlannerConfig, candidate_sequences, planner_policy
from latentdrive.rollout import PolicyInput, rollout
from latentdrive.seeds import eval_reset_seed
from latentdrive.vec import make_vec

__all__ = ["PlanBenchRow", "bench_planner", "format_plan_bench"]


@dataclass(frozen=True)
class PlanBenchRow:
    scenario: str
    envs: int
    decisions: int  # environment-decisions timed
    branch_steps_per_decision: int  # simulated steps each decision asks for (upper bound)
    plan_ms_per_decision: float  # planner time per environment-decision
    sim_ms_per_step: float  # the simulator's time per environment-step, same run

    @property
    def ratio(self) -> float:
        return self.plan_ms_per_decision / self.sim_ms_per_step

    def as_dict(self) -> dict[str, float | int | str]:
        return {**asdict(self), "plan_over_step": self.ratio}


class _Timed:
    """A policy that adds up the time it spends deciding."""

    def __init__(self, policy: Callable[[PolicyInput], NDArray[np.int64]]) -> None:
        self.policy, self.seconds = policy, 0.0

    def __call__(self, inp: PolicyInput) -> NDArray[np.int64]:
        t0 = time.perf_counter()
        out = self.policy(inp)
        self.seconds += time.perf_counter() - t0
        return out


def bench_planner(scenarios: Sequence[str], envs: int = 16, decisions: int = 20, cfg: PlannerConfig | None = None,
                  progress: Callable[[str], None] | None = None) -> list[PlanBenchRow]:
    """Time the planner on every scenario (fast backend)."""
    config = cfg or PlannerConfig()
    rows = []
    for name in scenarios:
        vec = make_vec(name, envs)
        timer = _Timed(planner_policy(config))
        for k, _ in enumerate(rollout(vec, timer, seed=eval_reset_seed(0))):
            if k == 0:  # the first step loads compiled kernels: not timed
                timer.seconds, vec.timings["simulate"] = 0.0, 0.0
            elif k >= decisions:
                break
        n = decisions * envs
        per = config.rounds * vec.n_av * candidate_sequences(config.depth, config.switch).shape[0] * (config.depth + config.tail)
        rows.append(PlanBenchRow(name, envs, n, per, 1e3 * timer.seconds / n, 1e3 * vec.timings["simulate"] / n))
        vec.close()
        if progress:
            progress(f"  {name}: done")
    return rows


def format_plan_bench(rows: list[PlanBenchRow], cfg: PlannerConfig) -> str:
    head = (f"lookahead planner (depth {cfg.depth}, tail {cfg.tail}, {cfg.rounds} round(s)), fast backend, one core\n"
            f"{'scenario':<13}{'envs':>5}{'decisions':>10}{'branch-steps':>13}{'plan ms/decision':>17}"
            f"{'sim ms/step':>12}{'plan/step':>10}")
    lines = [head]
    for r in rows:
        lines.append(f"{r.scenario:<13}{r.envs:>5}{r.decisions:>10}{r.branch_steps_per_decision:>13}"
                     f"{r.plan_ms_per_decision:>17.1f}{r.sim_ms_per_step:>12.3f}{r.ratio:>9.0f}x")
    return "\n".join(lines)
