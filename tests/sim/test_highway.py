import numpy as np
import pytest

from latentdrive.scenarios import SCENARIOS, get_spec
from latentdrive.scene import Kind
from latentdrive.sim.highway import HighwayBackend


@pytest.mark.parametrize("name", SCENARIOS)
def test_reset_places_every_vehicle_apart_and_on_the_road(name):
    spec = get_spec(name, n_av=3)
    backend = HighwayBackend(spec)
    scene = backend.reset(seed=7)
    assert scene.n_vehicles == spec.n_av + spec.n_hv
    assert scene.n_agents == 3
    assert np.all(scene.kind[scene.agents] == Kind.AV)
    assert np.sum(scene.kind == Kind.AV) == 3
    d = np.linalg.norm(scene.position[:, None] - scene.position[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    assert d.min() >= 6.0 - 1e-9
    assert np.all(scene.road.sample(scene.position) == 1)
    assert not scene.crashed.any()
    # Every AV starts on the edge of the spawn region it was assigned to.
    for i, av in enumerate(backend.avs):
        region = spec.av_spawn[i % len(spec.av_spawn)]
        assert av.lane_index[:2] == tuple(region.edge)


@pytest.mark.parametrize("name", SCENARIOS)
def test_several_avs_step(name):
    backend = HighwayBackend(get_spec(name, n_av=3))
    backend.reset(seed=1)
    for _ in range(3):
        scene = backend.step(np.array([1, 3, 4]))
    assert scene.time == pytest.approx(3.0)
    assert scene.n_agents == 3


def test_same_seed_same_scene_other_seed_other_scene():
    backend = HighwayBackend(get_spec("exit"))
    a = backend.reset(seed=3)
    a1 = backend.step(np.array([0, 3]))
    b = backend.reset(seed=3)
    b1 = backend.step(np.array([0, 3]))
    assert a == b and a1 == b1
    c = backend.reset(seed=4)
    assert not np.array_equal(a.position, c.position)


def test_driver_parameters_live_on_instances():
    from highway_env.vehicle.behavior import IDMVehicle

    saved = IDMVehicle.DISTANCE_WANTED
    IDMVehicle.DISTANCE_WANTED = 123.0  # what a foreign reset could leave behind
    try:
        merge = HighwayBackend(get_spec("merge"))
        merge.reset(seed=0)
        inter = HighwayBackend(get_spec("intersection"))
        inter.reset(seed=0)
    finally:
        IDMVehicle.DISTANCE_WANTED = saved
    assert merge.road is not None and inter.road is not None
    hv_merge = [v for v in merge.road.vehicles if v not in merge.avs]
    hv_inter = [v for v in inter.road.vehicles if v not in inter.avs]
    assert {v.DISTANCE_WANTED for v in hv_merge} == {get_spec("merge").driver.distance_wanted}
    assert {v.DISTANCE_WANTED for v in hv_inter} == {7.0}
    assert {v.COMFORT_ACC_MIN for v in hv_inter} == {-3.0}


def test_lane_change_where_there_is_no_lane_is_a_noop():
    backend = HighwayBackend(get_spec("intersection", n_hv=0))
    backend.reset(seed=0)
    lanes = [av.lane_index for av in backend.avs]
    backend.step(np.array([0, 2]))  # Left, Right on single-lane roads
    assert [av.target_lane_index[2] for av in backend.avs] == [idx[2] for idx in lanes]


def test_lane_change_left_moves_one_lane_left():
    spec = get_spec("highway", n_hv=0, n_av=1, av_spawn=[{
        "edge": ["0", "1"], "lanes": [1], "longitudinal": {"mean": 100.0}, "speed": {"mean": 25.0}}])
    backend = HighwayBackend(spec)
    backend.reset(seed=0)
    y0 = backend.avs[0].position[1]
    scene = backend.step(np.array([0]))  # Left
    scene = backend.step(np.array([1]))
    # highway-env lanes are 4 m apart and lane 0 lies at y = 0: left is towards -y.
    assert backend.avs[0].lane_index[2] == 0
    assert scene.position[0, 1] == pytest.approx(y0 - 4.0, abs=0.3)


def test_arrival_is_flagged_on_the_goal_edge():
    # One AV on an empty merge, accelerating: it passes x = 310 m + the goal distance (edge c-d) in time.
    spec = get_spec("merge", n_hv=0, n_av=1, duration=20)
    backend = HighwayBackend(spec)
    scene = backend.reset(seed=0)
    for _ in range(spec.max_steps):
        scene = backend.step(np.array([3]))
        assert scene.arrived is not None
        if scene.arrived[scene.agents].all():
            break
    av = backend.avs[0]
    assert scene.arrived is not None and scene.arrived[scene.agents].all()
    assert av.lane_index[1] == "d" and av.position[0] >= 310.0 + spec.goal.longitudinal


@pytest.mark.parametrize("name", SCENARIOS)
def test_presets_place_their_vehicles_for_every_seed(name):
    backend = HighwayBackend(get_spec(name))
    for seed in range(300):
        backend.reset(seed)
