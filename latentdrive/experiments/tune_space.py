"""The search space of ``latentdrive tune``: train-policy settings and their distributions.

A space file (YAML) has two sections::

    base:                        # train-policy settings every trial starts from (optional)
      mode: raw
    space:                       # dotted PolicyTrainConfig keys, one distribution each
      dqn.lr: {type: float, low: 1.0e-4, high: 3.0e-3, log: true}
      dqn.target_update: {type: int, low: 50, high: 2000, log: true}
      dqn.double: {type: categorical, choices: [true, false]}

Every key is checked against :class:`~latentdrive.rl.config.PolicyTrainConfig` before a
trial runs: it must name a setting (not a section) of the type its distribution draws, and
every extreme value (``low``, ``high``, each choice) must make a valid config on the base,
so that a bad space is a one-line error naming its key, not a failed trial hours later.
"""

from __future__ import annotations

import hashlib
import json
import types
import typing
from pathlib import Path
from typing import Annotated, Any, Literal, Union

from pydantic import BaseModel, Field, model_validator

from latentdrive.config import Config, ConfigError, load_preset, merge_overrides, validate
from latentdrive.experiments.graph import keyed_config
from latentdrive.rl.config import PolicyTrainConfig, check_mission_pays
from latentdrive.scenarios import SCENARIOS

__all__ = ["FIXED_KEYS", "PRESETS", "TUNE_BASE", "CategoricalDist", "FloatDist", "IntDist", "TuneSpace",
           "base_config", "check_space", "load_space", "search_hash", "trial_config"]

PRESETS_DIR = Path(__file__).parent / "presets"
#: Named space presets: ``tune-<name>.yaml`` beside the study presets.
PRESETS = ("raw", "raw-short")
#: Settings a search fixes itself: the seed comes from ``--seeds``, the budget from
#: ``--steps``, and trials are scored on validation episodes only.
FIXED_KEYS = ("seed", "steps", "eval_seeds")
#: What every search starts from, under the space's ``base`` and the command's flags: the
#: mixed scenarios in raw mode, periodic evaluations on validation episodes.
TUNE_BASE: dict[str, Any] = {"mode": "raw", "scenarios": list(SCENARIOS), "eval_seeds": "validation"}

Scalar = Union[None, bool, int, float, str]  # noqa: UP007 (pydantic reads the union at runtime)


class FloatDist(Config):
    """A float drawn uniformly from [low, high], or log-uniformly with ``log``."""

    type: Literal["float"] = Field(description="Distribution kind.")
    low: float = Field(description="Smallest value, in the setting's own unit.")
    high: float = Field(description="Largest value, in the setting's own unit.")
    log: bool = Field(False, description="Draw log-uniformly (low must be above 0).")

    @model_validator(mode="after")
    def _check(self) -> FloatDist:
        if self.low >= self.high:
            raise ValueError(f"low ({self.low:g}) must be below high ({self.high:g})")
        if self.log and self.low <= 0:
            raise ValueError(f"log needs low above 0, got {self.low:g}")
        return self

    def extremes(self) -> list[Any]:
        return [self.low, self.high]


class IntDist(Config):
    """An integer drawn uniformly from {low, low + step, ..., high}, or log-uniformly with ``log``."""

    type: Literal["int"] = Field(description="Distribution kind.")
    low: int = Field(description="Smallest value.")
    high: int = Field(description="Largest value.")
    step: int = Field(1, ge=1, description="Spacing of the values (1 with log).")
    log: bool = Field(False, description="Draw log-uniformly (low must be at least 1).")

    @model_validator(mode="after")
    def _check(self) -> IntDist:
        if self.low >= self.high:
            raise ValueError(f"low ({self.low}) must be below high ({self.high})")
        if self.log and (self.low < 1 or self.step != 1):
            raise ValueError("log needs low at least 1 and step 1")
        return self

    def extremes(self) -> list[Any]:
        return [self.low, self.high]


class CategoricalDist(Config):
    """One of a list of values."""

    type: Literal["categorical"] = Field(description="Distribution kind.")
    choices: tuple[Scalar, ...] = Field(min_length=1, description="The values, each a number, a string, true/false or null.")

    def extremes(self) -> list[Any]:
        return list(self.choices)


Distribution = Annotated[FloatDist | IntDist | CategoricalDist, Field(discriminator="type")]


