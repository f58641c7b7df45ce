"""The studies' figures, from their tables: Fig. 3(c) (:func:`plot_group_deltas`), Fig. 4 (:func:`plot_radar`),
the critical windows and Fig. 5 with phases (:func:`plot_critical_windows`, :func:`plot_weight_phases`), the budget
curve (:func:`plot_lines`) and the sensitivity grid (:func:`plot_heatmaps`). Built on the figure helpers of
:mod:`tar_rl.report.plots`; the studies (``benchmarks/studies``) and their analyses (``benchmarks/analysis``) draw
with them.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from tar_rl.report.phases import PHASES, first_gripper_close, phase_labels
from tar_rl.report.plots import (
    check_table,
    check_weights_table,
    new_figure,
    provenance,
    save_png,
    true_spans,
    zero_nan,
)
from tar_rl.report.stats import BASELINE, objective_key, table_levels

__all__ = [
    "plot_critical_windows",
    "plot_group_deltas",
    "plot_heatmaps",
    "plot_lines",
    "plot_radar",
    "plot_weight_phases",
]


def plot_radar(
    table: pd.DataFrame, path: str | os.PathLike, objective: str = "tar", caption: str | None = None
) -> Path:
    """The paper's Fig. 4: a radar over overall and group success and the efficiency spokes.

    Spokes: ``O`` (overall success), the difficulty groups present (``E``, ``M``, ``H``, ``VH``),
    ``F20`` (100 x Fast20) and ``N`` (100 x NEPS). Each spoke is rescaled to [0.1, 1] by the min and
    max of the plotted values on it, and the efficiency spokes are inverted (outer = lower cost).
    Dashed grey: ``uniform``; solid colour: ``objective``; one faint outline per policy and a thick
    mean over policies.

    Args:
        table: a :func:`~tar_rl.report.compare` table holding ``uniform`` and ``objective`` rows.
        path: the PNG to write (atomically).
        objective: the treatment drawn against ``uniform``.
        caption: provenance text for the footer.

    Returns:
        ``path``.

    Raises:
        ValueError: not a :func:`~tar_rl.report.compare` table, or no policy with both objectives.
    """
    check_table(table, ["policy", "objective", "success_overall_mean", "fast20_overall_mean", "neps_overall_mean"])
    short = {"overall": "O", "easy": "E", "medium": "M", "hard": "H", "very_hard": "VH"}
    levels = table_levels(table)
    spokes = [(f"success_{lv}_mean", short.get(lv, lv), False) for lv in levels]
    spokes += [("fast20_overall_mean", "F20", True), ("neps_overall_mean", "N", True)]
    policies = [
        p
        for p in sorted(table["policy"].unique())
        if {BASELINE, objective} <= set(table.loc[table["policy"] == p, "objective"])
    ]
    if not policies:
        raise ValueError(f"no policy has both {BASELINE!r} and {objective!r} rows: nothing to draw")
    rows = table[table["policy"].isin(policies) & table["objective"].isin([BASELINE, objective])]
    raw = rows[[c for c, _, _ in spokes]].to_numpy(dtype=float)
    finite = np.isfinite(raw)
    lo = np.where(finite.any(0), np.where(finite, raw, np.inf).min(0), 0.0)
    hi = np.where(finite.any(0), np.where(finite, raw, -np.inf).max(0), 0.0)
    inverted = np.array([inv for _, _, inv in spokes])

    def scaled(rec) -> np.ndarray:
        """Rescaled spoke values; a non-finite value (NEPS without success) sits at the centre."""
        v = np.array([float(rec[c]) for c, _, _ in spokes])
        ok = np.isfinite(v)
        s = (np.where(ok, v, lo) - lo) / np.where(hi > lo, hi - lo, 1.0)
        s = np.where(inverted, 1 - s, s)
        s = np.where(hi > lo, s, 0.5)
        return np.where(ok, 0.1 + 0.9 * s, 0.0)

    angles = np.linspace(0, 2 * np.pi, len(spokes), endpoint=False)
    closed = np.append(angles, angles[0])
    fig = new_figure(6.0, 6.0)
    fig.subplots_adjust(left=0.1, right=0.9, top=0.86, bottom=0.12)
    ax = fig.add_subplot(projection="polar")
    means = {BASELINE: [], objective: []}
    for policy in policies:
        for obj in (BASELINE, objective):
            rec = rows[(rows["policy"] == policy) & (rows["objective"] == obj)].iloc[0]
            s = scaled(rec)
            means[obj].append(s)
            style = {"color": "0.5", "linestyle": "--"} if obj == BASELINE else {"color": "C3", "linestyle": "-"}
            if len(policies) > 1:
                ax.plot(closed, np.append(s, s[0]), linewidth=0.8, alpha=0.35, **style)
    for obj in (BASELINE, objective):
        m = np.mean(means[obj], axis=0)
        style = {"color": "0.4", "linestyle": "--"} if obj == BASELINE else {"color": "C3", "linestyle": "-"}
        ax.plot(closed, np.append(m, m[0]), linewidth=2.2, label=f"{obj} (mean over {len(policies)} policies)", **style)
        if obj != BASELINE:
            ax.fill(closed, np.append(m, m[0]), color="C3", alpha=0.08)
    ax.set_xticks(angles, [s for _, s, _ in spokes])
    ax.set_ylim(0, 1.05)
    ax.set_yticklabels([])
    ax.set_title("Per-spoke rescaled; F20 and N inverted (outer = lower cost)", fontsize=9)
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.04), fontsize=8, ncol=2, frameon=False)
    return save_png(fig, path, caption or provenance(rows))


_PHASE_COLOURS = {"approach": "C0", "contact_onset": "C3", "transport": "C2", "completion": "C4"}


def plot_critical_windows(windows: pd.DataFrame, path: str | os.PathLike, caption: str = "") -> Path:
    """Stacked bars per task: share of TAR weight mass per phase, with each phase's share of steps as ticks.

    Args:
        windows: a :func:`critical_windows` table.
        path: the PNG to write (atomically).
        caption: provenance text for the footer.

    Returns:
        ``path``.
    """
    if len(windows) == 0:
        raise ValueError("the critical-window table is empty: nothing to plot")
    from matplotlib.patches import Patch

    n = len(windows)
    fig = new_figure(8.0, max(2.8, 0.38 * n + 1.8))
    fig.subplots_adjust(left=0.28, right=0.97, top=0.86, bottom=0.18)
    ax = fig.add_subplot()
    y = np.arange(n)
    left = np.zeros(n)
    step_left = np.zeros(n)
    for phase in PHASES:
        share = windows[f"{phase}_weight"].to_numpy(dtype=float)
        steps = windows[f"{phase}_steps"].to_numpy(dtype=float)
        ax.barh(y, share, left=left, color=_PHASE_COLOURS[phase], alpha=0.75, height=0.6)
        step_left += steps
        ax.plot(step_left, y, linestyle="none", marker="|", markersize=14, color="k")
        left += share
    ax.set_yticks(y, [f"{t} ({d})" for t, d in zip(windows["task"], windows["demos"])], fontsize=8)
    ax.invert_yaxis()
    ax.set_xlim(0, 1)
    ax.set_xlabel("share of TAR weight mass (bars); phase boundaries by share of steps (ticks)")
    handles = [Patch(color=_PHASE_COLOURS[p], alpha=0.75, label=p.replace("_", " ")) for p in PHASES]
    fig.legend(handles=handles, loc="upper center", ncol=4, fontsize=8, frameon=False)
    return save_png(fig, path, caption or "critical windows")


def _draw_demonstration(ax, one: pd.DataFrame, task: str, gripper: bool, phase_kw: dict) -> None:
    """One panel of :func:`plot_weight_phases`: a demonstration's loss, weight, phases and gripper-closing step."""
    t = one["t"].to_numpy()
    loss, weight = one["loss"].to_numpy(dtype=float), one["weight"].to_numpy(dtype=float)
    labels = phase_labels(one["gripper"].to_numpy(), **phase_kw)
    ax_w = ax.twinx()
    for a, b in true_spans(weight > 1.0):
        ax.axvspan(t[a] - 0.5, t[b] + 0.5, color="C1", alpha=0.2, linewidth=0)
    top = max(float(loss.max()), 1e-12)
    for phase in PHASES:
        for a, b in true_spans(labels == phase):
            ax.axvspan(t[a] - 0.5, t[b] + 0.5, ymin=0, ymax=0.05, color=_PHASE_COLOURS[phase], alpha=0.9, linewidth=0)
    ax.plot(t, loss, color="C0", linewidth=1.1)
    ax_w.plot(t, weight, color="C3", linewidth=1.1)
    ax_w.axhline(1.0, color="C3", linestyle=":", linewidth=0.8)
    close = first_gripper_close(one["gripper"].to_numpy())
    if close is not None:
        ax.axvline(t[close], color="k", linestyle="--", linewidth=0.9)
    ax.set_ylim(0, top * 1.1)
    ax_w.set_ylim(bottom=0)
    if gripper:
        ax_g = ax.twinx()
        ax_g.spines["right"].set_position(("axes", 1.12))
        ax_g.plot(t, one["gripper"].to_numpy(dtype=float), color="0.5", linewidth=0.9, drawstyle="steps-mid")
        ax_g.set_ylim(-1.3, 1.1)
        ax_g.set_ylabel("gripper action", color="0.4", fontsize=8)
    ax.set_ylabel("loss", color="C0", fontsize=8)
    ax_w.set_ylabel("TAR weight", color="C3", fontsize=8)
    anchor = f"gripper closes at t = {t[close]}" if close is not None else "no gripper closing: no contact anchor"
    ax.set_title(f"{task}, episode {int(one['episode'].iloc[0])} ({anchor})", fontsize=9)


