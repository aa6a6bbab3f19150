"""``latentdrive bench``: simulation and observation throughput, measured in one run.

For each scenario it steps the backend with random meta-actions (resetting when an
episode ends) and, at every step, times three things on the same instant:

- the simulation step alone (env steps/s),
- our VelocityMap frame for every AV, noise included (ms per agent-frame),
- highway-env's OccupancyGridObservation over the same cells for every AV (ms per
  agent-frame), the reference the VelocityMap is compared with.

Ratios are of figures measured in the same process, seconds apart, on the same scenes.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass

import numpy as np

from latentdrive.config import ObservationConfig
from latentdrive.observe import render_frame
from latentdrive.reward import episode_end
from latentdrive.scenarios import get_spec
from latentdrive.sim.highway import HighwayBackend

__all__ = ["BenchRow", "format_table", "run_bench"]


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
