"""The five scenarios of the paper, as data, and the spec type users write their own with."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from functools import cache
from pathlib import Path
from typing import Any

from latentdrive.config import ConfigError, load_yaml, merge_overrides, validate
from latentdrive.scenarios.spec import (
    LAYOUTS,
    ClippedGaussian,
    DriverParams,
    Goal,
    RewardConfig,
    ScenarioError,
    ScenarioSpec,
    SpawnRegion,
)

__all__ = [
    "LAYOUTS",
    "SCENARIOS",
    "ClippedGaussian",
    "DriverParams",
    "Goal",
    "RewardConfig",
    "ScenarioError",
    "ScenarioSpec",
    "SpawnRegion",
    "check_scenario_names",
    "get_spec",
    "resolve_specs",
]

_PRESETS = Path(__file__).parent / "presets"
SCENARIOS: tuple[str, ...] = ("roundabout", "intersection", "merge", "exit", "highway")


@cache
def _preset(name: str) -> dict[str, Any]:
    return load_yaml(_PRESETS / f"{name}.yaml")


def get_spec(scenario: str | ScenarioSpec, **overrides: Any) -> ScenarioSpec:
    """The spec of a named scenario (or a YAML file path), with ``overrides`` applied.

    Raises:
        ConfigError: unknown scenario, or an override that is unknown or out of range.
    """
    if isinstance(scenario, ScenarioSpec):
        base: dict[str, Any] = scenario.model_dump()
    elif scenario in SCENARIOS:
        base = _preset(scenario)
    elif str(scenario).endswith((".yaml", ".yml")):
        base = load_yaml(scenario)
    else:
        raise ConfigError(
            f"unknown scenario {scenario!r}: choose one of {', '.join(SCENARIOS)} or a .yaml spec file"
        )
    return validate(ScenarioSpec, merge_overrides(base, overrides), prefix="scenario.")


def check_scenario_names(names: tuple[str, ...]) -> tuple[str, ...]:
    """``names`` if each is a known scenario (or spec file) and none repeats; for config
    validators. Raises :class:`ConfigError` naming an unknown one, ``ValueError`` a repeat."""
    for name in names:
        get_spec(name)
    if len(set(names)) != len(names):
        raise ValueError(f"scenarios repeat a name: {', '.join(names)}")
    return names


def resolve_specs(names: Sequence[str], stored: Mapping[str, ScenarioSpec] | None = None) -> dict[str, ScenarioSpec]:
    """The spec of each of ``names``: the copy ``stored`` holds for it (what a run, dataset
    or study recorded when it was made), else the preset or spec file the name gives.

    A run folder evaluates and resumes from its stored copies, so it needs neither the spec
    file it was configured with nor today's version of a preset.

    Raises:
        ConfigError: a name is neither stored, nor a preset, nor a readable spec file.
    """
    stored = stored or {}
    return {name: stored[name] if name in stored else get_spec(name) for name in names}
