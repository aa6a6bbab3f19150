"""What one finished episode amounts to: the record evaluation and training logs share."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from latentdrive.scene import Kind, Scene

__all__ = ["FAILURE_CAUSES", "EpisodeOutcome", "failure_cause", "outcomes_from_json", "outcomes_to_json"]

#: Why an episode failed, as :func:`failure_cause` names it; a success's cause is "".
#: "unrecorded" marks failures read from files written before causes were recorded.
FAILURE_CAUSES: tuple[str, ...] = (
    "time-out", "HV ahead", "HV behind", "HV beside", "other AV", "no vehicle", "after arrival", "unrecorded",
)
#: Centre distance (m) within which a crashed vehicle counts as the crashed AV's partner;
#: two cars in contact are at most about one car length and one width apart.
PARTNER_RANGE = 8.0


class EpisodeOutcome(NamedTuple):
    """One finished episode of one environment.

    ``failed`` is the paper's "crashed or failed episode": an AV crashed, or time ran out
    before every AV completed its mission. ``success`` is its complement. A policy that
    always brakes rarely crashes but always fails, so the failure rate is the headline.
    """

    scenario: str
    #: Index of the environment slot in its vector env, and of the episode within that slot.
    env_index: int
    episode_index: int
    #: The episode seed the backend was reset with.
    seed: int
    #: Policy steps the episode lasted.
    steps: int
    #: ``(n_av,)`` bool: which AVs crashed, which completed their mission.
    agent_crashed: NDArray[np.bool_]
    agent_arrived: NDArray[np.bool_]
    #: ``(n_av,)`` undiscounted sum of each AV's rewards.
    agent_return: NDArray[np.float64]
    #: Mean AV speed over the agent-steps in which an AV was acting, m/s.
    mean_speed: float
    #: Human drivers crashed among themselves (or into the road's obstacles) while no AV
    #: had crashed. A wreck can block a lane for good: a failure no AV could avoid.
    traffic_crashed: bool = False
    #: Why it failed (one of :data:`FAILURE_CAUSES`), "" if it succeeded.
    cause: str = ""

    @property
    def crashed(self) -> bool:
        """Any AV crashed."""
        return bool(self.agent_crashed.any())

    @property
    def success(self) -> bool:
        """Every AV completed its mission and none crashed."""
        return bool(self.agent_arrived.all() and not self.agent_crashed.any())

    @property
    def failed(self) -> bool:
        """Crashed, or time ran out before every AV completed its mission."""
        return not self.success

    @property
    def timed_out(self) -> bool:
        """Failed without a crash: the mission was not completed in time."""
        return self.failed and not self.crashed


def failure_cause(scene: Scene, arrived_before: NDArray[np.bool_] | None = None) -> str:
    """Why the episode that ended at ``scene`` failed, or "" if every AV arrived unharmed.

    ``arrived_before``: ``(n_av,)`` the AVs that had completed their mission before the
    last step (default: none had). A crash is described by the first crashed AV (agent
    order) that was still driving, by its partner, the nearest other crashed vehicle within
    :data:`PARTNER_RANGE` m: "other AV", or an HV "ahead", "behind" or "beside", from
    where the HV's centre lies in the AV's frame (ahead or behind when the longitudinal
    offset is more than twice the lateral one). With no partner in range the AV crashed
    alone ("no vehicle": off the road, or into the road's end). Only when every crashed AV
    had arrived before is it "after arrival" (an AV that crashes on the step it arrives
    crashed while driving, as the reward counts it). Without a crash, a
    failure is a "time-out". The geometry is that of the last simulated instant, so "HV
    ahead" covers both running into a car and being cut in on: the label says where the
    other car was, not whose fault it was.
    """
    ag = scene.agents
    arrived = scene.arrived[ag] if scene.arrived is not None else np.zeros(len(ag), dtype=bool)
    crashed = scene.crashed[ag]
    if not crashed.any():
        return "" if arrived.all() else "time-out"
    before = np.zeros(len(ag), dtype=bool) if arrived_before is None else np.asarray(arrived_before, dtype=bool)
    driving = crashed & ~before
    if not driving.any():
        return "after arrival"
    first = int(np.flatnonzero(driving)[0])
    v = int(ag[first])
    offset = scene.position - scene.position[v]  # (N, 2), m
    dist = np.hypot(offset[:, 0], offset[:, 1])
    others = scene.mask & scene.crashed & (np.arange(len(dist)) != v) & (dist <= PARTNER_RANGE)
    if not others.any():
        return "no vehicle"
    j = int(np.flatnonzero(others)[np.argmin(dist[others])])
    if scene.kind[j] == Kind.AV:
        return "other AV"
    c, s = np.cos(scene.heading[v]), np.sin(scene.heading[v])
    lon = offset[j, 0] * c + offset[j, 1] * s
    lat = -offset[j, 0] * s + offset[j, 1] * c
    if abs(lon) > 2.0 * abs(lat):
        return "HV ahead" if lon > 0 else "HV behind"
    return "HV beside"


def outcomes_to_json(outcomes: list[EpisodeOutcome]) -> list[dict[str, object]]:
    """Outcomes as JSON values (arrays as lists), for files a study writes."""
    return [{**o._asdict(), "agent_crashed": o.agent_crashed.tolist(), "agent_arrived": o.agent_arrived.tolist(),
             "agent_return": o.agent_return.tolist(), "mean_speed": float(o.mean_speed)} for o in outcomes]


def outcomes_from_json(items: object) -> list[EpisodeOutcome]:
    """The inverse of :func:`outcomes_to_json`; raises ``ValueError`` naming the first bad entry."""
    if not isinstance(items, list):
        raise ValueError("outcomes: expected a list")
    out: list[EpisodeOutcome] = []
    for i, d in enumerate(items):
        try:
            # Files written before causes were recorded lack "cause".
            if not isinstance(d, dict) or set(d) not in (set(EpisodeOutcome._fields),
                                                          set(EpisodeOutcome._fields) - {"cause"}):
                raise ValueError("wrong fields")
            crashed = np.asarray(d["agent_crashed"], dtype=np.bool_)
            arrived = np.asarray(d["agent_arrived"], dtype=np.bool_)
            ret = np.asarray(d["agent_return"], dtype=np.float64)
            if crashed.ndim != 1 or crashed.shape != arrived.shape or crashed.shape != ret.shape:
                raise ValueError("per-agent arrays differ in shape")
            o = EpisodeOutcome(scenario=str(d["scenario"]), env_index=int(d["env_index"]),
                               episode_index=int(d["episode_index"]), seed=int(d["seed"]), steps=int(d["steps"]),
                               agent_crashed=crashed, agent_arrived=arrived, agent_return=ret,
                               mean_speed=float(d["mean_speed"]), traffic_crashed=bool(d["traffic_crashed"]))
            cause = d.get("cause", "" if o.success else "unrecorded")
            if cause not in (*FAILURE_CAUSES, "") or (cause == "") != o.success:
                raise ValueError(f"cause {cause!r} does not fit the episode's outcome")
            o = o._replace(cause=str(cause))
            if min(o.env_index, o.episode_index, o.seed, o.steps) < 0 or not math.isfinite(o.mean_speed):
                raise ValueError("a negative count or seed, or a speed that is not a number")
            out.append(o)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"outcome {i}: {exc}") from None
    return out
