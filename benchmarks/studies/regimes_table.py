"""The regime study's tables: the decision table (one row per regime and, for the chunked heads, per TAR arm),
the per-group rows, the chunked heads' fit and weights, Fig. 3 per regime, and the chunked heads' paired differences
at a glance (``fig_paired.png``: each arm minus uniform per seed, with R6's controls from its table's
``r6/paired.csv``),
from the finished runs.

Pairs (a chunked-heads seed's three runs) trained at different commits or on different machines are refused; a
chunked-heads regime is tabled over the seeds every arm has finished, and with ``complete`` a missing run of its
plan is refused, named. The markdown holds no provenance: it is recomputed exactly from the committed runs.
"""

from __future__ import annotations

import io
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from benchmarks.studies.compare import FINAL_SHARE, check_pairs, fit_means, fit_summary, holm_into
from benchmarks.studies.core import Spec, seed_major
from benchmarks.studies.protocol import BASELINE, CHUNKED_ARMS, TREATMENT
from benchmarks.studies.writers import fit_markdown, fmt_num, fmt_p, pending_lines, write_outputs

__all__ = [
    "PAIRED_FIGURE",
    "PAIRED_SOURCES",
    "PRIMARY",
    "Planned",
    "chunked_paired_rows",
    "decision_markdown",
    "regime_rows",
    "write_tables",
]

PRIMARY = ("R1", "R2", "R3")  # the comparisons the Holm correction runs over (R1: 3 demonstrations)
#: The paired differences at a glance (:func:`write_paired_figure`).
PAIRED_FIGURE = "fig_paired.png"
#: R6 (``why_act``, results/regimes/PLAN.md "Why TAR helps act") and R7 (``flow_signal``, "TAR for a sampled loss"):
#: their folders under the study's, and the file of per-seed differences their tables write there (``label``,
#: ``group``, ``seed``, ``delta``).
R6_FOLDER, R7_FOLDER, PAIRED_CSV = "r6", "r7", "paired.csv"


@dataclass(frozen=True)
class Planned:
    """The regime study's planned runs, as its tables read them (the study plans them: :mod:`.regimes`).

    Attributes:
        paired: the paired regimes' runs (R1, R1-10, R2, R3) by regime, those planned so far.
        chunked: ``(head, runs by arm)`` by chunked-heads regime (R4, R5), each plan checked unchanged since its
            runs started.
        screening: R2's screening record (``screening.json``).
        screened: the task list it holds (``None`` before the screening).
        out: the study's folder (``<out>``), under which the paired figure's other sources write their rows
            (:data:`PAIRED_SOURCES`).
    """

    paired: dict[str, list[Spec]]
    chunked: dict[str, tuple[str, dict[str, list[Spec]]]]
    screening: Path
    screened: list[str] | None
    out: Path

    @property
    def heads(self) -> dict[str, str]:
        """The chunked-heads regimes' heads by regime (``R4``: ``act``), in the plan's order."""
        return {label: head for label, (head, _) in self.chunked.items()}


def regime_rows(label: str, runs: Sequence) -> tuple[dict, pd.DataFrame]:
    """One decision-table row (success, Fast20, NEPS statistics and fit diagnostics) and the per-group rows."""
    from tar_rl.report import min_detectable_effect, paired_table

    paired = paired_table(runs, objectives=[TREATMENT], file=io.StringIO())
    row: dict = {"regime": label}
    for metric in ("success", "fast20", "neps"):
        rec = paired[(paired["metric"] == metric) & (paired["level"] == "overall")].iloc[0]
        row[f"{metric}_uniform"] = rec["baseline_mean"]
        row[f"{metric}_tar"] = rec["objective_mean"]
        row[f"d_{metric}"] = rec["delta_mean"]
        row[f"d_{metric}_ci_low"], row[f"d_{metric}_ci_high"] = rec["ci_low"], rec["ci_high"]
        row[f"p_{metric}"] = rec["p_value"]
        if metric == "success":
            row["pairs"] = int(rec["n_pairs"])
            row["mde_success"] = min_detectable_effect(rec["delta_std"], int(rec["n_pairs"]))
    for obj in (BASELINE, TREATMENT):
        mine = [r for r in runs if r.objective == obj and r.finished]
        row.update({f"{name}_{obj}": value for name, value in fit_means(mine).items()})
    groups = paired[(paired["metric"] == "success") & (paired["level"] != "overall")].assign(regime=label)
    return row, groups


