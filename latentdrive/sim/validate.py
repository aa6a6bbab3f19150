"""Fidelity and throughput of the fast backend against the highway-env reference.

It runs both backends, so it lives above both: the fast backend itself never imports the
reference it is measured against.

Fidelity: per scenario and policy (uniformly random meta-actions, or always Idle), the
same seeded episodes run on both backends (same placement, same action sequences), and
four statistics are compared with 95% intervals: crash rate (episodes ending with an AV
crashed), episode length (decisions), mean speed (all vehicles, every decision) and HV
lane-change rate (changes of an HV's lane within one road, per HV-minute). Episodes end
as in the env: an AV crashed, every AV arrived, or the time limit.

Throughput: env steps per second of each backend's simulation on one core, random actions
with auto-reset, Scenes produced every step; both measured in the same process, one after
the other. (With VelocityMaps, through the envs: :mod:`latentdrive.bench`.)

Known differences from highway-env (each makes single trajectories drift, none shows in
the statistics at the tolerances below):

- Arctangents come from the C library in the compiled kernels and from numpy's own
  vectorized code in highway-env; they differ in the last bit for some arguments. Such
  differences stay at 1e-12 m, except when an AV is nearly stopped, where highway-env's
  steering law divides by a speed floored at 0.01 m/s and amplifies them (to ~1e-4 m).
- A right-of-way prediction that runs onto a route edge with fewer lanes than the
  vehicle's current lane raises IndexError in highway-env; here it takes the edge's last
  lane (never happens on the intersection, the only regulated layout, whose edges all
  have one lane).
- Exact ties in longitudinal position between two vehicles on a lane resolve in slot
  order as in highway-env, but only when their positions are bit-identical.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass

import numpy as np

from latentdrive.reward import episode_end
from latentdrive.scenarios import SCENARIOS, get_spec
from latentdrive.scenarios.spec import ScenarioSpec
from latentdrive.scene import Scene
from latentdrive.sim.fast import FastBatch
from latentdrive.sim.highway import HighwayBackend

__all__ = [
    "TOLERANCES",
    "FidelityRow",
    "ThroughputRow",
    "fidelity_table",
    "format_fidelity",
    "format_throughput",
    "measure_scaling",
    "measure_throughput",
    "rollout_fast",
    "rollout_highway",
]

POLICIES = ("random", "idle")
IDLE = 1
# Allowed |fast - highway| per statistic: crash rate (fraction of episodes), episode
# length (decisions), mean speed (m/s), HV lane changes per HV-minute.
TOLERANCES = {"crash_rate": 0.02, "length": 0.25, "speed": 0.1, "lane_change_rate": 0.1}


@dataclass(frozen=True)
class Episode:
    """Statistics of one episode."""

    crashed: bool
    length: int  # decisions
    speed: float  # mean over decisions and vehicles, m/s
    hv_lane_changes: int
    hv_minutes: float  # HV count × simulated minutes


def _actions(policy: str, n_av: int, rng: np.random.Generator) -> np.ndarray:
    if policy == "idle":
        return np.full(n_av, IDLE, dtype=np.int64)
    return rng.integers(0, 5, n_av)


def _lane_changes(before: list[tuple[str, str, int]], after: list[tuple[str, str, int]], hv: np.ndarray) -> int:
    return sum(1 for k in np.flatnonzero(hv) if before[k][:2] == after[k][:2] and before[k][2] != after[k][2])


def _done(scene: Scene, steps: int, spec: ScenarioSpec) -> bool:
    return any(episode_end(scene, steps, spec))


def _episode(spec: ScenarioSpec, scenes: list[Scene], changes: int) -> Episode:
    last = scenes[-1]
    n_hv = int(np.sum(last.kind == 0))
    steps = len(scenes) - 1
    return Episode(
        crashed=bool(last.crashed[last.agents].any()),
        length=steps,
        speed=float(np.mean([s.speed.mean() for s in scenes[1:]])),
        hv_lane_changes=changes,
        hv_minutes=n_hv * steps / spec.policy_frequency / 60.0,
    )


def rollout_highway(spec: ScenarioSpec, seeds: Sequence[int], policy: str) -> list[Episode]:
    """Episodes on the highway-env reference, one per seed."""
    backend = HighwayBackend(spec)
    out = []
    for seed in seeds:
        rng = np.random.default_rng([seed, 3])
        scenes = [backend.reset(seed)]
        assert backend.road is not None
        hv = scenes[0].kind == 0
        lanes = [v.lane_index for v in backend.road.vehicles]
        changes = 0
        while not _done(scenes[-1], len(scenes) - 1, spec):
            scenes.append(backend.step(_actions(policy, spec.n_av, rng)))
            now = [v.lane_index for v in backend.road.vehicles]
            changes += _lane_changes(lanes, now, hv)
            lanes = now
        out.append(_episode(spec, scenes, changes))
    return out


def rollout_fast(spec: ScenarioSpec, seeds: Sequence[int], policy: str, batch_size: int = 64) -> list[Episode]:
    """The same episodes on the fast backend, ``batch_size`` at a time."""
    out: list[Episode] = []
    for start in range(0, len(seeds), batch_size):
        chunk = list(seeds[start: start + batch_size])
        batch = FastBatch([spec] * len(chunk))
        rngs = [np.random.default_rng([s, 3]) for s in chunk]
        scenes = [[s] for s in batch.reset(chunk)]
        lanes = [batch.lane_keys(i) for i in range(len(chunk))]
        changes = [0] * len(chunk)
        live = [True] * len(chunk)
        while any(live):
            actions = [_actions(policy, spec.n_av, rng) if alive else np.ones(spec.n_av, np.int64)
                       for rng, alive in zip(rngs, live, strict=True)]
            now_scenes = batch.step(actions)
            for i in range(len(chunk)):
                if not live[i]:
                    continue
                scenes[i].append(now_scenes[i])
                now = batch.lane_keys(i)
                changes[i] += _lane_changes(lanes[i], now, scenes[i][0].kind == 0)
                lanes[i] = now
                live[i] = not _done(now_scenes[i], len(scenes[i]) - 1, spec)
        out += [_episode(spec, sc, ch) for sc, ch in zip(scenes, changes, strict=True)]
    return out


def _mean_ci(x: np.ndarray) -> tuple[float, float]:
    """Mean and half-width of its normal 95% interval."""
    half = 1.96 * float(np.std(x, ddof=1)) / math.sqrt(len(x)) if len(x) > 1 else math.inf
    return float(np.mean(x)), half


def _rate_ci(k: int, n: int) -> tuple[float, float]:
    """Proportion and half-width of its Wilson 95% interval (centred on the proportion)."""
    if n == 0:
        return math.nan, math.inf
    z = 1.96
    p = k / n
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return p, half


def _summary(episodes: list[Episode]) -> dict[str, tuple[float, float]]:
    crashed = sum(e.crashed for e in episodes)
    minutes = sum(e.hv_minutes for e in episodes)
    per_ep_rate = np.array([e.hv_lane_changes / e.hv_minutes if e.hv_minutes else 0.0 for e in episodes])
    rate = sum(e.hv_lane_changes for e in episodes) / minutes if minutes else 0.0
    return {
        "crash_rate": _rate_ci(crashed, len(episodes)),
        "length": _mean_ci(np.array([e.length for e in episodes], dtype=float)),
        "speed": _mean_ci(np.array([e.speed for e in episodes])),
        "lane_change_rate": (rate, _mean_ci(per_ep_rate)[1]),
    }


@dataclass(frozen=True)
class FidelityRow:
    """One statistic of one scenario and policy on both backends."""

    scenario: str
    policy: str
    statistic: str
    highway: float
    highway_ci: float  # half-width of the 95% interval
    fast: float
    fast_ci: float
    tolerance: float

    @property
    def difference(self) -> float:
        return self.fast - self.highway

    @property
    def ok(self) -> bool:
        return abs(self.difference) <= self.tolerance

    def as_dict(self) -> dict[str, float | str | bool]:
        return {**asdict(self), "difference": self.difference, "ok": self.ok}


def fidelity_table(
    scenarios: Sequence[str] = SCENARIOS,
    episodes: int = 200,
    policies: Sequence[str] = POLICIES,
    seed: int = 0,
    progress: Callable[[str], None] | None = None,
) -> list[FidelityRow]:
    """Run ``episodes`` seeded episodes per scenario and policy on both backends.

    ``episodes=4`` is a quick smoke setting; 200 gives intervals of a few percent.
    """
    rows = []
    for name in scenarios:
        spec = get_spec(name)
        seeds = [seed + k for k in range(episodes)]
        for policy in policies:
            hw = _summary(rollout_highway(spec, seeds, policy))
            fa = _summary(rollout_fast(spec, seeds, policy))
            for stat, tol in TOLERANCES.items():
                rows.append(FidelityRow(name, policy, stat, hw[stat][0], hw[stat][1], fa[stat][0], fa[stat][1], tol))
            if progress:
                progress(f"  {name}/{policy}: done ({episodes} episodes)")
    return rows


def format_fidelity(rows: list[FidelityRow]) -> str:
    """A plain-text table of the rows."""
    lines = [f"{'scenario':<13}{'policy':<8}{'statistic':<18}{'highway':>16}{'fast':>16}{'diff':>9}{'tol':>7}  ok"]
    for r in rows:
        lines.append(
            f"{r.scenario:<13}{r.policy:<8}{r.statistic:<18}{r.highway:>9.3f} ±{r.highway_ci:<5.3f}"
            f"{r.fast:>9.3f} ±{r.fast_ci:<5.3f}{r.difference:>+9.3f}{r.tolerance:>7.2f}  {'yes' if r.ok else 'NO'}"
        )
    return "\n".join(lines)


@dataclass(frozen=True)
class ThroughputRow:
    """Env steps per second of both backends on one scenario."""

    scenario: str
    vehicles: int
    n_av: int
    batch_size: int
    velocity_maps: bool
    highway_steps_per_s: float
    fast_steps_per_s: float
    #: Over repeated runs: how many, and the smallest and largest speed-up (the row's
    #: rates are those of the run with the median speed-up).
    runs: int = 1
    speedup_min: float | None = None
    speedup_max: float | None = None

    @property
    def speedup(self) -> float:
        return self.fast_steps_per_s / self.highway_steps_per_s

    @property
    def fast_agent_obs_per_s(self) -> float:
        """Agent observations (one per AV per env step) per second of the fast batch."""
        return self.fast_steps_per_s * self.n_av

    def as_dict(self) -> dict[str, float | int | str | bool]:
        return {**asdict(self), "speedup": self.speedup, "fast_agent_obs_per_s": self.fast_agent_obs_per_s,
                "highway_agent_obs_per_s": self.highway_steps_per_s * self.n_av}


def measure_throughput(
    scenario: str | ScenarioSpec,
    batch_size: int = 64,
    fast_steps: int = 50,
    highway_steps: int = 40,
    seed: int = 0,
) -> ThroughputRow:
    """Env steps/s of the simulation alone: a ``batch_size`` FastBatch and the highway-env
    reference (observations: see :func:`latentdrive.bench.measure_env_throughput`).

    Both take random meta-actions, reset an environment as soon as its episode ends, and
    produce a Scene per environment per step. The fast figure counts ``batch_size`` env
    steps per batch step.
    """
    spec = get_spec(scenario)
    rng = np.random.default_rng(seed)

    backend = HighwayBackend(spec)
    scene = backend.reset(seed)
    episodes = 1
    t0 = time.perf_counter()
    for _ in range(highway_steps):
        scene = backend.step(rng.integers(0, 5, spec.n_av))
        if _done(scene, round(scene.time * spec.policy_frequency), spec):
            scene = backend.reset(seed + episodes)
            episodes += 1
    highway = highway_steps / (time.perf_counter() - t0)

    batch = FastBatch([spec] * batch_size)
    scenes = batch.reset(list(range(seed, seed + batch_size)))
    batch.step(rng.integers(0, 5, (batch_size, spec.n_av)))  # compile or load the kernels
    next_seed = seed + batch_size
    t0 = time.perf_counter()
    for _ in range(fast_steps):
        scenes = batch.step(rng.integers(0, 5, (batch_size, spec.n_av)))
        done = [i for i, s in enumerate(scenes) if _done(s, round(s.time * spec.policy_frequency), spec)]
        if done:
            batch.reset(list(range(next_seed, next_seed + len(done))), done)
            next_seed += len(done)
    fast = fast_steps * batch_size / (time.perf_counter() - t0)
    return ThroughputRow(spec.name, spec.n_av + spec.n_hv, spec.n_av, batch_size, False, highway, fast)


def measure_scaling(
    counts: Sequence[int] = (12, 25, 50, 100, 200), batch_size: int = 16, steps: int = 10, seed: int = 0,
) -> list[tuple[int, float]]:
    """Fast env steps/s on the highway layout against the number of HVs per environment.

    HVs are spread over three lanes at the highway preset's density (12 HVs per 320 m),
    so the road grows with the count; the AVs stay Idle and nothing is reset, so the
    figures are of the simulation alone.
    Returns ``(vehicles per environment, env steps/s)`` pairs; per-vehicle cost that stays
    flat as the count grows means linear scaling.
    """
    out = []
    for n_hv in counts:
        half = 160.0 * max(n_hv, 12) / 12  # metres either side of the region's centre
        spec = get_spec("highway", n_hv=n_hv, duration=steps + 1, hv_spawn=[{
            "edge": ["0", "1"], "lanes": [0, 1, 2], "longitudinal": {"mean": half + 40.0, "std": half / 2, "clip": half},
            "speed": {"mean": 24.0, "std": 1.5, "clip": 3.0}}])
        batch = FastBatch([spec] * batch_size)
        batch.reset(list(range(seed, seed + batch_size)))
        idle = np.full((batch_size, spec.n_av), IDLE, dtype=np.int64)
        batch.advance(idle)  # compile or load the kernels
        t0 = time.perf_counter()
        for _ in range(steps - 1):
            batch.advance(idle)
        out.append((spec.n_av + n_hv, (steps - 1) * batch_size / (time.perf_counter() - t0)))
    return out


def format_throughput(rows: list[ThroughputRow]) -> str:
    """A plain-text table of the rows (with the speed-up's range where a row is a median)."""
    lines = [f"{'scenario':<13}{'vehicles':>9}{'batch':>7}{'maps':>6}{'highway steps/s':>17}{'fast steps/s':>14}"
             f"{'speed-up':>10}{'runs':>6}{'range':>14}"]
    for r in rows:
        spread = f"{r.speedup_min:.0f}-{r.speedup_max:.0f}x" if r.runs > 1 else "-"
        lines.append(f"{r.scenario:<13}{r.vehicles:>9}{r.batch_size:>7}{'yes' if r.velocity_maps else 'no':>6}"
                     f"{r.highway_steps_per_s:>17.1f}{r.fast_steps_per_s:>14.0f}{r.speedup:>9.0f}x{r.runs:>6}{spread:>14}")
    return "\n".join(lines)
