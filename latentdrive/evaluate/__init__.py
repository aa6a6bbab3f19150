"""Evaluation statistics: per-scenario summaries with intervals, tables, paired comparisons."""

from __future__ import annotations

from latentdrive.evaluate.report import (
    MIXED,
    PolicyReport,
    ScenarioSummary,
    compare,
    format_compare,
    format_table,
    policy_report,
    summarize,
)
from latentdrive.evaluate.stats import (
    MeanCI,
    PairedTest,
    RateCI,
    mean_ci,
    paired_test,
    rate_ci,
)

__all__ = [
    "MIXED",
    "MeanCI",
    "PairedTest",
    "PolicyReport",
    "RateCI",
    "ScenarioSummary",
    "compare",
    "format_compare",
    "format_table",
    "mean_ci",
    "paired_test",
    "policy_report",
    "rate_ci",
    "summarize",
]
