"""``latentdrive bench``: simulation and observation throughput, measured in one run.

``bench --backend fast`` (:func:`bench_fast`) compares the fast backend with highway-env
per scenario, each figure measured in the same run as its reference: the simulation
alone, and whole environments with a VelocityMap for every acting AV, resets included
(:func:`measure_env_throughput`).

``bench`` on the highway backend (:func:`run_bench`) steps it with random meta-actions
(resetting when an episode ends) and, at every step, times three things on the same
instant:

- the simulation step alone (env steps/s),
- our VelocityMap frame for every AV, noise included (ms per agent-frame),
- highway-env's OccupancyGridObservation over the same cells for every AV (ms per
  agent-frame), the reference the VelocityMap is compared with.

Ratios are of figures measured in the same process, seconds apart, on the same scenes.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, replace

import numpy as np

from latentdrive.config import ObservationConfig
from latentdrive.env import make_env
from latentdrive.observe import render_frame
from latentdrive.reward import episode_end
from latentdrive.scenarios import get_spec
from latentdrive.sim.highway import HighwayBackend
from latentdrive.sim.validate import ThroughputRow, measure_throughput
from latentdrive.vec import make_vec

__all__ = ["BenchRow", "bench_fast", "format_table", "measure_env_throughput", "run_bench"]


@dataclass(frozen=True)
class BenchRow:
    """One scenario's measurements."""

    scenario: str
    vehicles: float  # mean vehicles per scene
    n_av: int
    steps: int
    sim_steps_per_s: float
    obs_ms_per_agent_frame: float
    grid_ms_per_agent_frame: float

    @property
    def grid_over_obs(self) -> float:
        """How many times cheaper the VelocityMap is than the OccupancyGrid."""
        return self.grid_ms_per_agent_frame / self.obs_ms_per_agent_frame

    def as_dict(self) -> dict[str, float | int | str]:
        return {**asdict(self), "grid_over_obs": self.grid_over_obs}


def _bench_one(name: str, steps: int, seed: int, obs_cfg: ObservationConfig) -> BenchRow:
    spec = get_spec(name)
    backend = HighwayBackend(spec)
    rng = np.random.default_rng(seed)
    noise_rng = np.random.default_rng([seed, 2])
    episode = 0
    scene = backend.reset(seed)
    grid = backend.occupancy_grid(obs_cfg)
    t_sim = t_obs = t_grid = 0.0
    agent_frames = 0
    n_vehicles = []
    ep_steps = 0  # policy steps into the current episode
    for _ in range(steps):
        actions = rng.integers(0, 5, size=spec.n_av)
        t0 = time.perf_counter()
        scene = backend.step(actions)
        t1 = time.perf_counter()
        render_frame(scene, scene.agents, obs_cfg, rng=noise_rng)
        t2 = time.perf_counter()
        grid()
        t3 = time.perf_counter()
        t_sim, t_obs, t_grid = t_sim + t1 - t0, t_obs + t2 - t1, t_grid + t3 - t2
        agent_frames += scene.n_agents
        n_vehicles.append(scene.n_vehicles)
        ep_steps += 1
        if any(episode_end(scene, ep_steps, spec)):
            ep_steps = 0
            episode += 1
            scene = backend.reset(seed + episode)
            grid = backend.occupancy_grid(obs_cfg)
    return BenchRow(
        scenario=name,
        vehicles=float(np.mean(n_vehicles)),
        n_av=spec.n_av,
        steps=steps,
        sim_steps_per_s=steps / t_sim,
        obs_ms_per_agent_frame=1e3 * t_obs / agent_frames,
        grid_ms_per_agent_frame=1e3 * t_grid / agent_frames,
    )


def run_bench(
    scenarios: Iterable[str],
    steps: int = 50,
    seed: int = 0,
    obs_cfg: ObservationConfig | None = None,
    progress: Callable[[str], None] | None = None,
) -> list[BenchRow]:
    """Measure every scenario; ``progress`` receives one line per finished scenario."""
    cfg = obs_cfg or ObservationConfig()
    rows = []
    for name in scenarios:
        row = _bench_one(name, steps, seed, cfg)
        rows.append(row)
        if progress:
            progress(f"  {name}: done ({row.steps} steps)")
    return rows


