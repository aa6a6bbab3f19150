"""The fast backend against highway-env: single trajectories and episode statistics."""

import numpy as np
import pytest

from latentdrive.scenarios import SCENARIOS, get_spec
from latentdrive.sim.fast import FastBackend
from latentdrive.sim.highway import HighwayBackend
from latentdrive.sim.validate import TOLERANCES, fidelity_table, format_fidelity

SLOWER, IDLE, FASTER = 4, 1, 3


def _run_both(spec, seed, script):
    """Max position error per decision of both backends fed the same actions."""
    hw, fast = HighwayBackend(spec), FastBackend(spec)
    a, b = hw.reset(seed), fast.reset(seed)
    errors = [float(np.abs(a.position - b.position).max())]
    for actions in script:
        a, b = hw.step(np.asarray(actions)), fast.step(np.asarray(actions))
        errors.append(float(np.abs(a.position - b.position).max()))
        if a.crashed[a.agents].any() or b.crashed[b.agents].any():
            break
    return np.array(errors), a, b


def test_idm_platoon_on_a_single_lane_matches_within_a_tenth_of_a_metre_over_20_s():
    # One lane: no lane change is possible. The AV leads and changes speed; six HVs follow.
    spec = get_spec(
        "highway", lanes_count=1, n_av=1, n_hv=6, duration=20, min_gap=20,
        av_spawn=[{"edge": ["0", "1"], "lanes": [0], "longitudinal": {"mean": 420.0}, "speed": {"mean": 25.0}}],
        hv_spawn=[{"edge": ["0", "1"], "lanes": [0], "longitudinal": {"mean": 220.0, "std": 60.0, "clip": 160.0},
                   "speed": {"mean": 24.0, "std": 1.5, "clip": 3.0}}],
    )
    script = [[IDLE]] * 5 + [[SLOWER]] * 2 + [[IDLE]] * 6 + [[FASTER]] * 2 + [[IDLE]] * 5
    for seed in (0, 1):
        errors, a, b = _run_both(spec, seed, script)
        assert len(errors) == 21 and a.time == b.time == pytest.approx(20.0)
        assert not a.crashed.any()
        assert errors.max() < 0.1
        assert errors.max() < 1e-6  # in fact the same numbers up to rounding


# A script exercising every meta-action; on single-lane roads lane changes are no-ops.
SCRIPT = [3, 3, 1, 0, 1, 2, 1, 4, 1, 3, 0, 1, 2, 1, 4, 1, 1, 3, 1, 1]


@pytest.mark.parametrize("name", SCENARIOS)
def test_av_script_on_an_empty_road_stays_within_half_a_metre(name):
    spec = get_spec(name, n_av=1, n_hv=0)
    for seed in (0, 1):
        errors, _, _ = _run_both(spec, seed, [[a] for a in SCRIPT[: spec.max_steps]])
        assert errors.max() < 0.5
        assert errors.max() < 1e-6


@pytest.mark.parametrize("name", SCENARIOS)
def test_traffic_with_idle_avs_follows_highway_env(name):
    spec = get_spec(name)
    for seed in (0, 1, 2):
        errors, a, b = _run_both(spec, seed, [[IDLE] * spec.n_av] * spec.max_steps)
        assert errors.max() < 1e-6
        assert np.array_equal(a.crashed, b.crashed) and np.array_equal(a.arrived, b.arrived)


def test_fidelity_table_small_setting():
    rows = fidelity_table(scenarios=("merge", "intersection"), episodes=3)
    assert {(r.scenario, r.policy, r.statistic) for r in rows} == {
        (s, p, k) for s in ("merge", "intersection") for p in ("random", "idle") for k in TOLERANCES}
    assert all(r.ok for r in rows), format_fidelity(rows)
    assert "crash_rate" in format_fidelity(rows)


@pytest.mark.slow
def test_fidelity_table_200_episodes_within_tolerance():
    rows = fidelity_table(episodes=200)
    assert all(r.ok for r in rows), format_fidelity(rows)