def _decision_lines(rows: Sequence[dict]) -> list[str]:
    lines = [
        "| regime | pairs | success % U / T | Δ success [95% CI] | p | Holm p | MDE (80%) | Δ Fast20 | Δ NEPS "
        "| passes | final train loss U / T | held-out loss U / T | alignment U / T |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        ci = f"[{fmt_num(r['d_success_ci_low'], 2, True)}, {fmt_num(r['d_success_ci_high'], 2, True)}]"
        lines.append(
            f"| {r['regime']} | {r['pairs']} | {fmt_num(r['success_uniform'])} / {fmt_num(r['success_tar'])} "
            f"| {fmt_num(r['d_success'], 2, True)} {ci} | {fmt_p(r['p_success'])} | {fmt_p(r['holm_p'])} "
            f"| {fmt_num(r['mde_success'], 2)} | {fmt_num(r['d_fast20'], 2, True)} | {fmt_num(r['d_neps'], 2, True)} "
            f"| {fmt_num(r['passes_uniform'], 0)} "
            f"| {fmt_num(r['train_loss_uniform'], 4)} / {fmt_num(r['train_loss_tar'], 4)} "
            f"| {fmt_num(r['heldout_loss_uniform'], 4)} / {fmt_num(r['heldout_loss_tar'], 4)} "
            f"| {fmt_num(r['alignment_uniform'], 2, True)} / {fmt_num(r['alignment_tar'], 2, True)} |"
        )
    return lines


def decision_markdown(rows: Sequence[dict], groups: pd.DataFrame, missing: dict[str, list[str]]) -> str:
    """The decision table, per-group rows and notes on missing runs, as markdown."""
    out = ["# Where does TAR help? Decision table", "", *_decision_lines(rows), ""]
    out += [
        "Success, Fast20 and NEPS in 100 x units; Δ = TAR - uniform over paired seeds (lower Fast20/NEPS is better). "
        "Holm: over the primary comparisons (" + ", ".join(PRIMARY) + "), and separately over the chunked heads' "
        "four (R4 and R5, each arm against uniform; the row names the arm: `tar` at tar-rl's defaults, "
        "`tar_gentle` the gentle preset). MDE: the smallest true Δ success a paired "
        "t-test detects with 80% power at the observed spread. Alignment: Spearman correlation over ten bins of "
        "episode time between TAR's weight on training demonstrations and the held-out per-step loss.",
        "",
        "## Success per difficulty group",
        "",
        "| regime | group | pairs | uniform % | TAR % | Δ [95% CI] | p |",
        "|---|---|---|---|---|---|---|",
    ]
    for g in groups.to_dict("records"):
        ci = f"[{fmt_num(g['ci_low'], 2, True)}, {fmt_num(g['ci_high'], 2, True)}]"
        out.append(
            f"| {g['regime']} | {g['level']} | {g['n_pairs']} | {fmt_num(g['baseline_mean'])} "
            f"| {fmt_num(g['objective_mean'])} | {fmt_num(g['delta_mean'], 2, True)} {ci} | {fmt_p(g['p_value'])} |"
        )
    out += pending_lines(missing)
    return "\n".join(out) + "\n"


def chunked_loaded(label: str, specs: dict[str, list[Spec]], complete: bool) -> tuple[dict, list[str]]:
    """The finished runs of a chunked-heads regime per arm (``specs``: its planned runs by arm), over the seeds
    every arm has finished, and the names of its runs not finished.

    Raises:
        SystemExit: with ``complete``, an arm misses a seed (the runs named); a seed's runs trained at different
            commits or machines (:func:`check_pairs`).
    """
    from tar_rl.report import load_run

    missing = [s.run_dir.name for s in seed_major(specs) if not s.finished]
    if complete and missing:
        raise SystemExit(f"regimes: {label} misses {len(missing)} run(s) of its plan: {', '.join(missing)}")
    done = {arm: {s.config["seed"]: s for s in group if s.finished} for arm, group in specs.items()}
    seeds = sorted(set.intersection(*(set(d) for d in done.values())))
    loaded = {arm: [load_run(done[arm][seed].run_dir) for seed in seeds] for arm in CHUNKED_ARMS}
    if seeds:
        check_pairs([run for group in loaded.values() for run in group])
    return loaded, missing


def by_device(label: str, loaded: dict) -> list[dict]:
    """The paired differences in overall success of each TAR arm of a chunked-heads regime, averaged over the
    seeds trained on each kind of device (``summary.json``'s ``machine.device``: ``cpu`` or the GPU's name).
    Descriptive, no test: PLAN.md's deviation for seeds trained on a lent GPU machine."""
    from tar_rl.report import run_percent

    def overall_success(run) -> float:
        return run_percent(run)[("success", "overall")]

    device = [(r.summary.get("machine") or {}).get("device", "unknown") for r in loaded[BASELINE]]
    uniform = [overall_success(r) for r in loaded[BASELINE]]
    rows = []
    for arm in CHUNKED_ARMS[1:]:
        deltas = [overall_success(r) - u for r, u in zip(loaded[arm], uniform)]
        for kind in sorted(set(device)):
            mine = [d for d, k in zip(deltas, device) if k == kind]
            seeds = [r.seed for r, k in zip(loaded[BASELINE], device) if k == kind]
            uni = [u for u, k in zip(uniform, device) if k == kind]
            rows.append(
                {"regime": f"{label} {arm}", "device": kind, "seeds": seeds, "uniform": sum(uni) / len(uni)}
                | {"delta": sum(mine) / len(mine), "higher": sum(d > 0 for d in mine)}
            )
    return rows


def by_device_markdown(rows: Sequence[dict]) -> str:
    """The per-device differences, when a regime's pairs were trained on more than one kind of device."""
    regimes = {r["regime"] for r in rows}
    if all(sum(r["regime"] == g for r in rows) < 2 for g in regimes):
        return ""
    lines = ["", "## Chunked heads by device (descriptive)", ""]
    lines += ["| regime | device | seeds | uniform % | Δ success | TAR higher |", "|---|---|---|---|---|---|"]
    for r in rows:
        seeds = ",".join(map(str, r["seeds"]))
        lines.append(
            f"| {r['regime']} | {r['device']} | {seeds} | {fmt_num(r['uniform'])} | {fmt_num(r['delta'], 2, True)} "
            f"| {r['higher']} of {len(r['seeds'])} |"
        )
    lines += [
        "",
        "Mean paired difference in overall success over the seeds trained on each kind of device (a seed's three "
        "runs on one machine); no test: the primary test is over all pairs above.",
    ]
    return "\n".join(lines) + "\n"


def chunked_tables(
    chunked: dict[str, tuple[str, dict[str, list[Spec]]]], complete: bool
) -> tuple[list, list, list, list, dict, list, dict]:
    """Decision rows (one per regime and TAR arm, Holm over all of them), per-group rows, fit rows, the
    figure's compare rows, the missing runs, the per-device rows and the runs per arm (by regime) of the
    chunked-heads regimes (``chunked``: :attr:`Planned.chunked`)."""
    from tar_rl.report import compare

    rows, groups, fits, figure, missing, devices, by_regime = [], [], [], [], {}, [], {}
    for label, (head, specs) in chunked.items():
        loaded, missing[label] = chunked_loaded(label, specs, complete)
        if not loaded[BASELINE]:
            continue
        by_regime[label] = loaded
        devices += by_device(label, loaded)
        for arm in CHUNKED_ARMS:
            fits.append({"regime": label, "head": head, "arm": arm, **fit_summary(loaded[arm])})
            table = compare(loaded[arm], file=io.StringIO())
            figure.append(table.assign(policy=f"{label} {head}", objective=arm))
        for arm in CHUNKED_ARMS[1:]:
            row, group = regime_rows(f"{label} {arm}", [*loaded[BASELINE], *loaded[arm]])
            rows.append(row)
            groups.append(group)
    holm_into(rows, "p_success")
    return rows, groups, fits, figure, missing, devices, by_regime


def chunked_markdown(fits: Sequence[dict]) -> str:
    """The chunked heads' fit diagnostics and weight statistics per regime and arm."""
    if not fits:
        return ""
    lines = ["", "## Chunked heads: fit and weights", ""]
    lines += fit_markdown(pd.DataFrame(fits), ["regime", "head", "arm"])
    lines += [
        "",
        "Means over the paired seeds; largest weight and ESS (fraction of valid steps) over the last "
        f"{FINAL_SHARE:.0%} of training steps (a uniform run's weights are all 1).",
    ]
    return "\n".join(lines) + "\n"


def pair_tables(planned: Planned) -> tuple[list, list, list, dict]:
    """The decision rows (Holm over :data:`PRIMARY`), per-group rows, the figure's compare rows and the missing
    runs of the paired regimes (R1-R3)."""
    from tar_rl.report import compare, load_run

    rows, groups, figure, missing = [], [], [], {}
    screened = planned.screened
    for label, specs in planned.paired.items():
        missing[label] = [s.run_dir.name for s in specs if not s.finished]
        runs = [load_run(s.run_dir) for s in specs if s.finished]
        if label == "R2" and screened is not None:
            for run in runs:
                if list(run.config["data"]["tasks"]) != list(screened):
                    raise SystemExit(f"regimes: {run.name} trained on tasks other than {planned.screening}'s")
        seeds = {r.seed for r in runs if r.objective == BASELINE} & {r.seed for r in runs if r.objective == TREATMENT}
        runs = [r for r in runs if r.seed in seeds]
        if not seeds:
            continue
        check_pairs(runs)
        row, group = regime_rows(label, runs)
        rows.append(row)
        groups.append(group)
        table = compare(runs, file=io.StringIO())
        figure.append(table[table["objective"].isin([BASELINE, TREATMENT])].assign(policy=label))
    for r in rows:
        r["holm_p"] = math.nan
    holm_into([r for r in rows if r["regime"] in PRIMARY], "p_success")
    return rows, groups, figure, missing


def _overall_success(run) -> float:
    from tar_rl.report import run_percent

    return run_percent(run)[("success", "overall")]


def chunked_paired_rows(by_regime: dict[str, dict], heads: dict[str, str]) -> list[dict]:
    """Each chunked-heads regime's TAR arms minus uniform, per seed: ``label`` (``R4 act: tar``), ``group`` (the
    regime), ``seed`` and ``delta`` (overall success, percentage points), regimes and arms in the table's order."""
    rows = []
    for label, loaded in by_regime.items():
        uniform = {r.seed: _overall_success(r) for r in loaded[BASELINE]}
        for arm in CHUNKED_ARMS[1:]:
            for run in loaded[arm]:
                delta = _overall_success(run) - uniform[run.seed]
                rows.append(
                    {"label": f"{label} {heads[label]}: {arm}", "group": label, "seed": run.seed, "delta": delta}
                )
    return rows


def _r6_source(planned: Planned, by_regime: dict[str, dict]) -> list[dict]:
    """R6's per-seed differences, as the ``why_act`` study's table writes them (``r6/paired.csv`` under
    :attr:`Planned.out`; it pairs R6's runs with R4's), or ``[]`` before it has."""
    path = planned.out / R6_FOLDER / PAIRED_CSV
    return pd.read_csv(path).to_dict("records") if path.is_file() else []


def _r7_source(planned: Planned, by_regime: dict[str, dict]) -> list[dict]:
    """R7's per-seed differences (each TAR arm minus uniform with the selected ranking signal), as the
    ``flow_signal`` study's table writes them (``r7/paired.csv`` under :attr:`Planned.out`), or ``[]`` before it
    has."""
    path = planned.out / R7_FOLDER / PAIRED_CSV
    return pd.read_csv(path).to_dict("records") if path.is_file() else []


#: The paired figure's rows beyond R4 and R5, each ``(the planned runs, the chunked regimes' runs per arm by regime)
#: -> rows`` (``label``, ``group``, ``seed``, ``delta``, as :func:`chunked_paired_rows`'s), drawn below them in this
#: order: R6's controls and R7's arms where their runs are present.
PAIRED_SOURCES: tuple[Callable[[Planned, dict], list[dict]], ...] = (_r6_source, _r7_source)


def write_paired_figure(planned: Planned, by_regime: dict[str, dict], dest: Path) -> Path | None:
    """``fig_paired.png``: each chunked arm minus uniform per seed, with the mean and its 95% t CI
    (:func:`tar_rl.report.plot_paired_deltas`), R4 and R5 then :data:`PAIRED_SOURCES`; None without rows."""
    from tar_rl.report import plot_paired_deltas

    rows = chunked_paired_rows(by_regime, planned.heads)
    for source in PAIRED_SOURCES:
        rows += source(planned, by_regime)
    if not rows:
        return None
    regimes = ", ".join(dict.fromkeys(r["group"] for r in rows))
    return plot_paired_deltas(
        pd.DataFrame(rows),
        dest / PAIRED_FIGURE,
        caption=f"{regimes}: overall success of each arm minus uniform's, paired by seed (the decision table's pairs)",
        xlabel="Δ success, arm - uniform (percentage points)",
        title="Each arm minus uniform: seeds (dots), mean and 95% t CI (bar)",
    )


def write_tables(planned: Planned, prov: dict, dest: Path, complete: bool = False) -> str:
    """The decision table (markdown + CSV), per-group CSV, Fig. 3 per regime and per chunked head, and the chunked
    heads' paired differences (:func:`write_paired_figure`) from the finished runs of ``planned``, written into
    ``dest``; returns the markdown.

    ``complete``: refuse a chunked-heads regime with a run of its plan missing (the final table)."""
    from tar_rl.report import plot_success_vs_neps

    rows, groups, figure, missing = pair_tables(planned)
    c_rows, c_groups, c_fits, c_figure, c_missing, c_devices, c_loaded = chunked_tables(planned.chunked, complete)
    rows, groups = rows + c_rows, groups + c_groups
    missing.update(c_missing)
    group_df = pd.concat(groups, ignore_index=True) if groups else pd.DataFrame()
    md = decision_markdown(rows, group_df, missing) + chunked_markdown(c_fits) + by_device_markdown(c_devices)
    tables = {"decision.csv": pd.DataFrame(rows)}
    if len(group_df):
        tables["groups.csv"] = group_df
    write_outputs(dest, {"decision.md": md}, tables, prov)
    if figure:
        fig_table = pd.concat(figure, ignore_index=True)
        plot_success_vs_neps(fig_table, dest / "fig3_regimes.png", caption="regimes as families: uniform -> TAR")
    if c_figure:
        fig_table = pd.concat(c_figure, ignore_index=True)
        caption = "chunked heads (R4 act, R5 flow): uniform -> tar, tar_gentle"
        plot_success_vs_neps(fig_table, dest / "fig3_chunked.png", caption=caption)
    write_paired_figure(planned, c_loaded, dest)
    return md
