"""highway-env's roads as both backends build them, and their rasters."""

import numpy as np
import pytest
from highway_env.envs.highway_env import HighwayEnv

from latentdrive.scenarios import SCENARIOS, get_spec
from latentdrive.sim.fast.network import get_network
from latentdrive.sim.roads import build_road, layout_edges, layout_raster


def test_road_is_the_one_highway_envs_own_env_builds():
    env = HighwayEnv(config={"lanes_count": 3})
    env.reset(seed=0)
    ours = build_road("highway", 3, np.random.default_rng(0)).network
    assert list(ours.lanes_dict()) == list(env.unwrapped.road.network.lanes_dict())
    for key, lane in ours.lanes_dict().items():
        ref = env.unwrapped.road.network.get_lane(key)
        assert type(lane) is type(ref) and lane.length == ref.length
        assert lane.position(10.0, 1.0).tolist() == ref.position(10.0, 1.0).tolist()


def test_merge_raster_literal_geometry():
    raster = layout_raster("merge", 3)
    pts = np.array([
        [100.0, 0.0],    # lane 0 centre
        [100.0, 2.0],    # boundary between lanes 0 and 1
        [100.0, 4.0],    # lane 1 centre
        [100.0, 9.5],    # grass between the highway (y <= 6) and the ramp (12.5..16.5)
        [100.0, 14.5],   # ramp centre
        [100.0, -4.0],   # left of the highway
        [600.0, 0.0],    # beyond the road's end (460 m)
    ])
    assert raster.sample(pts).tolist() == [1, 1, 1, 0, 1, 0, 0]


def test_raster_is_cached_and_read_only():
    a = layout_raster("roundabout", 3)
    assert a is layout_raster("roundabout", 3)
    with pytest.raises(ValueError):
        a.mask[0, 0] = 1


def test_merge_raster_edges_literal():
    raster = layout_raster("merge", 3)
    ids = layout_edges("merge", 3)
    pts = np.array([[100.0, 0.0], [100.0, 4.0], [100.0, 9.5], [100.0, 14.5], [600.0, 0.0]])
    main, ramp = 1 << ids[("a", "b")], 1 << ids[("j", "k")]
    assert raster.sample_edges(pts).tolist() == [main, main, 0, ramp, 0]


@pytest.mark.parametrize("name", SCENARIOS)
def test_edge_bits_cover_the_road_in_the_fast_networks_edge_order(name):
    spec = get_spec(name)
    raster = layout_raster(spec.layout, spec.lanes_count)
    assert list(layout_edges(spec.layout, spec.lanes_count)) == list(get_network(spec.layout, spec.lanes_count).edge_keys)
    assert raster.edges is not None and raster.edges.shape == raster.mask.shape
    np.testing.assert_array_equal(raster.edges != 0, raster.mask == 1)
    with pytest.raises(ValueError):
        raster.edges[0, 0] = 1
