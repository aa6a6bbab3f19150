"""Per-scenario evaluation summaries of a policy, their table, and paired policy comparisons.

The headline is the failure rate (crashed, or time ran out before every AV completed its
mission): a policy that always brakes almost never crashes but always fails, so the crash
rate alone ranks it best. Intervals are 95% (Wilson for rates, Student t for means) and
treat episodes as independent draws; they say nothing about scenarios or traffic the
evaluation did not sample.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from latentdrive.evaluate.stats import MeanCI, PairedTest, RateCI, mean_ci, paired_test, rate_ci
from latentdrive.outcome import FAILURE_CAUSES, EpisodeOutcome

__all__ = [
    "MIXED",
    "PolicyReport",
    "ScenarioSummary",
    "cause_counts",
    "compare",
    "format_causes",
    "format_compare",
    "format_table",
    "policy_report",
    "summarize",
    "tests_json",
]

#: The name of the pooled-over-all-scenarios entry in reports and comparisons.
MIXED = "mixed"

EpisodeKey = tuple[str, int, int, int]


@dataclass(frozen=True)
class ScenarioSummary:
    """What a set of episodes (one scenario, or all pooled) amounts to.

    Episode rates: ``failure_rate = crash_rate + timeout_rate`` and ``success_rate = 1 -
    failure_rate`` (see :class:`~latentdrive.outcome.EpisodeOutcome`). ``agent_crash_rate``
    and ``agent_arrival_rate`` count AV-episodes; AVs of one episode share traffic, so
    their intervals are too narrow. ``traffic_crash_rate``: episodes in which human
    drivers crashed among themselves (a wreck can block a mission). ``mean_speed`` (m/s), ``mean_return`` (each episode's
    per-AV return averaged over its AVs) and ``mean_steps`` are means over episodes;
    episodes whose value is NaN (e.g. no AV ever acted) are left out of that mean.
    Pooled ("mixed") numbers weight scenarios by their episode counts.
    """

    episodes: int
    failure_rate: RateCI
    crash_rate: RateCI
    success_rate: RateCI
    timeout_rate: RateCI
    agent_crash_rate: RateCI
    agent_arrival_rate: RateCI
    traffic_crash_rate: RateCI
    mean_speed: MeanCI
    mean_return: MeanCI
    mean_steps: MeanCI

    def as_dict(self) -> dict[str, Any]:
        """``{"episodes": n, "failure_rate": {"k", "n", "rate", "lo", "hi"}, ...,
        "mean_speed": {"mean", "lo", "hi", "n"}, ...}``; JSON-safe, NaN as ``None``."""
        out: dict[str, Any] = {}
        for f in fields(self):
            value = getattr(self, f.name)
            out[f.name] = value.as_dict() if isinstance(value, (RateCI, MeanCI)) else value
        return out


def _finite(values: Iterable[float]) -> list[float]:
    return [v for v in values if not math.isnan(v)]


def summarize(outcomes: Sequence[EpisodeOutcome]) -> ScenarioSummary:
    """Rates and means over ``outcomes``; no outcomes give NaN numbers and 0 episodes."""
    n = len(outcomes)

    def count(pred: Callable[[EpisodeOutcome], bool]) -> RateCI:
        return rate_ci(sum(1 for o in outcomes if pred(o)), n)

    agents = sum(int(o.agent_crashed.size) for o in outcomes)
    crashed_agents = sum(int(np.count_nonzero(o.agent_crashed)) for o in outcomes)
    arrived_agents = sum(int(np.count_nonzero(o.agent_arrived)) for o in outcomes)
    returns = [float(np.mean(o.agent_return)) if o.agent_return.size else math.nan for o in outcomes]
    return ScenarioSummary(
        episodes=n,
        failure_rate=count(lambda o: o.failed),
        crash_rate=count(lambda o: o.crashed),
        success_rate=count(lambda o: o.success),
        timeout_rate=count(lambda o: o.timed_out),
        agent_crash_rate=rate_ci(crashed_agents, agents),
        agent_arrival_rate=rate_ci(arrived_agents, agents),
        traffic_crash_rate=count(lambda o: o.traffic_crashed),
        mean_speed=mean_ci(_finite(float(o.mean_speed) for o in outcomes)),
        mean_return=mean_ci(_finite(returns)),
        mean_steps=mean_ci([float(o.steps) for o in outcomes]),
    )


def _by_scenario(outcomes: Iterable[EpisodeOutcome]) -> dict[str, list[EpisodeOutcome]]:
    groups: dict[str, list[EpisodeOutcome]] = {}
    for o in outcomes:
        groups.setdefault(o.scenario, []).append(o)
    return {name: groups[name] for name in sorted(groups)}


@dataclass(frozen=True)
class PolicyReport:
    """One policy's :class:`ScenarioSummary` per scenario (sorted by name) and pooled."""

    scenarios: dict[str, ScenarioSummary]
    mixed: ScenarioSummary

    def as_dict(self) -> dict[str, Any]:
        """``{"scenarios": {name: summary.as_dict()}, "mixed": summary.as_dict()}``."""
        return {
            "scenarios": {name: s.as_dict() for name, s in self.scenarios.items()},
            MIXED: self.mixed.as_dict(),
        }


