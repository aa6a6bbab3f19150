import numpy as np
import pytest

from latentdrive.config import ConfigError
from latentdrive.scenarios import SCENARIOS, ClippedGaussian, get_spec


def test_five_scenarios_share_one_spec_type():
    specs = [get_spec(name) for name in SCENARIOS]
    assert [s.name for s in specs] == list(SCENARIOS)
    assert len({type(s) for s in specs}) == 1
    assert {s.layout for s in specs} == set(SCENARIOS)


def test_unknown_scenario_is_a_config_error():
    with pytest.raises(ConfigError, match="unknown scenario 'lake'"):
        get_spec("lake")


@pytest.mark.parametrize("name", SCENARIOS)
def test_too_many_avs_names_the_field(name):
    with pytest.raises(ConfigError, match="n_av"):
        get_spec(name, n_av=64)


def test_policy_frequency_must_divide():
    with pytest.raises(ConfigError, match="policy_frequency"):
        get_spec("merge", simulation_frequency=15, policy_frequency=4)


def test_target_speeds_must_be_even():
    with pytest.raises(ConfigError, match="av_target_speeds"):
        get_spec("merge", av_target_speeds=[10, 20, 50])


def test_yaml_file_spec(tmp_path):
    spec = get_spec("merge")
    path = tmp_path / "mine.yaml"
    import yaml

    path.write_text(yaml.safe_dump({**spec.model_dump(mode="json"), "name": "mine", "n_hv": 1}))
    mine = get_spec(str(path))
    assert mine.name == "mine" and mine.n_hv == 1 and mine.layout == "merge"


def test_clipped_gaussian_stays_in_window_and_is_seeded():
    g = ClippedGaussian(mean=10.0, std=5.0, clip=2.0)
    x = g.sample(np.random.default_rng(0), 10_000)
    assert x.min() >= 8.0 and x.max() <= 12.0
    # Truncation (rejection), not clamping: no pile-up of mass at the bounds.
    assert np.mean(np.isclose(x, 8.0)) < 0.01
    assert np.array_equal(x, g.sample(np.random.default_rng(0), 10_000))


def test_zero_std_is_deterministic():
    g = ClippedGaussian(mean=3.0)
    assert np.all(g.sample(np.random.default_rng(5), 4) == 3.0)
