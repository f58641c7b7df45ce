"""The studies' output: number formats of the markdown tables, the tables they share (the fit table, the paper's
Table I and Table III), and the files of a table command written atomically (markdown, CSVs rounded to six
decimals, provenance)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import pandas as pd

from tar_rl.report.stats import BASELINE, table_levels
from tar_rl.report.tables import fmt_pm

__all__ = [
    "TABLE_I_COLUMNS",
    "comparison_lines",
    "controls_markdown",
    "fit_markdown",
    "fmt_num",
    "fmt_p",
    "group_lines",
    "groups_and_fit_lines",
    "pending_lines",
    "table_one_markdown",
    "write_outputs",
]


def fmt_num(v: float, digits: int = 1, signed: bool = False) -> str:
    """``v`` with ``digits`` decimals (and its sign with ``signed``) for a markdown table; ``-`` when not finite."""
    if v is None or not math.isfinite(v):
        return "-"
    return f"{v:+.{digits}f}" if signed else f"{v:.{digits}f}"


def fmt_p(p: float) -> str:
    """A p-value for a markdown table: three decimals, ``<0.001`` below that, ``-`` when there is none."""
    if p is None or math.isnan(p):
        return "-"
    return "<0.001" if p < 0.001 else f"{p:.3f}"


def comparison_lines(rows: Sequence[dict]) -> list[str]:
    """A markdown table of :func:`~benchmarks.studies.compare.contrast` rows (with ``holm_p`` where a family has
    one): pairs, success of both arms, Δ with its 95% CI, p, Holm p, MDE, pairs where T is higher, Δ Fast20 and NEPS."""
    lines = [
        "| comparison | pairs | success % T / B | Δ success [95% CI] | p | Holm p | MDE (80%) | T higher | Δ Fast20 "
        "| Δ NEPS |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        ci = f"[{fmt_num(r['d_success_ci_low'], 2, True)}, {fmt_num(r['d_success_ci_high'], 2, True)}]"
        lines.append(
            f"| {r['comparison']} | {r['pairs']} "
            f"| {fmt_num(r['success_treatment'])} / {fmt_num(r['success_baseline'])} "
            f"| {fmt_num(r['d_success'], 2, True)} {ci} | {fmt_p(r['p_success'])} | {fmt_p(r.get('holm_p'))} "
            f"| {fmt_num(r['mde_success'], 2)} | {r['higher']} of {r['pairs']} | {fmt_num(r['d_fast20'], 2, True)} "
            f"| {fmt_num(r['d_neps'], 2, True)} |"
        )
    return lines


def group_lines(groups: pd.DataFrame) -> list[str]:
    """A markdown table of the per-group rows of :func:`~benchmarks.studies.compare.contrast`."""
    lines = ["| comparison | group | pairs | T % | B % | Δ [95% CI] | p |", "|---|---|---|---|---|---|---|"]
    for g in groups.to_dict("records"):
        ci = f"[{fmt_num(g['ci_low'], 2, True)}, {fmt_num(g['ci_high'], 2, True)}]"
        lines.append(
            f"| {g['comparison']} | {g['level']} | {g['n_pairs']} | {fmt_num(g['objective_mean'])} "
            f"| {fmt_num(g['baseline_mean'])} | {fmt_num(g['delta_mean'], 2, True)} {ci} | {fmt_p(g['p_value'])} |"
        )
    return lines


def fit_markdown(fit: pd.DataFrame, keys: Sequence[str]) -> list[str]:
    """A markdown table of :func:`~benchmarks.studies.compare.fit_summary` rows: the columns ``keys`` as they
    are, then the five statistics."""
    head = [*keys, "final train loss", "held-out loss", "alignment", "largest weight", "ESS"]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for r in fit.to_dict("records"):
        cells = [str(r[k]) for k in keys]
        cells += [fmt_num(r["train_loss"], 4), fmt_num(r["heldout_loss"], 4), fmt_num(r["alignment"], 2, True)]
        cells += [fmt_num(r["weight_max"], 2), fmt_num(r["weight_ess"], 2)]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def groups_and_fit_lines(groups: pd.DataFrame, fits: Sequence[dict], final_share: float) -> list[str]:
    """A decision table's sections after its comparisons: success per difficulty group (:func:`group_lines`) and,
    when there are ``fits``, the arms' fit and weights (:func:`fit_markdown` by stage, arm and seeds), their weights
    taken over the last ``final_share`` of training steps."""
    out = ["## Success per difficulty group", "", *group_lines(groups)]
    if fits:
        out += ["", "## Arms: fit and weights", ""]
        out += fit_markdown(pd.DataFrame(fits), ["stage", "arm", "seeds"])
        out += [
            "",
            "Means over the seeds every arm of the stage has; largest weight and ESS (fraction of valid steps) over "
            f"the last {final_share:.0%} of training steps (a uniform run's weights are all 1).",
        ]
    return out


def pending_lines(missing: dict[str, Sequence[str]]) -> list[str]:
    """A decision table's last section: per stage (or regime) with planned runs not finished, how many and the first
    four names; nothing when every run is finished."""
    pending = {k: v for k, v in missing.items() if v}
    if not pending:
        return []
    return [
        "",
        "## Not finished yet",
        "",
        *(f"- {k}: {len(v)} run(s) ({', '.join(v[:4])}{', ...' if len(v) > 4 else ''})" for k, v in pending.items()),
    ]


def write_outputs(dest: Path, texts: dict[str, str], tables: dict[str, pd.DataFrame], prov: dict | None) -> None:
    """Write ``texts`` (name -> markdown) and ``tables`` (name -> CSV, rounded to six decimals) into ``dest``
    atomically, and ``prov`` as ``provenance.json`` when given."""
    from tar_rl.io import atomic_write, write_csv_atomic, write_json_atomic

    dest.mkdir(parents=True, exist_ok=True)
    for name, text in texts.items():
        atomic_write(dest / name, lambda f, text=text: f.write(text))
    for name, table in tables.items():
        write_csv_atomic(table.round(6), dest / name)
    if prov is not None:
        write_json_atomic(prov, dest / "provenance.json")


#: Table I's columns: ``(metric, level)`` and their headers.
TABLE_I_COLUMNS: tuple[tuple[str, str, str], ...] = (
    ("success", "easy", "Easy"),
    ("success", "medium", "Medium"),
    ("success", "hard", "Hard"),
    ("success", "very_hard", "Very Hard"),
    ("success", "overall", "Overall"),
    ("fast20", "overall", "100 x Fast20 ↓"),
    ("neps", "overall", "100 x NEPS ↓"),
)


def _cell(paired: pd.DataFrame, policy: str, objective: str, metric: str, level: str) -> dict | None:
    match = paired[
        (paired["policy"] == policy)
        & (paired["objective"] == objective)
        & (paired["metric"] == metric)
        & (paired["level"] == level)
    ]
    return None if match.empty else match.iloc[0].to_dict()


def table_one_markdown(paired: pd.DataFrame, objective: str = "tar") -> str:
    """The paper's Table I from a :func:`~tar_rl.report.paired_table`: per policy, baseline, objective, difference.

    Three rows per policy: the baseline and the objective (mean ± std over the paired seeds), then
    ``Δ`` (objective - baseline; mean and 95% CI over seeds) and a row of paired t-test p-values.
    Columns: success per difficulty group and overall (%), 100 x Fast20 and 100 x NEPS (lower is
    better). ``-``: no finite pair (e.g. NEPS with no success).

    Args:
        paired: a :func:`~tar_rl.report.paired_table`.
        objective: the treatment shown (default ``tar``).

    Returns:
        A markdown table (no trailing newline).
    """
    header = "| policy | row | pairs | " + " | ".join(h for _, _, h in TABLE_I_COLUMNS) + " |"
    lines = [header, "|" + "---|" * (3 + len(TABLE_I_COLUMNS))]
    for policy in sorted(paired["policy"].unique()):
        cells = [_cell(paired, policy, objective, m, lv) for m, lv, _ in TABLE_I_COLUMNS]
        if all(c is None for c in cells):
            continue
        n = max((c["n_pairs"] for c in cells if c is not None), default=0)
        base = next((c["baseline"] for c in cells if c is not None), BASELINE)

        def fmt(c, kind):
            if c is None or c["n_pairs"] == 0:
                return "-"
            if kind == "base":
                return fmt_pm(c["baseline_mean"], c["baseline_std"])
            if kind == "obj":
                return fmt_pm(c["objective_mean"], c["objective_std"])
            if kind == "delta":
                ci = "" if math.isnan(c["ci_low"]) else f" [{c['ci_low']:+.2f}, {c['ci_high']:+.2f}]"
                return f"{c['delta_mean']:+.2f}{ci}"
            return fmt_p(c["p_value"])

        for label, kind in (
            (base, "base"),
            (objective, "obj"),
            (f"Δ {objective} - {base} [95% CI]", "delta"),
            ("p (paired t)", "p"),
        ):
            lines.append(f"| {policy} | {label} | {n} | " + " | ".join(fmt(c, kind) for c in cells) + " |")
    return "\n".join(lines)


def controls_markdown(paired: pd.DataFrame, table: pd.DataFrame, policy: str) -> str:
    """The paper's Table III for one policy: success per group and overall for every objective.

    Args:
        paired: a :func:`~tar_rl.report.paired_table` (differences to ``uniform``).
        table: a :func:`~tar_rl.report.compare` table of the same runs (means ± std over each objective's seeds).
        policy: the policy family shown.

    Returns:
        A markdown table: one row per objective (``uniform`` first), success % per difficulty group
        and overall (mean ± std over seeds), the seeds, and the paired difference of the overall
        success to ``uniform`` with its 95% CI and p-value.
    """
    levels = [lv for lv in table_levels(table) if lv != "overall"] + ["overall"]
    header = "| objective | seeds | " + " | ".join(lv.replace("_", " ") for lv in levels)
    lines = [header + " | Δ overall vs uniform [95% CI] | p |", "|" + "---|" * (4 + len(levels))]
    rows = table[table["policy"] == policy]
    for rec in rows.to_dict("records"):
        cells = [
            fmt_pm(rec.get(f"success_{lv}_mean", math.nan), rec.get(f"success_{lv}_std", math.nan)) for lv in levels
        ]
        c = _cell(paired, policy, rec["objective"], "success", "overall")
        if c is None or c["n_pairs"] == 0:
            delta, p = "-", "-"
        else:
            ci = "" if math.isnan(c["ci_low"]) else f" [{c['ci_low']:+.2f}, {c['ci_high']:+.2f}]"
            delta, p = f"{c['delta_mean']:+.2f}{ci} (n={c['n_pairs']})", fmt_p(c["p_value"])
        lines.append(f"| {rec['objective']} | {rec['n_seeds']} | " + " | ".join(cells) + f" | {delta} | {p} |")
    return "\n".join(lines)