def policy_report(outcomes: Sequence[EpisodeOutcome]) -> PolicyReport:
    """Summaries of ``outcomes`` grouped by ``outcome.scenario``, and of all of them."""
    groups = _by_scenario(outcomes)
    return PolicyReport({name: summarize(g) for name, g in groups.items()}, summarize(outcomes))


def _pct(r: RateCI, ci: bool = True) -> str:
    if math.isnan(r.rate):
        return "-"
    text = f"{100 * r.rate:.1f}"
    return f"{text} [{100 * r.lo:.1f}, {100 * r.hi:.1f}]" if ci else text


def _num(m: MeanCI, digits: int) -> str:
    return "-" if math.isnan(m.mean) else f"{m.mean:.{digits}f}"


def render_table(header: Sequence[str], rows: Sequence[Sequence[str]], left: int) -> str:
    """Columns padded to width; the first ``left`` columns left-aligned, the rest right."""
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]

    def line(cells: Sequence[str]) -> str:
        pairs = enumerate(zip(cells, widths, strict=True))
        padded = [c.ljust(w) if i < left else c.rjust(w) for i, (c, w) in pairs]
        return "  ".join(padded).rstrip()

    return "\n".join([line(header), line(["-" * w for w in widths]), *map(line, rows)])


_TABLE_HEADER = (
    "policy", "scenario", "episodes", "failure % [95% CI]", "crash % [95% CI]",
    "success %", "AV arrival %", "HV wreck %", "speed m/s", "return", "steps",
)


def format_table(reports: Mapping[str, PolicyReport]) -> str:
    """A plain-text table: per policy, one row per scenario, then its pooled "mixed" row.

    Failure rate comes first; crash rate alone rewards a policy that never moves.
    Speed, return and steps are means over episodes.
    """
    rows: list[list[str]] = []
    for policy, report in reports.items():
        for scenario, s in [*report.scenarios.items(), (MIXED, report.mixed)]:
            rows.append([
                policy, scenario, str(s.episodes), _pct(s.failure_rate), _pct(s.crash_rate),
                _pct(s.success_rate, ci=False), _pct(s.agent_arrival_rate, ci=False),
                _pct(s.traffic_crash_rate, ci=False), _num(s.mean_speed, 2), _num(s.mean_return, 2), _num(s.mean_steps, 1),
            ])
    return render_table(_TABLE_HEADER, rows, left=2)


def cause_counts(outcomes: Sequence[EpisodeOutcome]) -> dict[str, dict[str, int]]:
    """Episodes by how they ended, per scenario (sorted) and pooled (:data:`MIXED`):
    ``{scenario: {"episodes": n, "success": k, cause: k, ...}}`` with every cause of
    :data:`~latentdrive.outcome.FAILURE_CAUSES` that occurs in ``outcomes``, in that order."""
    present = [c for c in FAILURE_CAUSES if any(o.cause == c for o in outcomes)]

    def count(group: Sequence[EpisodeOutcome]) -> dict[str, int]:
        return {"episodes": len(group), "success": sum(o.success for o in group),
                **{c: sum(o.cause == c for o in group) for c in present}}

    groups = _by_scenario(outcomes)
    return {**{name: count(g) for name, g in groups.items()}, MIXED: count(outcomes)}


def format_causes(outcomes: Mapping[str, Sequence[EpisodeOutcome]]) -> str:
    """A plain-text table of :func:`cause_counts` per policy, as % of episodes.

    "HV ahead/behind/beside" say where the other car was at the crash, not whose fault
    it was (:func:`~latentdrive.outcome.failure_cause`)."""
    counts = {policy: cause_counts(o) for policy, o in outcomes.items()}
    present = [c for c in FAILURE_CAUSES if any(c in row for by in counts.values() for row in by.values())]
    header = ("policy", "scenario", "episodes", "success %", *(f"{c} %" for c in present))
    rows = [
        [policy, scenario, str(row["episodes"]),
         *(_share(row.get(k, 0) / row["episodes"] if row["episodes"] else math.nan) for k in ("success", *present))]
        for policy, by in counts.items()
        for scenario, row in by.items()
    ]
    return render_table(header, rows, left=2)


