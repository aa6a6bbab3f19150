"""``OUT/report.md`` from ``results.json``: every table, figure, config and cost of a study."""

from __future__ import annotations

import shutil
from collections import Counter
from pathlib import Path
from typing import Any

import yaml

from latentdrive.config import dotted_items
from latentdrive.experiments.study_figures import write_study_figures
from latentdrive.experiments.study_runs import runs_summary
from latentdrive.fileio import atomic_write_text

__all__ = ["WEAK_BNN_RECALL", "summary_table", "write_report"]

#: Below this share of held-out vehicles recovered, the report warns that the latent arm
#: reads an encoder too weak to test the bottleneck (the noisy input itself shows ~90%).
WEAK_BNN_RECALL = 0.2


def _pct(x: float | None) -> str:
    return "–" if x is None else f"{100 * x:.1f}"


def _agg(e: dict[str, Any]) -> str:
    """``mean [lo, hi]`` in percent: over seeds when there are several; with one seed, the
    Wilson interval over its episodes, marked ``w``."""
    if e["lo"] is None:
        w = e["episodes"]
        return f"{_pct(e['mean'])} [{_pct(w['lo'])}, {_pct(w['hi'])}]w"
    return f"{_pct(e['mean'])} [{_pct(e['lo'])}, {_pct(e['hi'])}]"


def _wilson(e: dict[str, Any]) -> str:
    return f"{_pct(e['rate'])} [{_pct(e['lo'])}, {_pct(e['hi'])}]"


def _p(p: float | None) -> str:
    return "–" if p is None else (f"{p:.3f}" if p >= 0.001 else "<0.001")


def _relative(t: dict[str, Any]) -> str:
    """``1 - latent / raw`` with its episode-bootstrap interval (``–`` where undefined, ``-∞`` where unbounded)."""
    rel, lo, hi = t.get("relative"), t.get("relative_lo"), t.get("relative_hi")
    if rel is None:
        return "–"
    # rel is defined, so a missing bound is an unbounded one (-inf does not survive JSON).
    return f"{100 * rel:+.0f}% [{'-∞' if lo is None else f'{100 * lo:+.0f}'}, {_signed(hi)}]"


def _signed(v: float | None, digits: int = 0) -> str:
    """A share in signed percent (points), ``–`` where undefined."""
    return "–" if v is None else f"{100 * v:+.{digits}f}"


def _table(header: list[str], rows: list[list[str]]) -> list[str]:
    return ["| " + " | ".join(header) + " |", "|" + "---|" * len(header), *("| " + " | ".join(r) + " |" for r in rows)]


def summary_table(res: dict[str, Any]) -> str:
    """The headline as plain text: printed at the end of a study."""
    refs = res["references"]
    lines = [f"{'test set':<13}{'raw failure %':>24}{'latent failure %':>24}{'fewer failures':>22}{'McNemar p':>10}"
             f"{'random':>8}{'planner':>8}"]
    for r in res["headline"]:
        lines.append(f"{r['test']:<13}{_agg(r['raw']['failure']):>24}{_agg(r['latent']['failure']):>24}"
                     f"{_relative(r['paired']['failure']):>22}{_p(r['paired']['failure']['p_value']):>10}"
                     f"{_pct(refs['random'][r['test']]['failure']['rate']) if 'random' in refs else '–':>8}"
                     f"{_pct(refs['plan'][r['test']]['failure']['rate']) if 'plan' in refs else '–':>8}")
    return "\n".join(lines)


def _raw_network(cfg: dict[str, Any]) -> str:
    """What the ``raw`` policies are, in the report's opening sentence."""
    own = ((cfg["policy"].get("by_kind") or {}).get("raw") or {}).get("vfan")
    if own:
        return ("a DQN that reads the raw maps through another network (`raw`: "
                + ", ".join(f"`vfan.{k}={v}`" for k, v in dotted_items(own)) + "), so not the paper's raw baseline")
    return "the same network on the raw maps (`raw`)"