def plot_weight_phases(
    weights_df: pd.DataFrame,
    path: str | os.PathLike,
    tasks: Sequence[str],
    step: int | None = None,
    caption: str = "",
    gripper: bool = False,
    **phase_kw,
) -> Path:
    """The paper's Fig. 5: per-step loss and TAR weight along one demonstration per task, with phases.

    One panel per task (its lowest recorded episode): loss (left axis), weight (right axis, with the
    ``w = 1`` line), time windows with weight > 1 shaded, the phases of :func:`phase_labels`
    (approach, contact onset, transport, completion) as coloured bands under the curves, and the
    gripper-closing step as a dashed line.

    Args:
        weights_df: ``weights.csv`` rows of one run.
        path: the PNG to write (atomically).
        tasks: the tasks, one panel each.
        step: the training step of the recording (default: the largest).
        caption: provenance text for the footer.
        gripper: also draw the gripper action (grey, on an axis of its own at the far right).
        **phase_kw: ``onset`` and ``completion`` of :func:`phase_labels`.

    Returns:
        ``path``.

    Raises:
        ValueError: no tasks, missing columns, or a task without a recording (the available ones are listed).
    """
    check_weights_table(weights_df)
    if not tasks:
        raise ValueError("name at least one task to plot")
    step = int(weights_df["step"].max()) if step is None else step
    df = weights_df[weights_df["step"] == step]
    for task in tasks:
        if task not in set(df["task"]):
            raise ValueError(f"no weights for task {task!r} at step {step}; tasks: {sorted(df['task'].unique())}")
    from matplotlib.patches import Patch

    height = 2.6 * len(tasks) + 1.2
    fig = new_figure(8.0, height)
    right = 0.82 if gripper else 0.9
    fig.subplots_adjust(left=0.12, right=right, top=1 - 0.5 / height, bottom=0.75 / height, hspace=0.55)
    axes = fig.subplots(len(tasks), 1, squeeze=False)[:, 0]
    for ax, task in zip(axes, tasks):
        tdf = df[df["task"] == task]
        _draw_demonstration(ax, tdf[tdf["episode"] == tdf["episode"].min()].sort_values("t"), task, gripper, phase_kw)
    axes[-1].set_xlabel(f"time step t along the demonstration (weights at training step {step})")
    handles = [Patch(color="C1", alpha=0.2, label="weight > 1")]
    handles += [Patch(color=_PHASE_COLOURS[p], label=p.replace("_", " ")) for p in PHASES]
    fig.legend(handles=handles, loc="upper center", ncol=5, fontsize=8, frameon=False)
    return save_png(fig, path, caption or f"weights at step {step}")


