"""Collection runs on the shared episode loop (:func:`latentdrive.rollout.rollout`) and
records exactly what a plain single-env loop records."""

from __future__ import annotations

import numpy as np
import pytest

from latentdrive.data.collect import (
    CollectConfig,
    WorkUnit,
    _rollout_unit,
    episode_seeds,
    plan_units,
    resolve_env_configs,
)
from latentdrive.data.policies import episode_policy
from latentdrive.data.shards import quantize
from latentdrive.env import DrivingEnv, EnvConfig
from latentdrive.rollout import rollout, scene_policy
from latentdrive.vec import DrivingVecEnv

from .conftest import tiny_config


def reference_unit(cfg: CollectConfig, env_cfg: EnvConfig, unit: WorkUnit
                   ) -> tuple[dict[str, np.ndarray], list[int], list[str], list[tuple[int, bool]]]:
    """A unit collected with a plain ``DrivingEnv`` loop: reset with the episode's seed, record
    the observation after ``step`` policy steps (reset = step 0, final one included) when
    ``step % sample_every == 0``, step until the episode ends.

    Also returns each episode's ``(steps, terminated)``."""
    env = DrivingEnv(config=env_cfg)
    n_av = env_cfg.scenario.n_av
    rows: dict[str, list[np.ndarray]] = {k: [] for k in ("noisy", "clean", "episode", "seed", "step")}
    counts, policies, ends = [], [], []
    for e in range(unit.first_local, unit.first_local + unit.episodes):
        env_seed, rng = episode_seeds(cfg.seed, unit.scenario_name, e)
        name, policy = episode_policy(cfg.behaviour, rng, rule_fraction=cfg.rule_fraction,
                                      cruise_speeds=env_cfg.scenario.av_target_speeds)
        obs, info = env.reset(seed=env_seed)
        step, done, terminated, recorded = 0, False, False, 0
        while True:
            if step % cfg.sample_every == 0:
                rows["noisy"].append(quantize(obs))
                rows["clean"].append(quantize(info["clean_observation"]))
                for key, value in (("episode", unit.scenario * cfg.episodes + e), ("seed", env_seed), ("step", step)):
                    rows[key].append(np.full(n_av, value, dtype=np.int64))
                recorded += n_av
            if done:
                break
            obs, _, terminated, truncated, info = env.step(policy(info["scene"], rng))
            step += 1
            done = terminated or truncated
        counts.append(recorded)
        policies.append(name)
        ends.append((step, terminated))
    arrays = {k: np.concatenate(v) for k, v in rows.items()}
    arrays["scenario"] = np.full(sum(counts), unit.scenario, dtype=np.int64)
    arrays["agent"] = np.tile(np.arange(n_av, dtype=np.int64), sum(counts) // n_av)
    return arrays, counts, policies, ends


@pytest.mark.parametrize(("backend", "sample_every", "behaviour", "duration"), [
    ("highway", 1, "mixed", 4),
    ("highway", 2, "random", 4),
    # Long enough for random driving to crash: episodes end early, some on a recorded step.
    ("fast", 2, "random", 20),
])
def test_rollout_unit_matches_a_plain_single_env_loop(backend: str, sample_every: int, behaviour: str,
                                                      duration: int) -> None:
    cfg = tiny_config(episodes=4, sample_every=sample_every, behaviour=behaviour, seed=4,
                      env={"observation": {"height": 16, "width": 32, "frames": 2}, "duration": duration,
                           "backend": backend})
    env_cfgs = resolve_env_configs(cfg)
    ends = []
    for unit in plan_units(cfg, env_cfgs):
        env_cfg = env_cfgs[unit.scenario]
        got, got_counts, got_policies = _rollout_unit(cfg, env_cfg, unit)
        want, want_counts, want_policies, unit_ends = reference_unit(cfg, env_cfg, unit)
        assert (got_counts, got_policies) == (want_counts, want_policies), unit.name
        assert set(got) == set(want), unit.name
        for key in want:
            assert got[key].dtype == want[key].dtype, (unit.name, key)
            assert np.array_equal(got[key], want[key]), (unit.name, key)
        ends += unit_ends
    # The final observation is recorded in some episodes (and, with sparse sampling, not in others).
    assert any(steps % sample_every == 0 for steps, _ in ends)
    if sample_every > 1 and duration > 4:
        assert any(steps % sample_every != 0 for steps, _ in ends)
        assert any(terminated for _, terminated in ends)


def test_step_records_carry_clean_observations_only_when_the_env_makes_them() -> None:
    env_cfg = resolve_env_configs(tiny_config())[0]
    spec, obs_cfg = env_cfg.scenario, env_cfg.observation
    rng = np.random.default_rng(0)
    _, policy = episode_policy("random", rng)
    single = DrivingEnv(config=env_cfg)
    obs, info = single.reset(seed=5)
    for rec in rollout(DrivingVecEnv([spec], backend=env_cfg.backend, observation=obs_cfg, clean_observation=True),
                       scene_policy(policy, np.random.default_rng(1)), seed=5):
        assert rec.clean_obs is not None and rec.clean_next_obs is not None
        assert np.array_equal(rec.obs[0], obs)
        assert np.array_equal(rec.clean_obs[0], info["clean_observation"])
        obs, _, terminated, truncated, info = single.step(rec.actions[0])
        assert np.array_equal(rec.next_obs[0], obs)
        assert np.array_equal(rec.clean_next_obs[0], info["clean_observation"])
        if rec.ended[0]:
            assert terminated or truncated
            break
    plain = DrivingVecEnv([spec], backend=env_cfg.backend, observation=obs_cfg)
    rec = next(rollout(plain, scene_policy(policy, rng), seed=5))
    assert rec.clean_obs is None and rec.clean_next_obs is None


def test_an_hv_crashing_on_the_step_an_av_crashes_is_no_traffic_wreck() -> None:
    from latentdrive.env import AgentStep
    from latentdrive.rollout import _Tally

    tally = _Tally(num_envs=2, n_av=2)
    agents = AgentStep(np.zeros((2, 2)), np.ones((2, 2), bool), np.zeros((2, 2), bool),
                       np.zeros((2, 2), bool), np.ones((2, 2), bool))
    crashed = np.array([[True, False], [False, False]])
    tally.add(agents, np.zeros((2, 2)), crashed, np.zeros((2, 2), bool), np.array([True, True]))
    assert not tally.close(0, "s", 0, "HV ahead").traffic_crashed  # the HV hit the AV
    assert tally.close(1, "s", 0, "time-out").traffic_crashed  # the HVs hit each other
