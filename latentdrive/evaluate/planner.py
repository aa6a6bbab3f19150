"""``plan``: a lookahead reference that drives with the simulator itself.

Not a learned policy: it reads the simulator's state (privileged access a policy never
has) and tries action sequences on copies of it before every decision. It bounds how many
failures are avoidable at all, so a policy's failure rate reads against the planner's,
not against zero.

At each decision, for every environment at once:

1. every AV starts from the plan "Idle for ``depth`` steps";
2. in turn (AV 0, 1, ...; ``rounds`` times), one AV tries every candidate sequence while
   the others keep their current plans. A candidate is an action ``a1`` for ``switch``
   steps followed by ``a2`` until the horizon (5 × 5 = 25 candidates, constant sequences
   included). All candidates of all environments run as branches of one batched
   simulation (:meth:`FastBatch.branch <latentdrive.sim.fast.batch.FastBatch.branch>`);
3. a candidate's score is the team's discounted return under the env's own reward, with
   ``crash_penalty`` added on the step any AV crashes. Nothing counts after the episode
   would have ended (a crash, every AV arrived, or the time limit). After the horizon
   every AV brakes for ``tail`` more steps, and a crash there costs the penalty too: a
   plan should not end where a crash can no longer be avoided. (A braking AV can also
   be rear-ended by a close follower, so the tail errs on the side of caution.) The AV adopts the best
   candidate (the lowest index on ties, so the planner is deterministic);
4. every AV applies the first action of its plan.

The other vehicles follow the simulator's own driver models, each on the route it was
given (so the planner knows which exit or turn every human driver will take);
``human_routes="follow_road"`` takes that knowledge away and lets each human follow the road
in the branches. Same state, same decision: the planner has no random stream.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Literal, NamedTuple

import numpy as np
from numpy.typing import NDArray
from pydantic import Field

from latentdrive.actions import IDLE, N_ACTIONS, SLOWER
from latentdrive.config import Config, ConfigError, parse_override_args, validate
from latentdrive.reward import agent_rewards
from latentdrive.rollout import Policy, PolicyInput
from latentdrive.scenarios import RewardConfig
from latentdrive.sim.fast import FastBatch

__all__ = ["Plan", "PlannerConfig", "candidate_sequences", "plan", "planner_config", "planner_config_from_args",
           "planner_policy"]



class PlannerConfig(Config):
    """Settings of the lookahead planner (``evaluate --policy plan --set planner.KEY=VALUE``)."""

    depth: int = Field(8, ge=1, le=30, description="Decisions looked ahead (the horizon, in policy steps).")
    switch: int = Field(1, ge=1, le=30, description="Steps a candidate holds its first action before its second.")
    rounds: int = Field(2, ge=1, le=4, description="Passes over the AVs, each re-planning one AV given the others' plans.")
    discount: float = Field(0.95, gt=0.0, le=1.0, description="Per-step discount of the planning return.")
    crash_penalty: float = Field(-20.0, le=0.0, description="Added to the planning return on the step any AV crashes.")
    tail: int = Field(2, ge=0, le=10, description="Steps of braking (every AV Decelerates) simulated after the horizon; a crash there is penalized, no reward counts.")
    human_routes: Literal["known", "follow_road"] = Field(
        "known",
        description="What the lookahead assumes about where each human driver goes. known: the "
        "route it was given at spawn (the simulator's truth); follow_road: the road ahead, "
        "taking at each junction the continuation closest to its lane, so the planner no "
        "longer knows which exit or turn a human will take (it still knows every position, "
        "speed and driver parameter).")


def candidate_sequences(depth: int, switch: int) -> NDArray[np.int64]:
    """``(C, depth)`` action sequences: ``a1`` for ``switch`` steps, then ``a2``; C = 25
    (or 5 when ``switch >= depth``, where ``a2`` never plays). Idle-only comes first."""
    order = [IDLE] + [a for a in range(N_ACTIONS) if a != IDLE]
    firsts = np.asarray(order, dtype=np.int64)
    if switch >= depth:
        return np.repeat(firsts[:, None], depth, axis=1)
    a1, a2 = np.meshgrid(firsts, firsts, indexing="ij")
    seq = np.where(np.arange(depth)[None, :] < switch, a1.reshape(-1, 1), a2.reshape(-1, 1))
    return seq.astype(np.int64)


def _scores(sim: FastBatch, env_ids: NDArray[np.int64], plans: NDArray[np.int64], steps_left: NDArray[np.int64],
            cfg: PlannerConfig, reward: RewardConfig) -> NDArray[np.float64]:
    """Planning return of each joint plan. ``plans`` ``(E, C, A, D)``: C joint plans per
    environment; ``steps_left`` ``(E,)`` decisions before the time limit. Returns ``(E, C)``."""
    n_env, n_cand, n_av, depth = plans.shape
    branches = sim.branch(env_ids, n_cand)
    if cfg.human_routes == "follow_road":
        branches.forget_human_routes()
    flat = plans.reshape(n_env * n_cand, n_av, depth)
    left = np.repeat(steps_left, n_cand)
    spec_of = [sim.specs[int(e)] for e in env_ids]
    lo = np.repeat([s.reward_speed_range[0] for s in spec_of], n_cand)[:, None]
    hi = np.repeat([s.reward_speed_range[1] for s in spec_of], n_cand)[:, None]
    _, crashed, arrived = branches.agents()
    alive = ~(crashed.any(axis=1) | arrived.all(axis=1))
    score = np.zeros(n_env * n_cand)
    for t in range(depth):
        alive &= t < left
        if not alive.any():
            break
        branches.advance(flat[:, :, t])
        speed, now_crashed, now_arrived = branches.agents()
        # The speed range differs per scenario: map speeds to [0, 1] first, then reuse the
        # env's reward with the unit range.
        unit = (speed - lo) / (hi - lo)
        r = agent_rewards(unit, now_crashed, now_arrived, crashed, arrived, (0.0, 1.0), reward)
        # An AV that had already crashed or arrived earns nothing, as in the env.
        r = np.where(crashed | arrived, 0.0, r).sum(axis=1)
        r += cfg.crash_penalty * (now_crashed.any(axis=1) & ~crashed.any(axis=1))
        score += np.where(alive, cfg.discount**t * r, 0.0)
        alive &= ~(now_crashed.any(axis=1) | now_arrived.all(axis=1))
        crashed, arrived = now_crashed, now_arrived
    # A plan can end where no action avoids a crash a moment later. Braking after the
    # horizon exposes such ends: a crash there costs the penalty, nothing else counts.
    brake = np.full((n_env * n_cand, n_av), SLOWER, dtype=np.int64)
    for t in range(depth, depth + cfg.tail):
        alive &= t < left
        if not alive.any():
            break
        branches.advance(brake)
        _, now_crashed, now_arrived = branches.agents()
        hit = now_crashed.any(axis=1) & ~crashed.any(axis=1)
        score += np.where(alive & hit, cfg.discount**t * cfg.crash_penalty, 0.0)
        alive &= ~(now_crashed.any(axis=1) | now_arrived.all(axis=1))
        crashed = now_crashed
    return score.reshape(n_env, n_cand)


class Plan(NamedTuple):
    """One decision of the planner for environments ``env_ids``."""

    #: ``(E, n_av)`` the first action of each AV's adopted plan.
    actions: NDArray[np.int64]
    #: ``(E, n_av, N_ACTIONS)`` per AV and first action, the best planning return of a
    #: candidate that starts with it, the other AVs on their plans, as scored in the last
    #: round (what the AV's choice weighed; the adopted action's value is its row's maximum).
    values: NDArray[np.float64]


def plan(sim: FastBatch, env_ids: NDArray[np.int64], steps_left: NDArray[np.int64], n_av: int,
         cfg: PlannerConfig, reward: RewardConfig) -> Plan:
    """The planner's decision, with what each first action was worth, for ``env_ids`` of ``sim``."""
    cands = candidate_sequences(cfg.depth, cfg.switch)
    n_env, n_cand = env_ids.size, cands.shape[0]
    plans = np.full((n_env, n_av, cfg.depth), IDLE, dtype=np.int64)
    values = np.full((n_env, n_av, N_ACTIONS), -np.inf)
    first = [cands[:, 0] == a for a in range(N_ACTIONS)]
    for rnd in range(cfg.rounds):
        for agent in range(n_av):
            joint = np.repeat(plans[:, None], n_cand, axis=1)  # (E, C, A, D)
            joint[:, :, agent, :] = cands[None]
            scores = _scores(sim, env_ids, joint, steps_left, cfg, reward)
            plans[:, agent, :] = cands[np.argmax(scores, axis=1)]
            if rnd == cfg.rounds - 1:  # earlier rounds' values are replaced
                for a, starts in enumerate(first):
                    values[:, agent, a] = scores[:, starts].max(axis=1)
    return Plan(plans[:, :, 0], values)