def plot_lines(
    df: pd.DataFrame, path: str | os.PathLike, x: str, xlabel: str, ylabel: str, title: str, caption: str = ""
) -> Path:
    """Mean ± std lines, one per ``objective`` (e.g. the budget curve: success vs demonstrations per task).

    Args:
        df: columns ``objective``, ``x``, ``mean``, ``std``.
        path: the PNG to write (atomically).
        x: the x column; drawn on a log axis when all values are positive and span a factor >= 10.
        xlabel, ylabel, title: labels.
        caption: provenance text for the footer.

    Returns:
        ``path``.
    """
    if len(df) == 0:
        raise ValueError("nothing to plot: the table is empty")
    fig = new_figure(6.5, 4.4)
    fig.subplots_adjust(left=0.12, right=0.97, top=0.9, bottom=0.16)
    ax = fig.add_subplot()
    for i, (objective, odf) in enumerate(sorted(df.groupby("objective"), key=lambda kv: objective_key(kv[0]))):
        odf = odf.sort_values(x)
        ax.errorbar(
            odf[x],
            odf["mean"],
            yerr=np.nan_to_num(odf["std"].to_numpy(dtype=float)),
            marker="o",
            capsize=3,
            color=f"C{i}",
            label=objective,
        )
    xs = df[x].to_numpy(dtype=float)
    if (xs > 0).all() and xs.max() >= 10 * xs.min():
        ax.set_xscale("log")
    ax.set_xticks(sorted(set(xs)), [f"{v:g}" for v in sorted(set(xs))])
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=10)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    return save_png(fig, path, caption or title)


