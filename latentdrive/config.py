"""Typed, validated configuration shared by every part of latentdrive.

Every concern has one frozen pydantic model whose fields carry units in their
descriptions. Unknown keys and out-of-range values raise :class:`ConfigError`, a
``ValueError`` whose one-line message names the offending field, so the CLI can print it
without a traceback. The resolved config is saved beside every artifact; its
:func:`config_hash` identifies artifacts made under the same settings.
"""

from __future__ import annotations

import argparse
import hashlib
import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypeVar

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from latentdrive.errors import LatentDriveError
from latentdrive.fileio import MAX_CONFIG_BYTES, read_text

__all__ = [
    "Config",
    "ConfigError",
    "LatentDriveError",
    "NoiseConfig",
    "ObservationConfig",
    "config_hash",
    "dotted_items",
    "load_preset",
    "load_yaml",
    "merge_overrides",
    "nonnegative_int",
    "parse_override_args",
    "positive_int",
    "unit_fraction",
    "validate",
]

C = TypeVar("C", bound="Config")


class ConfigError(LatentDriveError, ValueError):
    """A config value is unknown, malformed or out of range; the message names the field."""


class Config(BaseModel):
    """Base of every config object: immutable, strict about unknown keys."""

    # NaN and infinity are refused by every float field: NaN passes no range check silently.
    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True, allow_inf_nan=False)

    def replace(self: C, **changes: Any) -> C:
        """A validated copy with ``changes`` merged in (nested dicts merge recursively)."""
        return validate(type(self), merge_overrides(self.model_dump(), changes))


def describe_validation_error(exc: ValidationError, prefix: str = "", first: bool = False) -> str:
    """``exc`` as ``loc: message`` parts joined by ``; `` (only the first with ``first``).

    Locations quote keys from the user's file; :class:`ConfigError` escapes any control
    characters they hold, so the message stays on one line.
    """
    parts = []
    for err in exc.errors()[:1] if first else exc.errors():
        loc = ".".join(str(p) for p in err["loc"] if p != "__root__")
        loc = f"{prefix}{loc}" if loc else prefix.rstrip(".") or "config"
        msg = err["msg"].removeprefix("Value error, ")
        if err["type"] == "extra_forbidden":
            msg = "unknown key"
        parts.append(f"{loc}: {msg}")
    return "; ".join(parts)


def validate(model: type[C], data: Mapping[str, Any], prefix: str = "",
             context: Mapping[str, Any] | None = None) -> C:
    """Build ``model`` from ``data``, turning validation failures into :class:`ConfigError`.

    ``data`` usually comes from a file; anything but a mapping is a one-line error too.
    ``context`` reaches the model's validators (e.g. ``specs``: the scenario specs an
    artifact stored, which stand for their names).
    """
    if not isinstance(data, Mapping):
        where = prefix.rstrip(".") or "config"
        raise ConfigError(f"invalid config: {where}: expected a mapping, got {type(data).__name__}")
    try:
        return model.model_validate(dict(data), context=dict(context) if context is not None else None)
    except ValidationError as exc:
        raise ConfigError("invalid config: " + describe_validation_error(exc, prefix)) from None


def dotted_items(settings: Mapping[str, Any], prefix: str = "") -> list[tuple[str, Any]]:
    """Nested settings as ``(dotted name, value)`` pairs in their order: the inverse of the
    dotted keys :func:`merge_overrides` expands."""
    out: list[tuple[str, Any]] = []
    for k, v in settings.items():
        out += dotted_items(v, f"{prefix}{k}.") if isinstance(v, Mapping) else [(f"{prefix}{k}", v)]
    return out


def merge_overrides(base: Mapping[str, Any], overrides: Mapping[str, Any]) -> dict[str, Any]:
    """Recursively merge ``overrides`` into a copy of ``base``.

    Keys may be dotted (``"observation.frames"``) to reach into nested sections.
    """
    out: dict[str, Any] = {k: v for k, v in base.items()}
    for key, value in overrides.items():
        if not isinstance(key, str):  # not a setting's name: validation refuses it in one line
            out[key] = value
            continue
        head, _, rest = key.partition(".")
        if rest:
            value = {rest: value}
        current = out.get(head)
        if isinstance(value, Mapping) and (rest or isinstance(current, Mapping)):
            # A dotted key goes into an empty section too, so that its deeper dots expand
            # (a.b.c); a mapping given whole replaces a missing section as it is, so that
            # keys holding dots of their own (spec file names under specs) stay whole.
            out[head] = merge_overrides(current if isinstance(current, Mapping) else {}, value)
        else:
            out[head] = value
    return out


def nonnegative_int(text: str) -> int:
    """argparse type of a seed or a count that may be 0."""
    value = _int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be 0 or more, got {value}")
    return value