def _provenance(command: str | None, steps: dict[str, Any]) -> list[str]:
    """Report lines: the command of the last run, and the commits the steps ran from."""
    lines = [f"- Command of the last run: `{command}`."] if command else []
    counts = Counter(s["source"] for s in steps.values() if s.get("source"))
    unknown = len(steps) - sum(counts.values())
    why = "not run from a git checkout, or recorded before commits were kept"
    if not counts:
        return [*lines, f"- Code: the commit the steps ran from is unknown ({why})."]
    rest = f"; {unknown} steps' commit unknown ({why})" if unknown else ""
    if len(counts) == 1:
        (commit, n), = counts.items()
        return [*lines, f"- Code: {f'{n} steps' if unknown else 'every step'} ran from commit `{commit}`{rest}."]
    return [*lines, "- Code: **the steps ran from more than one commit**: "
            + ", ".join(f"`{c}` ({n} steps)" for c, n in counts.most_common())
            + rest + "; compare the commits before reading the results as one study's."]


def _scale(res: dict[str, Any]) -> list[str]:
    cfg = res["meta"]["config"]
    seeds, eps = res["seeds"], res["evaluation"]["episodes_per_scenario"]
    lines = [f"- Scale: {seeds} training seed(s); {cfg['policy']['steps']:,} agent-transitions per policy "
             f"({cfg['policy']['finetune_steps']:,} of fine-tuning); {eps} evaluation episodes per scenario and policy "
             f"(mixed test set: {eps * len(res['scenarios'])}); BNNs trained {cfg['bnn']['train']['pretrain_epochs'] + cfg['bnn']['train']['mixed_epochs']} epochs "
             f"on {cfg['bnn']['collect']['episodes']} episodes per scenario."]
    for kind, settings in (cfg["policy"].get("by_kind") or {}).items():
        if settings:
            lines.append(f"- `{kind}` policies only: " + ", ".join(f"`{k}={v}`" for k, v in dotted_items(settings)) + ".")
    if seeds < 3:
        lines.append("- With fewer than 3 training seeds, intervals over seeds are missing or rest on very few "
                     "draws: the rates describe these trained policies, not the training method.")
    lines.append("- Intervals: `[lo, hi]` after a mean over seeds is rliable's 95% stratified-bootstrap interval over "
                 "training seeds; `[lo, hi]w` (one seed) and intervals of single policies are 95% Wilson intervals "
                 "over episodes, which say how well these trained policies were measured, not how another training "
                 "seed would do. McNemar's "
                 "exact test pairs latent and raw on identical episodes (seed k against seed k, pooled); a large p "
                 "does not show the two are equal.")
    lines.append("- Evaluation episodes are drawn from seeds disjoint from every training seed.")
    bnn = res["bnn"]["report"]
    run = res["bnn"]["policy_run"]
    recall = bnn["runs"].get(run, {}).get("vehicle_recall")
    base = (bnn.get("noisy_input_vehicles") or {}).get("vehicle_recall")
    if recall is not None and recall < WEAK_BNN_RECALL:
        lines.append(f"- **The BNN the latent policies read ({run}) recovers {_pct(recall)}% of held-out vehicles** "
                     f"(the noisy input itself: {_pct(base)}%). Its latents carry little of the scene, so at this "
                     "scale `latent` against `raw` cannot test the paper's claim: it compares the raw maps with a "
                     "nearly uninformed encoder (compare `latent-random`). The BNN needs more data and epochs.")
    return lines


def _imitation(res: dict[str, Any]) -> list[str]:
    """Section 1's imitation-reference table: what a policy reading the map reached by imitation."""
    im, refs = res["imitation"], res["references"]
    mix = {rep: res["matrix"][rep]["mixed"] for rep in ("raw", "latent")}  # failure means over seeds
    rows = [[t, _pct(mix["raw"][t]), _pct(mix["latent"][t]), _agg(im["policy"][t]["failure"]),
             *(_pct(refs[ref][t]["failure"]["rate"]) if ref in refs else "–" for ref in ("rule", "plan"))]
            for t in res["tests"]]
    vs = im["vs_raw"]
    return ["", "**The imitation reference.** The raw-mode network trained by DAgger to copy the planner's "
            "decisions from the map, with as many labelled decisions as a policy's budget: the failure rate shown "
            "reachable from this observation at this budget, beside the planner's privileged floor "
            "(failure %, mix policies):", "",
            *_table(["test set", "raw (DQN)", "latent (DQN)", "imitation", "rule", "planner"], rows), "",
            f"Raw DQN against the imitation reference on the same mixed episodes (seed k against seed k): "
            f"{_points(vs)} percentage points of failures, "
            f"McNemar p {_p(vs['p_value'])}."]