def format_table(rows: list[BenchRow], cfg: ObservationConfig) -> str:
    """A plain-text table of the rows, with the grid they were measured at."""
    head = (
        f"VelocityMap {cfg.height}x{cfg.width} cells at {cfg.resolution} m, noise on; "
        f"OccupancyGrid on the same {cfg.height * cfg.width} cells (4 features)\n"
        f"{'scenario':<13}{'vehicles':>9}{'sim steps/s':>13}{'obs ms/agent-frame':>20}"
        f"{'grid ms/agent-frame':>21}{'grid/obs':>10}"
    )
    lines = [head]
    for r in rows:
        lines.append(
            f"{r.scenario:<13}{r.vehicles:>9.1f}{r.sim_steps_per_s:>13.1f}"
            f"{r.obs_ms_per_agent_frame:>20.3f}{r.grid_ms_per_agent_frame:>21.2f}{r.grid_over_obs:>9.0f}x"
        )
    return "\n".join(lines)


def measure_env_throughput(scenario: str, batch_size: int = 64, fast_steps: int = 50, highway_steps: int = 40,
                           obs_cfg: ObservationConfig | None = None, seed: int = 0) -> ThroughputRow:
    """Env steps/s with VelocityMaps: ``make_vec(scenario, batch_size)`` on the fast
    backend against ``make_env(scenario)`` on highway-env, measured one after the other.

    Both are stepped through the environments with random meta-actions, so every step
    renders a stacked observation for every AV that acted, and an ended episode is reset
    (the vector env auto-resets, the single env is reset by the loop) with its first
    observation rendered: resets are inside the timed loop. The first reset (and, for the
    fast batch, one step that compiles or loads the kernels) is not timed.
    """
    obs = (obs_cfg or ObservationConfig()).model_dump()
    rng = np.random.default_rng(seed)
    env = make_env(scenario, backend="highway", observation=obs)
    n_av = env.config.scenario.n_av
    env.reset(seed=seed)
    t0 = time.perf_counter()
    for _ in range(highway_steps):
        _, _, terminated, truncated, _ = env.step(rng.integers(0, 5, n_av))
        if terminated or truncated:
            env.reset()
    highway = highway_steps / (time.perf_counter() - t0)
    env.close()

    vec = make_vec(scenario, batch_size, backend="fast", observation=obs)
    vec.reset(seed=seed)
    vec.step(rng.integers(0, 5, (batch_size, n_av)))
    t0 = time.perf_counter()
    for _ in range(fast_steps):
        vec.step(rng.integers(0, 5, (batch_size, n_av)))
    fast = fast_steps * batch_size / (time.perf_counter() - t0)
    vec.close()
    spec = env.config.scenario
    return ThroughputRow(spec.name, spec.n_av + spec.n_hv, n_av, batch_size, True, highway, fast)


def bench_fast(scenarios: Iterable[str], batch_size: int = 64, steps: int = 50, seed: int = 0,
               obs_cfg: ObservationConfig | None = None, repeat: int = 1,
               progress: Callable[[str], None] | None = None) -> list[ThroughputRow]:
    """Two rows per scenario: the simulation alone (:func:`~latentdrive.sim.validate.measure_throughput`)
    and the environments with VelocityMaps (:func:`measure_env_throughput`), each with
    ``steps`` policy steps of both backends.

    With ``repeat`` > 1 every measurement runs that many times and its row is the run with
    the median speed-up (the lower middle one for an even count), with the speed-ups'
    range: a shared machine's speed varies from run to run, and a ratio of two figures
    taken seconds apart varies less than either figure.
    """
    if repeat < 1:
        raise ValueError(f"repeat must be at least 1, got {repeat}")
    rows = []
    for name in scenarios:
        for maps in (False, True):
            runs = [measure_env_throughput(name, batch_size, steps, steps, obs_cfg, seed) if maps
                    else measure_throughput(name, batch_size, steps, steps, seed) for _ in range(repeat)]
            ratios = sorted(r.speedup for r in runs)
            median = next(r for r in runs if r.speedup == ratios[(len(ratios) - 1) // 2])
            rows.append(replace(median, runs=repeat, speedup_min=ratios[0], speedup_max=ratios[-1]))
            if progress:
                progress(f"  {name}{' with maps' if maps else ''}: {median.speedup:.0f}x (median of {repeat})")
    return rows