def _episode_key(o: EpisodeOutcome) -> EpisodeKey:
    return (o.scenario, int(o.seed), int(o.env_index), int(o.episode_index))


def _index(outcomes: Sequence[EpisodeOutcome], name: str) -> dict[EpisodeKey, EpisodeOutcome]:
    index: dict[EpisodeKey, EpisodeOutcome] = {}
    for o in outcomes:
        key = _episode_key(o)
        if key in index:
            raise ValueError(f"{name} holds episode {key} (scenario, seed, env, episode) twice")
        index[key] = o
    return index


def compare(
    a: Sequence[EpisodeOutcome], b: Sequence[EpisodeOutcome]
) -> dict[str, dict[str, PairedTest]]:
    """Paired tests of policy ``a`` against ``b`` on the same evaluation episodes.

    Episodes pair by (scenario, seed, env_index, episode_index); both sides must hold
    exactly the same keys, else ``ValueError``. Returns ``{scenario: {"failed": test,
    "crashed": test}}`` for each scenario (sorted) and :data:`MIXED` (all pooled); see
    :func:`~latentdrive.evaluate.stats.paired_test` for what each number can show. Pairing
    on identical seeds removes the episode-to-episode variance the two policies share, so
    it detects smaller differences than comparing two independent rates.
    """
    ia, ib = _index(a, "a"), _index(b, "b")
    if ia.keys() != ib.keys():
        only_a, only_b = sorted(ia.keys() - ib.keys()), sorted(ib.keys() - ia.keys())
        example = (only_a or only_b)[0]
        raise ValueError(
            f"not the same evaluation episodes: {len(only_a)} only in a, {len(only_b)} only "
            f"in b (e.g. {example}; key is scenario, seed, env_index, episode_index)"
        )
    keys = sorted(ia)
    if any(k[0] == MIXED for k in keys):
        raise ValueError(f"a scenario named {MIXED!r} clashes with the pooled entry")
    groups: dict[str, list[EpisodeKey]] = {}
    for k in keys:
        groups.setdefault(k[0], []).append(k)
    groups[MIXED] = keys

    def tests(ks: list[EpisodeKey]) -> dict[str, PairedTest]:
        return {
            "failed": paired_test([ia[k].failed for k in ks], [ib[k].failed for k in ks]),
            "crashed": paired_test([ia[k].crashed for k in ks], [ib[k].crashed for k in ks]),
        }

    return {name: tests(ks) for name, ks in groups.items()}


def tests_json(results: Mapping[str, Mapping[str, PairedTest]]) -> dict[str, dict[str, Any]]:
    """:func:`compare`'s result as JSON values."""
    return {scope: {k: t.as_dict() for k, t in by.items()} for scope, by in results.items()}


def _pp(t: PairedTest) -> str:
    if math.isnan(t.difference):
        return "-"
    return f"{100 * t.difference:+.1f} [{100 * t.lo:+.1f}, {100 * t.hi:+.1f}]"


def _share(rate: float) -> str:
    return "-" if math.isnan(rate) else f"{100 * rate:.1f}"


def _p(value: float) -> str:
    return "-" if math.isnan(value) else f"{value:.3g}"


def format_compare(
    results: Mapping[str, Mapping[str, PairedTest]], names: tuple[str, str] = ("A", "B")
) -> str:
    """:func:`compare`'s result as a plain-text table: one row per scenario and outcome with
    both rates, the difference A−B in percentage points with its 95% bootstrap interval,
    the discordant pair counts and McNemar's exact p-value."""
    na, nb = names
    header = (
        "scenario", "outcome", "n", f"{na} %", f"{nb} %", f"{na}-{nb} pp [95% CI]",
        f"{na} only", f"{nb} only", "p (McNemar exact)",
    )
    rows = [
        [
            scenario, outcome, str(t.n), _share(t.rate_a), _share(t.rate_b), _pp(t),
            str(t.a_only), str(t.b_only), _p(t.p_value),
        ]
        for scenario, by_outcome in results.items()
        for outcome, t in by_outcome.items()
    ]
    return render_table(header, rows, left=2)
