"""Where TAR's weight mass lies along a demonstration: per recorded demonstration, each phase's share of the steps
and of the weight (:func:`phase_weight_mass`), and per task the means and the phase with the largest weight per
step (:func:`critical_windows`). Phases anchor at the gripper-closing step (:func:`tar_rl.report.phase_labels`).
"""

from __future__ import annotations

import math
from typing import Any

import pandas as pd

from tar_rl.report.phases import PHASES, first_gripper_close, phase_labels
from tar_rl.report.plots import check_weights_table

__all__ = ["critical_windows", "phase_weight_mass"]


def phase_weight_mass(weights_df: pd.DataFrame, step: int | None = None, **phase_kw) -> pd.DataFrame:
    """Share of steps and of TAR weight mass in each phase, per recorded demonstration.

    Args:
        weights_df: ``weights.csv`` rows (:data:`tar_rl.runs.WEIGHTS_COLUMNS`), optionally with a ``run`` column
            (several runs' recordings concatenated).
        step: the training step of the recording (default: the largest, per run).
        **phase_kw: ``onset`` and ``completion`` of :func:`phase_labels`.

    Returns:
        One row per (run, task, episode, phase): ``steps``, ``step_share`` (steps / T), ``weight_share``
        (sum of the phase's weights / sum of the demonstration's weights) and ``anchor`` (the
        gripper-closing step, ``-1`` without one).

    Raises:
        ValueError: missing columns, no rows, or a recording with no positive weight.
    """
    check_weights_table(weights_df)
    if len(weights_df) == 0:
        raise ValueError("weights table has no rows")
    df = weights_df if "run" in weights_df.columns else weights_df.assign(run="")
    rows = []
    for run, rdf in df.groupby("run", sort=True):
        at = int(rdf["step"].max()) if step is None else step
        rdf = rdf[rdf["step"] == at]
        for (task, episode), one in rdf.groupby(["task", "episode"], sort=True):
            one = one.sort_values("t")
            labels = phase_labels(one["gripper"].to_numpy(), **phase_kw)
            weight = one["weight"].to_numpy(dtype=float)
            total = weight.sum()
            if not total > 0:
                raise ValueError(f"run {run!r}, task {task!r}, episode {episode}: no positive weight recorded")
            anchor = first_gripper_close(one["gripper"].to_numpy())
            for phase in PHASES:
                sel = labels == phase
                rows.append(
                    {
                        "run": run,
                        "task": task,
                        "episode": int(episode),
                        "phase": phase,
                        "steps": int(sel.sum()),
                        "step_share": float(sel.mean()),
                        "weight_share": float(weight[sel].sum() / total),
                        "anchor": -1 if anchor is None else anchor,
                    }
                )
    return pd.DataFrame(rows)


def critical_windows(mass: pd.DataFrame) -> pd.DataFrame:
    """Per task: mean over recorded demonstrations of each phase's weight and step share.

    Args:
        mass: a :func:`phase_weight_mass` table.

    Returns:
        One row per task: ``demos`` (recordings averaged), ``with_anchor`` (how many had a
        gripper-closing step); for each phase ``P``: ``P_weight`` and ``P_steps`` (mean shares) and
        ``P_ratio`` = ``P_weight / P_steps`` (> 1: the phase gets more than a uniform share of the
        weight; ``nan`` for an empty phase); ``peak``, the phase with the largest ratio.
    """
    rows = []
    for task, tdf in mass.groupby("task", sort=True):
        demos = tdf.groupby(["run", "episode"])
        row: dict[str, Any] = {
            "task": task,
            "demos": demos.ngroups,
            "with_anchor": int((demos["anchor"].first() >= 0).sum()),
        }
        best, best_ratio = None, -math.inf
        for phase in PHASES:
            p = tdf[tdf["phase"] == phase]
            wshare, sshare = float(p["weight_share"].mean()), float(p["step_share"].mean())
            ratio = wshare / sshare if sshare > 0 else math.nan
            row[f"{phase}_weight"], row[f"{phase}_steps"], row[f"{phase}_ratio"] = wshare, sshare, ratio
            if math.isfinite(ratio) and ratio > best_ratio:
                best, best_ratio = phase, ratio
        row["peak"] = best or "-"
        rows.append(row)
    return pd.DataFrame(rows)