class TuneSpace(Config):
    """A search space file: the base settings and the distributions of the searched ones."""

    base: dict[str, Any] = Field(default_factory=dict, description="train-policy settings (dotted keys allowed) every trial starts from, under the command's --steps and --set.")
    space: dict[str, Distribution] = Field(min_length=1, description="Dotted PolicyTrainConfig key (dqn.lr) -> its distribution.")


def load_space(preset: str) -> TuneSpace:
    """A named space preset (:data:`PRESETS`) or a ``.yaml`` file; one-line errors otherwise."""
    return load_preset(TuneSpace, preset, {p: PRESETS_DIR / f"tune-{p}.yaml" for p in PRESETS})


def base_config(space: TuneSpace, steps: int | None, overrides: dict[str, Any]) -> PolicyTrainConfig:
    """The config every trial starts from: :data:`TUNE_BASE`, the space's ``base``, ``steps``
    and the command's ``--set`` overrides, in that order."""
    for where, data in (("base", space.base), ("--set", overrides)):
        for key in data:
            if key.split(".")[0] in FIXED_KEYS and key != "steps":
                raise ConfigError(f"{where}: {key} is set by the search itself (seeds: --seeds; "
                                  "periodic evaluations: validation episodes)")
    data = merge_overrides(merge_overrides(TUNE_BASE, space.base), overrides)
    if steps is not None:
        data["steps"] = steps
    return validate(PolicyTrainConfig, data)


def _leaf_type(key: str) -> Any:
    """The annotation of the setting ``key`` names; ConfigError if it names none."""
    model: Any = PolicyTrainConfig
    for i, part in enumerate(key.split(".")):
        fields = model.model_fields if isinstance(model, type) and issubclass(model, BaseModel) else {}
        if part not in fields:
            where = ".".join(key.split(".")[:i]) or "train-policy"
            raise ConfigError(f"space: {key}: {where} has no setting {part!r}")
        model = fields[part].annotation
    if isinstance(model, type) and issubclass(model, BaseModel):
        raise ConfigError(f"space: {key}: a section, not a setting; name one of its keys ({key}.KEY)")
    return model


def _types_of(annotation: Any) -> set[Any]:
    if typing.get_origin(annotation) in (Union, types.UnionType):
        return {t for a in typing.get_args(annotation) for t in _types_of(a)}
    return {annotation}


def check_space(space: TuneSpace, base: PolicyTrainConfig) -> None:
    """Refuse a space whose key names no setting, draws the wrong type, or whose extreme
    values make an invalid config on ``base`` (out of range, a reward under which arriving
    never pays). Raises ConfigError naming the key."""
    for key, dist in space.space.items():
        if key.split(".")[0] in FIXED_KEYS:
            raise ConfigError(f"space: {key}: set by the search itself, not searched")
        kinds = _types_of(_leaf_type(key))
        want = {"float": float, "int": int}.get(dist.type)
        if want is not None and want not in kinds:
            raise ConfigError(f"space: {key}: a {dist.type} distribution for a setting of type "
                              f"{' | '.join(sorted(getattr(t, '__name__', str(t)) for t in kinds))}")
        for value in dist.extremes():
            try:
                check_mission_pays(validate(PolicyTrainConfig, merge_overrides(base.model_dump(), {key: value})))
            except ConfigError as exc:
                raise ConfigError(f"space: {key}: value {value!r}: {exc}") from None


def trial_config(base: PolicyTrainConfig, params: dict[str, Any], seed: int) -> PolicyTrainConfig:
    """The config of one trial's training run: ``base`` with the drawn ``params`` and ``seed``."""
    cfg = validate(PolicyTrainConfig, merge_overrides(base.model_dump(), {**params, "seed": seed}))
    check_mission_pays(cfg)
    return cfg


def search_hash(space: TuneSpace, base: PolicyTrainConfig, seeds: int) -> str:
    """What a study's trial values depend on: the space, the base config and the seed count.

    Settings added after a search was started stay out of the hash at their old behaviour
    (:data:`~latentdrive.experiments.graph.LATER_SETTINGS`), so that search resumes."""
    blob = json.dumps({"space": {k: d.model_dump(mode="json") for k, d in space.space.items()},
                       "base": keyed_config(base.model_dump(mode="json")), "seeds": seeds},
                      sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(blob.encode()).hexdigest()[:16]