def planner_policy(cfg: PlannerConfig | None = None, reward: RewardConfig | None = None,
                   record: Callable[[Plan], None] | None = None) -> Policy:
    """The planner as a :data:`~latentdrive.rollout.Policy` (needs the fast backend).
    ``record``, when given, receives every decision's :class:`Plan` (with its values)."""
    config = cfg or PlannerConfig()
    rew = reward or RewardConfig()

    def policy(inp: PolicyInput) -> NDArray[np.int64]:
        sim = inp.simulator
        if not isinstance(sim, FastBatch):
            raise ConfigError("the planner needs the fast backend (it branches the simulation state, "
                              "which highway-env cannot copy cheaply): use --backend fast")
        n_av = inp.active.shape[1]
        env_ids = np.arange(inp.active.shape[0], dtype=np.int64)
        steps_left = np.asarray([sim.specs[e].max_steps - round(s.time * sim.specs[e].policy_frequency)
                                 for e, s in enumerate(inp.scenes)], dtype=np.int64)
        decision = plan(sim, env_ids, steps_left, n_av, config, rew)
        if record is not None:
            record(decision)
        return decision.actions

    return policy


def planner_config_from_args(items: list[str]) -> PlannerConfig:
    """A :class:`PlannerConfig` from CLI ``planner.KEY=VALUE`` items (ConfigError otherwise)."""
    parsed = parse_override_args(items)
    unknown = sorted(k for k in parsed if not k.startswith("planner.") or k == "planner.")
    if unknown:
        raise ConfigError(f"--set {unknown[0]}: expected planner.KEY=VALUE (planner.depth=5)")
    return planner_config({k.removeprefix("planner."): v for k, v in parsed.items()})


def planner_config(overrides: dict[str, Any]) -> PlannerConfig:
    """A :class:`PlannerConfig` from ``KEY=VALUE`` overrides (ConfigError names a bad key)."""
    return validate(PlannerConfig, overrides, prefix="planner.")
