"""A BNN study's report: its Markdown (:func:`format_report`), and reading back what the
study wrote, its report and its runs' metrics, checked.

``latentdrive figures bnn DIR`` redraws figures from files that may have been edited,
truncated or copied from elsewhere. Everything the figures and the Markdown report use is
checked here first, so that such a file is one line naming it, before any figure is
redrawn, rather than a traceback halfway through.
"""

from __future__ import annotations

import csv
import io
import math
from pathlib import Path
from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from latentdrive.bnn.vehicles import REACH_CELLS
from latentdrive.config import ConfigError, describe_validation_error
from latentdrive.fileio import MAX_JSON_BYTES, confined, read_json, read_text

__all__ = ["MAX_METRICS_BYTES", "epoch_rows", "fmt_value", "format_report", "read_report"]

#: Largest metrics.csv read (a row every few optimizer steps: a long run's is a few MiB).
MAX_METRICS_BYTES = 256 << 20

_EPOCH_FLOATS = ("recon", "val_loss")
_OPTIONAL_FLOATS = ("val_vehicle_recall",)


#: Shares by distance in cells (``{"1": 0.3, "2": 0.5, ...}``): the report's "where the drawn
#: vehicle cells lie" (absent from reports written before it was measured).
_Reach = dict[str, Annotated[float, Field(ge=0.0, le=1.0)] | None]


def _square(names: list[str], matrix: list[list[float]], what: str) -> None:
    n = len(names)
    if len(matrix) != n or any(len(row) != n for row in matrix):
        raise ValueError(f"{what} must be {n}×{n}, one row and column per scenario")


class _InputVehicles(BaseModel):
    model_config = ConfigDict(extra="allow")

    vehicle_recall: float | None = None
    vehicle_precision: float | None = None
    by_scenario: dict[str, float | None] | None = None
    drawn_cells_within: _Reach | None = None


class _Run(BaseModel):
    model_config = ConfigDict(extra="allow", populate_by_name=True)

    latent_dim: int = Field(ge=1)
    lambda_: float = Field(alias="lambda", ge=0.0)
    val_recon: float | None
    mean_between_scenario_distance: float | None
    latent_scenarios: list[str]
    latent_distance: list[list[float]]
    vehicle_recall: float | None = None
    drawn_cells_within: _Reach | None = None

    @model_validator(mode="after")
    def _shapes(self) -> _Run:
        _square(self.latent_scenarios, self.latent_distance, "latent_distance")
        return self


class _Report(BaseModel):
    model_config = ConfigDict(extra="allow")

    dataset_samples: int = Field(ge=0)
    held_out_samples: int = Field(ge=0)
    scored_samples: int | None = Field(None, ge=1)
    raw_scenarios: list[str]
    raw_distance: list[list[float]]
    raw_mean_between_scenario_distance: float | None
    noisy_input_vehicles: _InputVehicles | None = None
    every_cell_within: _Reach | None = None
    runs: dict[str, _Run] = Field(min_length=1)

    @model_validator(mode="after")
    def _shapes(self) -> _Report:
        _square(self.raw_scenarios, self.raw_distance, "raw_distance")
        if not any(r.lambda_ == 0 for r in self.runs.values()):
            raise ValueError("no run with lambda 0")
        return self


def read_report(out: Path) -> dict[str, Any]:
    """``out/report.json`` checked: every field the figures and tables use, with its type.

    Run names are folders under ``out/runs``, so each must be a path inside it. Raises
    :class:`ConfigError` naming the file and the first problem; a missing report raises
    ``FileNotFoundError``.
    """
    path = out / "report.json"
    data = read_json(path, limit=MAX_JSON_BYTES, what="study report", error=ConfigError)
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: not a BNN study report (a JSON {type(data).__name__}, not an object)")
    try:
        report = _Report.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(f"{path}: not a BNN study report ({describe_validation_error(exc, first=True)})") from None
    for name in report.runs:
        confined(out / "runs", name, source=path, error=ConfigError)
    return report.model_dump(by_alias=True)


def epoch_rows(run_dir: Path) -> list[dict[str, str]]:
    """The per-epoch rows of a run's ``metrics.csv``, each with a numeric ``epoch``,
    ``recon`` and ``val_loss`` (NaN allowed); :class:`ConfigError` naming the file otherwise."""
    path = run_dir / "metrics.csv"
    try:
        text = read_text(path, limit=MAX_METRICS_BYTES, what="metrics file", error=ConfigError)
    except FileNotFoundError:
        raise ConfigError(f"{path}: missing; the run's training log is needed for its loss curve") from None
    reader = csv.DictReader(io.StringIO(text, newline=""))
    needed = {"kind", "epoch", *_EPOCH_FLOATS}
    if not needed <= set(reader.fieldnames or ()):
        raise ConfigError(f"{path}: not a BNN training log (no {', '.join(sorted(needed))} columns)")
    rows = []
    try:
        for row in reader:
            if row["kind"] == "epoch":
                _check_epoch_row(row)
                rows.append(row)
    except (csv.Error, TypeError, ValueError):
        raise ConfigError(f"{path}: line {reader.line_num} is not a valid epoch row") from None
    return rows


def _check_epoch_row(row: dict[str, str]) -> None:
    if int(row["epoch"]) < 0:
        raise ValueError("negative epoch")
    for key in _EPOCH_FLOATS:
        float(row[key])  # any float, NaN included
    for key in _OPTIONAL_FLOATS:
        if row.get(key):
            float(row[key])


