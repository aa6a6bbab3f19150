"""Scenario specs: what to build, as data.

One :class:`ScenarioSpec` type describes every scenario; the five of the paper are YAML
instances of it (``latentdrive/scenarios/presets``), and users can write their own.
Road geometry comes from the named ``layout``; everything else (traffic, randomization of
initial states, mission, timing, driver parameters, reward speed range) is here.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from pydantic import Field, model_validator

from latentdrive.config import Config, ConfigError

__all__ = [
    "LAYOUTS",
    "ClippedGaussian",
    "DriverParams",
    "Goal",
    "RewardConfig",
    "ScenarioError",
    "ScenarioSpec",
    "SpawnRegion",
]

LAYOUTS = ("roundabout", "intersection", "merge", "exit", "highway")
Layout = Literal["roundabout", "intersection", "merge", "exit", "highway"]
Edge = tuple[str, str]


class ScenarioError(ConfigError):
    """A scenario cannot be built as specified (e.g. its vehicles cannot be placed)."""


class ClippedGaussian(Config):
    """A Gaussian truncated to ``[mean - clip, mean + clip]`` (the paper's eq. 15)."""

    mean: float = Field(description="Mean, in the quantity's unit.")
    std: float = Field(0.0, ge=0.0, description="Standard deviation, same unit.")
    clip: float = Field(0.0, ge=0.0, description="Half-width δ of the allowed window, same unit.")

    def sample(self, rng: np.random.Generator, size: int | None = None) -> np.ndarray:
        """Draw by rejection (at most 64 rounds, then clamp), so the density is a truncated Gaussian."""
        n = 1 if size is None else size
        x = self.mean + self.std * rng.standard_normal(n)
        lo, hi = self.mean - self.clip, self.mean + self.clip
        for _ in range(64):
            bad = (x < lo) | (x > hi)
            if not bad.any():
                break
            x[bad] = self.mean + self.std * rng.standard_normal(int(bad.sum()))
        x = np.clip(x, lo, hi)
        return x if size is not None else x[:1]


class SpawnRegion(Config):
    """Where and how vehicles start: one road edge, some of its lanes, random position and speed."""

    edge: Edge = Field(description="Road-network edge (from node, to node) of the layout.")
    lanes: list[int] = Field(min_length=1, description="Lane ids on the edge, drawn uniformly per vehicle.")
    longitudinal: ClippedGaussian = Field(description="Initial Frenet longitudinal position along the lane, metres from its start.")
    speed: ClippedGaussian = Field(description="Initial speed, m/s.")
    destinations: list[str] = Field(default_factory=list, description="Route target nodes, drawn uniformly per vehicle; empty: follow the road.")

    def capacity(self, min_gap: float) -> int:
        """How many vehicles this region can hold at least ``min_gap`` metres apart."""
        return len(self.lanes) * (math.floor(2 * self.longitudinal.clip / min_gap) + 1)


class Goal(Config):
    """The mission: an AV completes it on reaching an edge that ends at a goal node."""

    nodes: list[str] = Field(default_factory=list, description="Goal nodes for AVs without a destination of their own; an AV with a destination must reach that node instead.")
    longitudinal: float = Field(0.0, ge=0.0, description="How far along the goal edge the AV must be, metres.")


class DriverParams(Config):
    """IDM (longitudinal) and MOBIL (lane change) parameters of human drivers.

    Set on every HV instance, never on a class: highway-env's intersection writes some of
    these on the shared IDMVehicle class, which would leak into every later scenario.
    Defaults are highway-env 1.12.1's IDMVehicle values.
    """

    acc_max: float = Field(6.0, gt=0, description="Acceleration limit, m/s².")
    comfort_acc_max: float = Field(3.0, gt=0, description="IDM desired maximum acceleration a, m/s².")
    comfort_acc_min: float = Field(-5.0, lt=0, description="IDM desired deceleration -b, m/s².")
    distance_wanted: float = Field(10.0, gt=0, description="IDM jam distance s0 (front to front, includes a car length), metres.")
    time_wanted: float = Field(1.5, gt=0, description="IDM desired time gap T, seconds.")
    delta_range: tuple[float, float] = Field((3.5, 4.5), description="IDM acceleration exponent δ, drawn uniformly per vehicle.")
    politeness: float = Field(0.0, ge=0, le=1, description="MOBIL politeness factor p.")
    lane_change_min_acc_gain: float = Field(0.2, ge=0, description="MOBIL incentive threshold, m/s².")
    lane_change_max_braking_imposed: float = Field(2.0, ge=0, description="MOBIL safety limit on the new follower's braking, m/s².")
    lane_change_delay: float = Field(1.0, gt=0, description="Time between lane-change decisions, seconds.")


class RewardConfig(Config):
    """One per-agent reward for every scenario.

    r_i = collision·crashed_i (on the step it crashes)
        + speed·clip((v_i − v_lo)/(v_hi − v_lo), 0, 1)   (v_lo, v_hi: the scenario's reward_speed_range)
        + mission·arrived_i (on the step the mission completes, unless the AV also
          crashes on that step: a crash is a failure and is never paid as an arrival).

    Optionally, ``failure`` is paid to every AV still driving when the episode ends as a
    failure (see the field), so that time-outs and a partner's crash reach the learner.

    An AV that completes its mission stops earning (its episode terminated), so the
    mission must be worth more than the speed term it gives up: at discount γ cruising
    forever is worth ``speed / (1 − γ)`` (4.0 at γ = 0.95, the DQN's default), which a
    learner that bootstraps through the time limit would otherwise prefer to arriving.
    The default of 5 keeps arriving the better choice (``train-policy`` refuses a reward
    where it is not).
    """

    collision: float = Field(-1.0, le=0, description="Reward on the step an AV crashes.")
    speed: float = Field(0.2, ge=0, description="Weight of the normalized-speed term, per step.")
    mission: float = Field(5.0, ge=0, description="Reward on the step an AV completes its mission.")
    failure: float = Field(0.0, le=0, description="Reward, on the step an episode ends as a failure (an AV crashed, or time ran out before every AV completed its mission), for each AV still driving: the crashed AV's partner and every AV short of its goal at the time limit. When nonzero those transitions are terminal (no bootstrap): the failure is the end of their episode. 0 (the default) pays nothing and bootstraps them, as cut off.")


class ScenarioSpec(Config):
    """A mixed-autonomy driving scenario."""

    name: str = Field(min_length=1, description="Scenario name, as in `latentdrive scenarios`.")
    layout: Layout = Field(description="Road geometry: one of " + ", ".join(LAYOUTS) + ".")
    lanes_count: int = Field(3, ge=1, le=8, description="Number of through lanes (highway and exit layouts only).")
    duration: float = Field(15.0, gt=0, le=600, description="Episode time limit, seconds.")
    simulation_frequency: int = Field(15, ge=1, le=100, description="Physics steps per second, Hz.")
    policy_frequency: int = Field(1, ge=1, le=100, description="Decisions per second, Hz; must divide simulation_frequency.")
    n_av: int = Field(2, ge=1, le=64, description="Autonomous vehicles driven by the policy (each one an agent).")
    n_hv: int = Field(6, ge=0, le=256, description="Human-driven vehicles (IDM + MOBIL).")
    min_gap: float = Field(8.0, ge=6.0, description="Minimum initial distance between two vehicles on the same lane, metres (any two vehicles start at least 6 m apart).")
    av_spawn: list[SpawnRegion] = Field(min_length=1, description="Regions AVs start in; AV i uses region i mod len.")
    hv_spawn: list[SpawnRegion] = Field(default_factory=list, description="Regions HVs start in; HV i uses region i mod len.")
    av_target_speeds: list[float] = Field(default_factory=lambda: [20.0, 25.0, 30.0], min_length=2, description="Speeds Accelerate/Decelerate step between, m/s, ascending and evenly spaced.")
    reward_speed_range: tuple[float, float] = Field((20.0, 30.0), description="Speeds mapped to 0 and 1 in the reward's speed term, m/s.")
    goal: Goal = Field(default_factory=Goal, description="The AVs' mission.")
    driver: DriverParams = Field(default_factory=DriverParams, description="Human driver model parameters.")

    @model_validator(mode="after")
    def _check(self) -> ScenarioSpec:
        if self.simulation_frequency % self.policy_frequency:
            raise ValueError("policy_frequency must divide simulation_frequency")
        speeds = np.asarray(self.av_target_speeds)
        if np.any(np.diff(speeds) <= 0) or not np.allclose(np.diff(speeds), speeds[1] - speeds[0]):
            raise ValueError("av_target_speeds must be ascending and evenly spaced")
        lo, hi = self.reward_speed_range
        if hi <= lo:
            raise ValueError("reward_speed_range must be (low, high) with low < high")
        if self.n_hv and not self.hv_spawn:
            raise ValueError("n_hv > 0 needs at least one hv_spawn region")
        self._check_capacity("n_av", self.n_av, self.av_spawn)
        self._check_capacity("n_hv", self.n_hv, self.hv_spawn)
        return self

    def _check_capacity(self, field: str, n: int, regions: list[SpawnRegion]) -> None:
        counts = np.bincount(np.arange(n) % max(len(regions), 1), minlength=len(regions))
        for i, (count, region) in enumerate(zip(counts, regions, strict=True)):
            cap = region.capacity(self.min_gap)
            if count > cap:
                raise ValueError(
                    f"{field}={n} is more than scenario {self.name!r} can place: "
                    f"{'av' if field == 'n_av' else 'hv'}_spawn[{i}] on edge {region.edge} "
                    f"holds at most {cap} vehicles {self.min_gap} m apart"
                )

    @property
    def steps_per_action(self) -> int:
        """Physics steps per policy decision."""
        return self.simulation_frequency // self.policy_frequency

    @property
    def max_steps(self) -> int:
        """Policy steps before the episode is truncated."""
        return math.ceil(self.duration * self.policy_frequency)