def positive_int(text: str) -> int:
    """argparse type of a count that must be at least 1."""
    value = _int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def unit_fraction(text: str) -> float:
    """argparse type of a share in (0, 1]."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not 0.0 < value <= 1.0:
        raise argparse.ArgumentTypeError(f"must be in (0, 1], got {text}")
    return value


def _int(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None


def parse_override_args(items: list[str]) -> dict[str, Any]:
    """Parse CLI ``key=value`` overrides; values are read as YAML scalars (``3``, ``0.5``, ``[1,2]``)."""
    out: dict[str, Any] = {}
    for item in items:
        key, sep, raw = item.partition("=")
        if not sep or not key:
            raise ConfigError(f"invalid override {item!r}: expected key=value")
        try:
            out[key.strip()] = yaml.safe_load(raw)
        except (yaml.YAMLError, RecursionError):
            raise ConfigError(f"invalid override {item!r}: value is not valid YAML") from None
    return out


def load_yaml(path: str | Path) -> dict[str, Any]:
    """Read a YAML mapping, with a one-line error naming the file when it is not one.

    The file is read with a size bound (:data:`~latentdrive.fileio.MAX_CONFIG_BYTES`); a
    folder, a binary file or YAML nested beyond the parser's limits is refused the same way.
    """
    p = Path(path)
    try:
        text = read_text(p, limit=MAX_CONFIG_BYTES, what="config file", error=ConfigError)
    except FileNotFoundError:
        raise ConfigError(f"{p}: no such config file") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{p}: malformed YAML ({str(exc).splitlines()[0]})") from None
    except RecursionError:
        raise ConfigError(f"{p}: malformed YAML (nested too deeply)") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{p}: expected a mapping at the top level")
    return data


def config_hash(cfg: BaseModel) -> str:
    """A short stable hash of a config's resolved values (key order does not matter)."""
    blob = json.dumps(cfg.model_dump(mode="json"), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


class NoiseConfig(Config):
    """Sensor noise q_D applied to the observed scene before rasterization (paper eq. 8).

    All draws come from a generator seeded per episode, so noisy observations are
    reproducible. Zeros everywhere give the clean observation.
    """

    position_std: float = Field(0.75, ge=0.0, le=10.0, description="Std of the Gaussian jitter added to each other vehicle's x and y position, metres.")
    speed_std: float = Field(1.0, ge=0.0, le=10.0, description="Std of the Gaussian jitter added to each vehicle's Frenet longitudinal speed, m/s.")
    heading_std: float = Field(0.02, ge=0.0, le=1.0, description="Std of the Gaussian jitter added to each other vehicle's heading, radians.")
    miss_prob: float = Field(0.1, ge=0.0, le=1.0, description="Probability that another vehicle is missed (not drawn) in a frame.")


class ObservationConfig(Config):
    """Stacked multi-channel VelocityMap (paper section V-A).

    The grid is ego-centred and aligned with the observer's heading: rows run across the
    road (lateral, left of the observer at row 0), columns along it (longitudinal,
    behind the observer at column 0). In the observer's frame (x ahead, y to its right, as
    world y is to the right of a car heading along +x) cell (i, j) is centred at
    x = -behind + (j + 0.5)·resolution and y = (i + 0.5)·resolution - height·resolution/2.
    Defaults are sized for CPU training: a 32×64 grid of 1.5 m cells sees 48 m across
    and 96 m along the road, 32 m behind and 64 m ahead.
    """

    height: int = Field(32, ge=4, le=512, description="Grid rows (lateral cells).")
    width: int = Field(64, ge=4, le=1024, description="Grid columns (longitudinal cells).")
    resolution: float = Field(1.5, gt=0.05, le=10.0, description="Cell size, metres per cell (square cells).")
    behind: float = Field(32.0, ge=0.0, description="Distance seen behind the observer, metres; the rest of width·resolution is ahead.")
    frames: int = Field(4, ge=1, le=32, description="T: number of stacked frames, most recent last.")
    alpha: float = Field(0.5, gt=0.0, description="α of eq. 13, 1/(m/s): scales |v| inside the log.")
    beta: float = Field(0.30, gt=0.0, description="β of eq. 13, dimensionless: slope of the log decay. With α=0.5 a vehicle 10 m/s faster or slower than the observer maps to 0.52, 40 m/s to 0.10, and beyond ~54 m/s to 0, so a stopped car stays visible to an observer at highway speed.")
    v0: float = Field(2.0, gt=0.0, description="v0 of eq. 13, m/s: below it a vehicle cell is 1. Default 1/α makes the map continuous at v0.")
    max_speed: float = Field(40.0, gt=0.0, description="Absolute speed mapped to 1 in the MV (mission vehicle) channel, m/s.")
    route: float = Field(0.0, ge=0.0, le=1.0, description="Value drawn in the MV channel on the road the observer's route still takes (its current edge and the rest of its planned route, every lane of each edge), under its own footprint. 0, the default, is the paper's map, which does not show where the AV is going; any other value is an option that shows it, as a planner knows it.")
    # model_validate rather than the bare class keeps mypy (without the pydantic plugin)
    # from reading the fields' defaults as required constructor arguments.
    noise: NoiseConfig = Field(
        default_factory=lambda: NoiseConfig.model_validate({}), description="Sensor noise."
    )

    @model_validator(mode="after")
    def _check_extent(self) -> ObservationConfig:
        if self.behind > self.width * self.resolution:
            raise ValueError(
                f"behind={self.behind} m exceeds the grid length width*resolution="
                f"{self.width * self.resolution} m"
            )
        return self

    @property
    def shape(self) -> tuple[int, int, int, int]:
        """Per-agent observation shape ``(4, T, H, W)``."""
        return (4, self.frames, self.height, self.width)


def load_preset(model: type[C], preset: str, presets: Mapping[str, Path],
                overrides: Mapping[str, Any] | None = None) -> C:
    """``model`` from a named preset (a key of ``presets``, which maps names to YAML files)
    or a ``.yaml`` file, with dotted ``overrides`` merged in; one-line errors for the rest."""
    if preset in presets:
        data = load_yaml(presets[preset])
    elif preset.endswith((".yaml", ".yml")):
        data = load_yaml(preset)
    else:
        raise ConfigError(f"unknown preset {preset!r}: choose one of {', '.join(presets)} or a .yaml file")
    return validate(model, merge_overrides(data, overrides or {}))