def fmt_value(v: float | None, spec: str) -> str:
    return "–" if v is None or not math.isfinite(v) else format(v, spec)


def _matrix_md(names: list[str], m: list[list[float]]) -> str:
    lines = ["| | " + " | ".join(names) + " |", "|---" * (len(names) + 1) + "|"]
    lines += [f"| {n} | " + " | ".join(f"{v:.3f}" for v in row) + " |" for n, row in zip(names, m, strict=True)]
    return "\n".join(lines)


def _recall_table(report: dict[str, Any]) -> list[str]:
    """Vehicles recovered per scenario and run (Markdown), when the report has them."""
    rows = {n: r.get("vehicle_recall_by_scenario") for n, r in report["runs"].items()}
    ref = (report.get("noisy_input_vehicles") or {}).get("by_scenario")
    if ref:
        rows = {"noisy input (reference)": ref, **rows}
    rows = {n: r for n, r in rows.items() if r}
    if not rows:
        return []
    scen = list(next(iter(rows.values())))
    lines = ["", "## Held-out vehicles recovered, per scenario", "",
             "| run | " + " | ".join(scen) + " |", "|---" * (len(scen) + 1) + "|"]
    lines += [f"| {n} | " + " | ".join(fmt_value(r.get(s), ".1%") for s in scen) + " |" for n, r in rows.items()]
    return lines


def _reach_table(report: dict[str, Any]) -> list[str]:
    """Where each run's drawn vehicle cells lie (absent from reports written before it was measured)."""
    rows = {n: r["drawn_cells_within"] for n, r in report["runs"].items() if r.get("drawn_cells_within")}
    if not rows:
        return []
    ref = report.get("noisy_input_vehicles") or {}
    if ref.get("drawn_cells_within"):
        rows["noisy input (reference)"] = ref["drawn_cells_within"]
    if report.get("every_cell_within"):
        rows["every cell (chance)"] = report["every_cell_within"]
    ks = [str(k) for k in REACH_CELLS]
    return ["", "## Where the drawn vehicle cells lie", "",
            f"Share of reconstructed HV and AV cells ≥ 0.25 within k cells of a real vehicle, on the "
            f"{report['held_out_samples']} held-out samples of the figures (k = 1 is the precision above, "
            "on these samples). The chance row is the share of all cells within k cells of a vehicle: what "
            "cells drawn at random would score.", "",
            "| run | " + " | ".join(f"≤ {k} cell{'s' if k != '1' else ''}" for k in ks) + " |",
            "|---" * (len(ks) + 1) + "|"] + [
        f"| {n} | " + " | ".join(fmt_value(r.get(k), ".1%") for k in ks) + " |" for n, r in rows.items()]


def _scored(report: dict[str, Any]) -> str:
    n = report.get("scored_samples")
    return "every held-out sample" if n is None else f"the first {n} held-out samples of mixed batches"


def format_report(report: dict[str, Any]) -> str:
    """The study's findings as Markdown tables."""
    runs = report["runs"]
    lines = [
        "# Bottleneck network study",
        "",
        f"Dataset: {report['dataset_samples']} samples; whole episodes held out. Reconstruction error and "
        f"vehicles are scored on {_scored(report)}, scenario distances and figures on "
        f"{report['held_out_samples']} of them.",
        "",
        "## Reconstruction error and scenario distance per run",
        "",
        "| run | d | λ | held-out L2 (mean per element) | held-out L2 on vehicle cells "
        "| vehicles recovered | precision of bright cells | mean between-scenario MMD² (latent) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    lines += [f"| {n} | {r['latent_dim']} | {r['lambda']:g} | {fmt_value(r['val_recon'], '.6f')} | {fmt_value(r.get('val_vehicle_l2'), '.4f')} "
              f"| {fmt_value(r.get('vehicle_recall'), '.1%')} | {fmt_value(r.get('vehicle_precision'), '.1%')} "
              f"| {fmt_value(r['mean_between_scenario_distance'], '.4f')} |" for n, r in runs.items()]
    ref = report.get("noisy_input_vehicles")
    if ref is not None:
        lines += [f"| noisy input (reference) | – | – | – | – | {fmt_value(ref['vehicle_recall'], '.1%')} "
                  f"| {fmt_value(ref['vehicle_precision'], '.1%')} | – |"]
    lines += _recall_table(report)
    lines += ["", "A vehicle (a blob of cells in a clean HV or AV frame) is *recovered* when the "
              "reconstruction reaches half its peak value on it or within one cell of it; *precision* is "
              "the share of reconstructed cells ≥ 0.25 within one cell of a real vehicle "
              "(`latentdrive.bnn.vehicles`). The reference row scores the noisy input itself as a "
              "reconstruction of the clean target."]
    lines += _reach_table(report)
    lines += ["", f"Raw-input baseline space: mean between-scenario MMD² {fmt_value(report['raw_mean_between_scenario_distance'], '.4f')}.",
              "", "## Scenario distance (MMD²), raw-input baseline space", "",
              _matrix_md(report["raw_scenarios"], report["raw_distance"])]
    for n, r in runs.items():
        lines += ["", f"## Scenario distance (MMD²), latent space of {n}", "",
                  _matrix_md(r["latent_scenarios"], r["latent_distance"])]
    return "\n".join(lines) + "\n"
