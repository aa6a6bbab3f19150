import pytest

from latentdrive.config import (
    ConfigError,
    ObservationConfig,
    config_hash,
    merge_overrides,
    parse_override_args,
    validate,
)


def test_unknown_key_names_the_field():
    with pytest.raises(ConfigError, match=r"observation\.bogus: unknown key"):
        validate(ObservationConfig, {"bogus": 1}, prefix="observation.")


def test_out_of_range_names_the_field():
    with pytest.raises(ConfigError, match=r"frames"):
        ObservationConfig().replace(frames=0)
    with pytest.raises(ConfigError, match=r"noise\.miss_prob"):
        ObservationConfig().replace(**{"noise.miss_prob": 1.5})


def test_behind_cannot_exceed_grid():
    with pytest.raises(ConfigError, match="behind"):
        ObservationConfig().replace(behind=1000.0)


def test_error_message_is_one_line():
    with pytest.raises(ConfigError) as exc:
        validate(ObservationConfig, {"height": "tall", "width": -1})
    assert "\n" not in str(exc.value)
    assert "height" in str(exc.value) and "width" in str(exc.value)


def test_dotted_overrides_merge_recursively():
    merged = merge_overrides({"a": {"b": 1, "c": 2}, "d": 3}, {"a.b": 10, "d": 4})
    assert merged == {"a": {"b": 10, "c": 2}, "d": 4}


def test_parse_override_args_reads_yaml_scalars():
    assert parse_override_args(["n_av=3", "x.y=0.5", "l=[1, 2]", "s=abc"]) == {
        "n_av": 3, "x.y": 0.5, "l": [1, 2], "s": "abc"}
    with pytest.raises(ConfigError, match="key=value"):
        parse_override_args(["novalue"])


def test_config_hash_tracks_values_only():
    a, b = ObservationConfig(), ObservationConfig()
    assert config_hash(a) == config_hash(b)
    assert config_hash(a) != config_hash(a.replace(frames=2))


def test_dotted_overrides_three_levels_deep_expand_into_a_missing_section():
    # Regression: the second key used to stay dotted ("planner.depth": unknown key).
    merged = merge_overrides({}, {"imitation.planner.depth": 3, "imitation.planner.rounds": 1})
    assert merged == {"imitation": {"planner": {"depth": 3, "rounds": 1}}}


def test_a_section_given_whole_keeps_keys_with_dots_and_odd_keys_stay_for_validation():
    specs = {"specs": {"runs/my.yaml": {"name": "x"}}}
    assert merge_overrides({}, specs) == specs
    assert merge_overrides({"dqn": {"lr": 1}}, {"dqn": {1: 2}}) == {"dqn": {"lr": 1, 1: 2}}


def test_dotted_items_undo_the_dotted_keys_merge_overrides_expands() -> None:
    from latentdrive.config import dotted_items, merge_overrides

    nested = {"dqn": {"lr": 1e-3, "n_step": 2}, "vfan": {"reader": "objects"}, "seed": 3}
    assert dotted_items(nested) == [("dqn.lr", 1e-3), ("dqn.n_step", 2), ("vfan.reader", "objects"), ("seed", 3)]
    assert merge_overrides({}, dict(dotted_items(nested))) == nested