def plot_heatmaps(
    df: pd.DataFrame, path: str | os.PathLike, row: str, col: str, panel: str, value: str, title: str, caption: str = ""
) -> Path:
    """Annotated heat maps of ``value`` over ``row`` x ``col``, one panel per ``panel`` value (the sensitivity grid).

    Args:
        df: one row per cell with the columns named.
        path: the PNG to write (atomically).
        row, col, panel, value: column names.
        title: figure title.
        caption: provenance text for the footer.

    Returns:
        ``path``.
    """
    if len(df) == 0:
        raise ValueError("nothing to plot: the table is empty")
    panels = sorted(df[panel].unique(), key=str)
    fig = new_figure(max(4.5, 3.6 * len(panels) + 1.0), 4.0)
    fig.subplots_adjust(left=0.1, right=0.95, top=0.82, bottom=0.2, wspace=0.35)
    axes = fig.subplots(1, len(panels), squeeze=False)[0]
    finite = df[value].to_numpy(dtype=float)
    finite = finite[np.isfinite(finite)]
    bound = float(np.abs(finite).max()) if finite.size else 1.0
    bound = bound or 1.0
    for ax, p in zip(axes, panels):
        sub = df[df[panel] == p].pivot_table(index=row, columns=col, values=value, aggfunc="mean")
        ax.imshow(sub.to_numpy(dtype=float), cmap="RdBu", vmin=-bound, vmax=bound, aspect="auto")
        ax.set_xticks(range(sub.shape[1]), [f"{v:g}" for v in sub.columns])
        ax.set_yticks(range(sub.shape[0]), [f"{v:g}" for v in sub.index])
        ax.set_xlabel(col)
        ax.set_ylabel(row)
        ax.set_title(f"{panel} = {p}", fontsize=9)
        for i in range(sub.shape[0]):
            for j in range(sub.shape[1]):
                v = sub.iat[i, j]
                ax.text(j, i, "-" if not np.isfinite(v) else f"{v:+.1f}", ha="center", va="center", fontsize=8)
    fig.suptitle(title, fontsize=10)
    return save_png(fig, path, caption or title)


def plot_group_deltas(
    paired: pd.DataFrame, path: str | os.PathLike, objective: str = "tar", caption: str | None = None
) -> Path:
    """The paper's Fig. 3(c): per difficulty group, Δ success (bars) and Δ 100 x Fast20 (line).

    Bars: the paired difference of success (objective - baseline, percentage points), averaged over
    policies; error bars: the 95% CI over seeds with one policy, the std over policies with several
    (the paper's across-family variability). Line (right axis): baseline - objective of 100 x Fast20
    (positive = the objective is faster), averaged over policies.

    Args:
        paired: a :func:`~tar_rl.report.paired_table`.
        path: the PNG to write (atomically).
        objective: the treatment shown.
        caption: provenance text for the footer.

    Returns:
        ``path``.

    Raises:
        ValueError: no rows for ``objective``.
    """
    rows = paired[(paired["objective"] == objective) & (paired["n_pairs"] > 0)]
    if rows.empty:
        raise ValueError(f"no paired rows for objective {objective!r}: nothing to plot")
    levels = [lv for lv in dict.fromkeys(rows["level"]) if lv != "overall"] + ["overall"]
    policies = sorted(rows["policy"].unique())
    bars, errs, line = [], [], []
    for level in levels:
        s = rows[(rows["metric"] == "success") & (rows["level"] == level)]
        f = rows[(rows["metric"] == "fast20") & (rows["level"] == level)]
        bars.append(float(s["delta_mean"].mean()) if len(s) else math.nan)
        if len(policies) == 1 and len(s):
            errs.append(zero_nan(float(s["ci_high"].iloc[0] - s["delta_mean"].iloc[0])))
        else:
            errs.append(zero_nan(float(s["delta_mean"].std(ddof=1))) if len(s) > 1 else 0.0)
        line.append(-float(f["delta_mean"].mean()) if len(f) else math.nan)
    fig = new_figure(6.5, 4.2)
    fig.subplots_adjust(left=0.12, right=0.87, top=0.9, bottom=0.17)
    ax = fig.add_subplot()
    x = np.arange(len(levels))
    ax.bar(x, np.nan_to_num(bars), yerr=errs, capsize=3, color="C0", alpha=0.8)
    ax.axhline(0, color="0.3", linewidth=0.8)
    ax_f = ax.twinx()
    ax_f.plot(x, line, color="C3", marker="o")
    ax.set_xticks(x, [lv.replace("_", " ") for lv in levels])
    ax.set_ylabel(f"Δ success ({objective} - {BASELINE}, pp)")
    ax_f.set_ylabel(f"Δ 100 x Fast20 ({BASELINE} - {objective})", color="C3")
    spread = "95% CI over seeds" if len(policies) == 1 else f"std over {len(policies)} policies"
    ax.set_title(f"Per-group effect of {objective} (bars: mean, error: {spread})", fontsize=10)
    ax.grid(True, axis="y", alpha=0.3)
    return save_png(fig, path, caption or f"paired differences, {len(policies)} policies")