def _points(t: dict[str, Any]) -> str:
    """A paired test's difference in percentage points with its interval."""
    if t["difference"] is None:
        return "–"
    return f"{_signed(t['difference'], 1)} [{_signed(t['lo'], 1)}, {_signed(t['hi'], 1)}]"


def _significant(t: dict[str, Any], fewer: bool, alpha: float = 0.05) -> bool:
    """Significantly fewer (or more) failures than the other arm of a paired test."""
    if t["p_value"] is None or t["p_value"] >= alpha:
        return False
    return t["rate_a"] < t["rate_b"] if fewer else t["rate_a"] > t["rate_b"]


def _per_seed(per: dict[str, Any]) -> list[str]:
    """Section 1's seed-by-seed tables: each mix policy against the references, and latent
    against raw, on the same mixed episodes."""
    refs = [r for r in ("random", "rule") if per.get(f"vs_{r}")]
    md: list[str] = []
    if refs:
        first = per[f"vs_{refs[0]}"]
        header = ["policy", "seed", "fail %", *(h for r in refs for h in (f"{r} fail %", "McNemar p"))]
        rows = [[rep, str(k), _pct(t["rate_a"]),
                 *(c for r in refs for c in (_pct(per[f"vs_{r}"][rep][k]["rate_b"]), _p(per[f"vs_{r}"][rep][k]["p_value"])))]
                for rep, tests in first.items() for k, t in enumerate(tests)]
        md += ["", "Mixed-scenario policies against the references on the same episodes, seed by seed (failure):", "",
               *_table(header, rows)]
    if "rule" in refs:
        vs = per["vs_rule"]
        fewer = ", ".join(f"`{rep}` {sum(_significant(t, True) for t in tests)} of {len(tests)}" for rep, tests in vs.items())
        more = ", ".join(f"`{rep}` {sum(_significant(t, False) for t in tests)}" for rep, tests in vs.items())
        md += ["", f"Seeds that fail significantly less often than the rule driver (McNemar p < 0.05 for each seed, "
               f"no correction over seeds): {fewer}; significantly more often: {more}."]
    else:
        md += ["", "The rule driver was not evaluated (`evaluate.references`): no seed is tested against it."]
    if per.get("latent_vs_raw"):
        md += ["", "Latent against raw, seed by seed (mixed test set, failure):", "",
               *_table(["seed", "raw fail %", "latent fail %", "latent − raw (points)", "McNemar p"],
                       [[str(k), _pct(t["rate_b"]), _pct(t["rate_a"]), _points(t), _p(t["p_value"])]
                        for k, t in enumerate(per["latent_vs_raw"])])]
    return md


