"""Text tables ``tar-rl report`` prints: one row per run, the comparison over seeds and the paired differences.

Cells are strings: numbers with one decimal (two for differences), ``mean ± std`` where a std exists,
``inf`` for an infinite value and ``-`` for a missing one.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import pandas as pd

from tar_rl.metrics import METRIC_COLUMNS
from tar_rl.report.load import Run
from tar_rl.report.stats import BASELINE, run_percent, table_levels

__all__ = ["display_comparison", "display_pairs", "fmt_pm", "runs_table"]


_LABELS = {"success": "success %", "fast20": "100 x Fast20", "neps": "100 x NEPS"}


def _fmt(value: float, digits: int = 1) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    return "inf" if math.isinf(value) else f"{value:.{digits}f}"


def fmt_pm(mean: float, std: float) -> str:
    text = _fmt(mean)
    return text if math.isnan(std) else f"{text} ± {std:.1f}"


def runs_table(runs: Sequence[Run]) -> pd.DataFrame:
    """One row per run, for printing: name, objective, policy, seed, steps, status, overall metrics (%)."""
    rows = []
    for run in runs:
        row = {
            "run": run.name,
            "objective": run.objective,
            "policy": run.policy,
            "seed": run.seed,
            "steps": "-" if run.steps is None else run.steps,
            "status": "finished" if run.finished else "not evaluated" if run.not_evaluated else "unfinished",
        }
        overall = run_percent(run) if run.finished else {}
        for metric in METRIC_COLUMNS:
            row[_LABELS[metric]] = _fmt(overall.get((metric, "overall"), math.nan))
        rows.append(row)
    return pd.DataFrame(rows)


def display_comparison(table: pd.DataFrame) -> pd.DataFrame:
    levels = table_levels(table)
    rows = []
    for rec in table.to_dict("records"):
        row = {"policy": rec["policy"], "objective": rec["objective"], "seeds": rec["n_seeds"]}
        for metric in METRIC_COLUMNS:
            row[_LABELS[metric]] = fmt_pm(rec[f"{metric}_overall_mean"], rec[f"{metric}_overall_std"])
        for level in levels[1:]:
            row[f"success {level}"] = fmt_pm(rec[f"success_{level}_mean"], rec[f"success_{level}_std"])
        rows.append(row)
    return pd.DataFrame(rows)


def display_pairs(table: pd.DataFrame) -> pd.DataFrame:
    rows = []
    for rec in table[table["objective"] != BASELINE].to_dict("records"):
        rows.append(
            {
                "policy": rec["policy"],
                "objective": rec["objective"],
                "pairs": rec["n_pairs"],
                "Δ success (pp)": _fmt(rec["delta_success"], 2),
                "Δ 100 x Fast20": _fmt(rec["delta_fast20"], 2),
                "Δ 100 x NEPS": _fmt(rec["delta_neps"], 2),
            }
        )
    return pd.DataFrame(rows)
