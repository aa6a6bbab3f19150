"""Branches copy an environment's state exactly and leave the batch alone."""

from __future__ import annotations

import numpy as np
import pytest

from latentdrive.actions import IDLE
from latentdrive.scenarios import SCENARIOS, get_spec
from latentdrive.sim.fast import FastBatch
from latentdrive.sim.fast.branch import Branches
from latentdrive.sim.fast.state import ARRIVED, AV, CRASHED, HV, KIND, ROUTE_HEAD, ROUTE_LEN, X, Y


def _idle_done(batch: FastBatch, actions: np.ndarray) -> np.ndarray:
    # The env drives crashed and arrived AVs Idle; branches do the same by themselves.
    st = batch._groups[0].state
    n = actions.shape[1]
    return np.where(st.flag[CRASHED, :, :n] | st.flag[ARRIVED, :, :n], IDLE, actions)


def _idle_done_all(batch: FastBatch, actions: np.ndarray) -> np.ndarray:
    out = actions.copy()
    for e in range(batch.num_envs):
        scene = batch.scene(e)
        assert scene.arrived is not None
        done = scene.crashed[:2] | scene.arrived[:2]
        out[e] = np.where(done, IDLE, actions[e])
    return out


@pytest.mark.parametrize("name", SCENARIOS)
def test_branches_follow_the_environment_they_copy_exactly(name: str) -> None:
    spec = get_spec(name)
    batch = FastBatch([spec] * 3)
    batch.reset([11, 12, 13])
    rng = np.random.default_rng(0)
    for _ in range(2):
        batch.advance(_idle_done(batch, rng.integers(0, 5, (3, spec.n_av))))
    before = [a.copy() for a in batch._groups[0].state]
    branches = batch.branch([2, 0], copies=2)
    plan = [rng.integers(0, 5, (3, spec.n_av)) for _ in range(4)]
    for acts in plan:  # copies of env 2 get env 2's actions, copies of env 0 env 0's
        branches.advance(np.stack([acts[2], acts[2], acts[0], acts[0]]))
    # Branching and advancing branches changed nothing in the batch.
    for a, b in zip(batch._groups[0].state, before, strict=True):
        np.testing.assert_array_equal(a, b)
    for acts in plan:
        batch.advance(_idle_done(batch, acts))
    speed, crashed, arrived = branches.agents()
    for k, env in enumerate([2, 2, 0, 0]):
        scene = batch.scene(env)
        np.testing.assert_array_equal(speed[k], scene.speed[: spec.n_av])
        np.testing.assert_array_equal(crashed[k], scene.crashed[: spec.n_av])
        assert scene.arrived is not None
        np.testing.assert_array_equal(arrived[k], scene.arrived[: spec.n_av])
    np.testing.assert_array_equal(branches.time(), [batch.scene(e).time for e in (2, 2, 0, 0)])


def test_branches_of_a_mixed_batch_keep_their_order() -> None:
    specs = [get_spec("merge"), get_spec("highway"), get_spec("merge")]
    batch = FastBatch(specs)
    batch.reset([1, 2, 3])
    branches = batch.branch([1, 0], copies=1)
    rng = np.random.default_rng(3)
    for _ in range(3):  # both layouts advance, each with its own environment's actions
        acts = rng.integers(0, 5, (3, 2))
        branches.advance(acts[[1, 0]])
        batch.advance(_idle_done_all(batch, acts))
    speed, crashed, _ = branches.agents()
    for k, env in enumerate([1, 0]):
        np.testing.assert_array_equal(speed[k], batch.scene(env).speed[:2])
        np.testing.assert_array_equal(crashed[k], batch.scene(env).crashed[:2])
    np.testing.assert_array_equal(branches.time(), [batch.scene(1).time, batch.scene(0).time])


def test_bad_branch_requests_are_refused() -> None:
    batch = FastBatch([get_spec("merge")])
    with pytest.raises(RuntimeError, match="reset"):
        batch.branch([0], 2)
    batch.reset([0])
    with pytest.raises(ValueError, match="copies"):
        batch.branch([0], 0)
    with pytest.raises(ValueError, match="actions must be"):
        batch.branch([0], 2).advance(np.zeros((3, 2), dtype=np.int64))
    with pytest.raises(ValueError, match="integers in"):
        batch.branch([0], 1).advance(np.array([[0, 5]]))
    mixed = FastBatch([get_spec("merge"), get_spec("merge", n_av=3)])
    mixed.reset([0, 1])
    with pytest.raises(ValueError, match="AV count"):
        mixed.branch([0, 1], 1)


def _advance_idle(batch: FastBatch, branches: Branches, steps: int) -> None:
    n_av = branches.n_av
    for _ in range(steps):
        acts = np.full((batch.num_envs, n_av), IDLE, dtype=np.int64)
        branches.advance(acts)
        batch.advance(acts)


def test_forgetting_human_routes_empties_only_the_branches_human_routes() -> None:
    spec = get_spec("intersection")
    batch = FastBatch([spec] * 4)
    batch.reset([0, 1, 2, 3])
    st = batch._groups[0].state
    before = [a.copy() for a in st]
    branches = batch.branch([0, 1, 2, 3], copies=1)
    branches.forget_human_routes()
    part = branches._parts[0].state
    human, av = part.i[KIND] == HV, part.i[KIND] == AV
    assert (st.i[ROUTE_LEN][st.i[KIND] == HV] > st.i[ROUTE_HEAD][st.i[KIND] == HV]).any()
    np.testing.assert_array_equal(part.i[ROUTE_LEN][human], part.i[ROUTE_HEAD][human])
    np.testing.assert_array_equal(part.i[ROUTE_LEN][av], st.i[ROUTE_LEN][av])
    for a, b in zip(st, before, strict=True):  # the batch keeps every route
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize(("name", "routes_matter"), [("intersection", True), ("highway", False)])
def test_a_branch_without_human_routes_drives_them_along_the_road(name: str, routes_matter: bool) -> None:
    # Intersection HVs are given turns; without them a branch sends some elsewhere. Highway
    # HVs have no destination, so the branch goes on exactly as the environment does.
    spec = get_spec(name)
    batch = FastBatch([spec] * 4)
    batch.reset([0, 1, 2, 3])
    branches = batch.branch([0, 1, 2, 3], copies=1)
    branches.forget_human_routes()
    _advance_idle(batch, branches, 12)
    st, part = batch._groups[0].state, branches._parts[0].state
    human = (st.i[KIND] == HV) & ~st.flag[CRASHED]
    apart = np.hypot(part.f[X] - st.f[X], part.f[Y] - st.f[Y])[human]
    if routes_matter:
        assert apart.max() > 5.0  # metres: at least one HV took another road
    else:
        np.testing.assert_array_equal(part.f[X], st.f[X])
        np.testing.assert_array_equal(part.f[Y], st.f[Y])
