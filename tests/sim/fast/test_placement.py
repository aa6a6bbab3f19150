import numpy as np
import pytest

from latentdrive.scenarios import SCENARIOS, ClippedGaussian, ScenarioError, get_spec
from latentdrive.sim.fast import FastBackend
from latentdrive.sim.fast.network import get_network
from latentdrive.sim.fast.placement import (
    PlacementPlan,
    draw_clipped,
    draw_index,
    draw_uniform,
    place_vehicles,
)
from latentdrive.sim.highway import HighwayBackend


@pytest.mark.parametrize("g", [ClippedGaussian(mean=5.0, std=2.0, clip=1.0),
                               ClippedGaussian(mean=0.0, std=3.0, clip=0.1),
                               ClippedGaussian(mean=7.0)])
def test_scalar_draws_reproduce_numpy_draws(g):
    for seed in range(300):
        a, b = np.random.default_rng(seed), np.random.default_rng(seed)
        for n in (1, 2, 3, 1, 4):
            assert draw_clipped(g, a) == float(g.sample(b)[0])
            assert draw_index(n, a) == int(b.choice(list(range(n))))
            assert draw_uniform(3.5, 4.5, a) == float(b.uniform(3.5, 4.5))
        assert a.standard_normal() == b.standard_normal()  # same generator state after


@pytest.mark.parametrize("name", SCENARIOS)
def test_reset_scene_equals_highway_backend(name):
    spec = get_spec(name, n_av=3)
    hw, fast = HighwayBackend(spec), FastBackend(spec)
    for seed in (0, 7, 123):
        assert fast.reset(seed) == hw.reset(seed)
        assert hw.road is not None
        assert fast.lane_keys() == [v.lane_index for v in hw.road.vehicles]


def test_placement_is_a_pure_function_of_the_generator():
    spec, net = get_spec("roundabout"), get_network("roundabout", 3)
    a = place_vehicles(spec, net, np.random.default_rng(5))
    b = PlacementPlan(spec, net).place(np.random.default_rng(5))
    assert a.lane_keys == b.lane_keys and np.array_equal(a.x, b.x) and a.destination == b.destination
    c = place_vehicles(spec, net, np.random.default_rng(6))
    assert not np.array_equal(a.x, c.x)
    d = np.hypot(a.x[:, None] - a.x[None], a.y[:, None] - a.y[None])
    np.fill_diagonal(d, np.inf)
    assert d.min() >= 6.0


@pytest.mark.parametrize("backend", [HighwayBackend, FastBackend])
@pytest.mark.parametrize(
    ("region", "needle"),
    [
        ({"edge": ["a", "zz"]}, r"edge \('a', 'zz'\) is not in the merge layout"),
        ({"lanes": [5]}, r"has lanes 0..1, not \[5\]"),
        ({"lanes": [-1]}, r"has lanes 0..1, not \[-1\]"),
        ({"longitudinal": {"mean": 220.0, "clip": 20.0}}, r"window \[200, 240\] m leaves edge"),
    ],
)
def test_both_backends_name_a_bad_spawn_region(backend, region, needle):
    base = get_spec("merge").av_spawn[0].model_dump()
    with pytest.raises(ScenarioError, match=needle) as exc:
        backend(get_spec("merge", av_spawn=[{**base, **region}]))
    assert "av_spawn[0]" in str(exc.value)