def write_report(res: dict[str, Any], out: Path) -> str:
    """Write ``out/report.md`` and ``out/figures``; return the summary table."""
    figures = out / "figures"
    write_study_figures(res, figures)
    bnn_fig = out / res["bnn"]["figures"]
    if bnn_fig.is_dir():
        for f in sorted(bnn_fig.glob("*.png")):
            shutil.copyfile(f, figures / f.name)
    meta = res["meta"]
    refs = res["references"]
    md = [f"# latentdrive reproduce: {meta['preset'] or 'custom'} preset", "",
          "The paper's study: a denoising bottleneck (BNN) over stacked VelocityMaps, whose frozen latents "
          "feed a 3D-convolutional DQN (`latent`), against " + _raw_network(meta["config"]) + ".", "",
          "## What this run can and cannot show", "", *_scale(res),
          "- The failure rate (a crash, or the mission not completed in time) is the headline: a policy that "
          "always brakes rarely crashes. The planner (a lookahead with privileged access to the simulator) is the "
          "avoidable floor: the failure it still has is hard to avoid for any policy.", "",
          "## 1. Bottleneck vs baseline", "", "![headline](figures/headline.png)", ""]
    rows = []
    for r in res["headline"]:
        row = [f"{r['train']} → {r['test']}"]
        for w in ("failure", "crash"):
            row += [_agg(r["raw"][w]), _agg(r["latent"][w]), _relative(r["paired"][w]), _p(r["paired"][w]["p_value"])]
        row += [_pct(refs[ref][r["test"]]["failure"]["rate"]) if ref in refs else "–" for ref in ("random", "rule", "plan")]
        rows.append(row)
    md += _table(["trained → tested", "raw failure %", "latent failure %", "fewer failures", "p",
                  "raw crash %", "latent crash %", "fewer crashes", "p", "random fail %", "rule fail %", "planner fail %"],
                 rows)
    md += ["", "The paper reports 47% fewer crashed and failed episodes with the bottleneck ('fewer failures': "
           "1 − latent / raw over the paired episodes, with its 95% bootstrap interval over episodes; it describes "
           "these trained policies, not other training seeds)."]
    md += _per_seed(res["per_seed"])

    if "imitation" in res:
        md += _imitation(res)

    tests = res["tests"]
    md += ["", "## 2. Train × test", "", "![matrix](figures/matrix.png)", ""]
    for rep in ("raw", "latent"):
        md += [f"Failure % of `{rep}` policies (rows: trained on; columns: tested on; mean over seeds):", ""]
        rows = [[tr, *(_pct(v[t]) for t in tests)] for tr, v in res["matrix"][rep].items()]
        rows += [[f"*{ref} (reference)*", *(_pct(refs[ref][t]["failure"]["rate"]) for t in tests)] for ref in refs]
        md += _table(["trained on", *tests], rows)
        md.append("")

    md += ["## 3. Domain adaptation: the mix policy against each scenario's own", ""]
    md += _table(["scenario", "raw: mix", "raw: own", "latent: mix", "latent: own"],
                 [[s, _agg(res["domain_adaptation"]["raw"][s]["mixed"]), _agg(res["domain_adaptation"]["raw"][s]["oracle"]),
                   _agg(res["domain_adaptation"]["latent"][s]["mixed"]), _agg(res["domain_adaptation"]["latent"][s]["oracle"])]
                  for s in res["scenarios"]])

    if "transfer" in res:
        tr = res["transfer"]
        md += ["", f"## 4. Transfer learning to {tr['target']}", "", "![transfer](figures/transfer.png)", ""]
        md += _table(["representation", "zero-shot %", "fine-tuned %", "from scratch %"],
                     [[rep, _agg(tr[rep]["zero_shot"]), _agg(tr[rep]["finetuned"]), _agg(tr[rep]["scratch"])]
                      for rep in ("raw", "latent")])
        md += ["", "From scratch trains with the full budget; fine-tuning with its own (smaller) one after pretraining "
               "on the other scenarios."]

    if "leave_one_out" in res:
        loo = res["leave_one_out"]
        md += ["", "## 5. Leave one scenario out (zero-shot)", "", "![loo](figures/leave_one_out.png)", ""]
        md += _table(["left out", "raw zero-shot %", "raw own %", "latent zero-shot %", "latent own %", "MMD² latent", "MMD² raw"],
                     [[s, _agg(loo["raw"]["scenarios"][s]["zero_shot"]), _agg(loo["raw"]["scenarios"][s]["oracle"]),
                       _agg(loo["latent"]["scenarios"][s]["zero_shot"]), _agg(loo["latent"]["scenarios"][s]["oracle"]),
                       _num(loo["latent"]["scenarios"][s].get("distance_latent")),
                       _num(loo["latent"]["scenarios"][s].get("distance_raw"))] for s in res["scenarios"]])
        corr = [f"{rep} policies, {space} distance: Spearman ρ {_num(c['spearman'])} (p {_p(c['p'])}, {c['points']} points)"
                for rep in ("raw", "latent") for space, c in loo[rep]["distance_vs_zero_shot"].items()]
        if corr:
            md += ["", "Does a smaller distance predict better transfer? " + "; ".join(corr) +
                   ". With one point per scenario this is weak evidence either way."]

    if "ablations" in res:
        md += ["", "## 6. Ablations on the mix", "", "![ablations](figures/ablations.png)", ""]
        md += _table(["input", "failure %", "crash %"],
                     [[v, _agg(e["failure"]), _agg(e["crash"])] for v, e in res["ablations"].items()])
        md += ["", "`latent-random`: the same frozen encoder with untrained weights; `end-to-end`: the encoder "
               "trained by the Q-loss alone; `latent-lam`: the λ > 0 BNN."]

    if "cross_backend" in res:
        md += ["", "## 7. Cross-backend check (mixed policies)", ""]
        md += _table(["policy", "seed", "fast fail %", "highway-env fail %", "McNemar p", "agree?"],
                     [[rep, str(k), _wilson(e["fast"]["failure"]), _wilson(e["highway"]["failure"]),
                       _p(e["paired"]["p_value"]), "yes" if (e["paired"]["p_value"] or 1) >= 0.05 else "NO"]
                      for rep, per in res["cross_backend"].items() for k, e in enumerate(per)])
        md += ["", "'Agree' means no significant difference on these episodes, not proof of equality."]

    if "probes" in res:
        pr = res["probes"]
        kinds = [k for k in ("raw", "latent", "latent-random") if k in pr]
        targets = list(pr[kinds[0]]) if kinds else []
        md += ["", "## 8. What the features hold: linear probes", "",
               f"Linear read-outs fitted on frozen features of {pr['samples']['train']} samples (rule driver), scored on "
               f"{pr['samples']['test']} samples of held-out episodes: R² for quantities, accuracy for flags (beside "
               "the majority-class accuracy, since free-lane flags are imbalanced).", ""]
        md += _table(["target", "metric", *kinds, "baseline"],
                     [[t, pr[kinds[0]][t]["metric"], *(_num(pr[k][t]["value"]) for k in kinds),
                       _num(pr[kinds[0]][t]["baseline"])] for t in targets])
        md += ["", "A high score shows the quantity is linearly readable from the features; a low one does not show "
               "the policy cannot use it (its network is not linear)."]

    bnn = res["bnn"]["report"]
    md += ["", "## 9. Bottleneck network", "", "![loss](figures/bnn_loss.png)", "![recon](figures/bnn_reconstruction.png)",
           "![latents](figures/bnn_latents.png)", "![distance](figures/bnn_distance.png)", ""]
    noisy = bnn.get("noisy_input_vehicles") or {}
    md += _table(["run", "d", "λ", "held-out recon", "vehicle recall", "precision", "mean scenario MMD²"],
                 [[n, str(r["latent_dim"]), f"{r['lambda']:g}", _num(r.get("val_recon"), 4), _pct(r.get("vehicle_recall")),
                   _pct(r.get("vehicle_precision")), _num(r.get("mean_between_scenario_distance"))]
                  for n, r in bnn["runs"].items()]
                 + [["noisy input (reference)", "", "", "", _pct(noisy.get("vehicle_recall")),
                     _pct(noisy.get("vehicle_precision")), ""]])
    md += ["", f"Latent policies use `{res['bnn']['policy_run']}`; raw-input mean scenario MMD²: "
           f"{_num(bnn.get('raw_mean_between_scenario_distance'))}."]

    steps = res["steps"]
    # A step resumed after an interruption costs its finishing attempt plus what the
    # earlier ones did that it kept.
    cost = {n: s["wall_s"] + s.get("resumed_s", 0.0) for n, s in steps.items()}
    total = sum(cost.values())
    resumed = [s["resumed_s"] for s in steps.values() if s.get("resumed_s")]
    by_kind: dict[str, list[float]] = {}
    for n, s in steps.items():
        by_kind.setdefault(s["kind"], []).append(cost[n])
    env = meta["environment"]
    md += ["", "## Cost, hardware, versions", "",
           f"- Last run: {meta['last_run'].get('wall_s', '–')} s wall with {meta['last_run'].get('workers', '–')} "
           f"worker(s); {total:.0f} s of step time in all (finished steps of earlier runs included"
           + (f"; {len(resumed)} step(s) resumed after an interruption, with the {sum(resumed):.0f} s their "
              "earlier attempts spent on the work they kept)." if resumed else ")."),
           *([line] if (line := runs_summary(meta.get("runs"))) else []),
           *_provenance(meta["last_run"].get("command"), steps),
           f"- Peak memory of a step: {max(s['peak_rss_mb'] for s in steps.values()):.0f} MB.",
           f"- Machine: {env['machine']}, {env['cpus']} CPUs, GPU: {env['gpu'] or 'none'}; latentdrive "
           f"{env.get('latentdrive', '–')}, Python {env['python']}, torch {env['torch']}, numpy {env['numpy']}.", ""]
    md += _table(["step kind", "steps", "total s", "longest s"],
                 [[k, str(len(v)), f"{sum(v):.0f}", f"{max(v):.0f}"] for k, v in sorted(by_kind.items())])
    md += ["", "## Config", "", "```yaml", yaml.safe_dump(meta["config"], sort_keys=False).rstrip(), "```", ""]
    atomic_write_text(out / "report.md", "\n".join(md))
    return summary_table(res)


def _num(x: float | None, digits: int = 3) -> str:
    return "–" if x is None else f"{x:.{digits}f}"
