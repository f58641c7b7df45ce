"""The figures ``tar-rl report`` draws, and the figure helpers other reports share.

* :func:`plot_success_vs_neps` (the paper's Fig. 3), :func:`plot_group_bars` and :func:`plot_weights`
  (Fig. 5) write PNG figures atomically, with the run names and git commits in a footer.
* :func:`plot_paired_deltas` draws paired differences (each arm minus its baseline, per seed) with their mean and
  95% t CI (:func:`paired_summary`, the numbers it draws; :func:`draw_paired_deltas` onto a given figure).
* :func:`new_figure` and :func:`save_png` make and write a figure; :func:`provenance` is the default
  footer of a :func:`tar_rl.report.compare` table's figure.

Matplotlib is imported only by the plotting functions, which draw with the Agg canvas directly
(``matplotlib.figure.Figure`` + ``FigureCanvasAgg``): no display is needed and a caller's pyplot
backend is left alone.
"""

from __future__ import annotations

import io
import math
import os
import textwrap
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from tar_rl.io import atomic_write
from tar_rl.report.phases import first_gripper_close
from tar_rl.report.stats import BASELINE, objective_key, paired_t, table_levels
from tar_rl.runs import WEIGHTS_COLUMNS

__all__ = [
    "PAIRED_SUMMARY_COLUMNS",
    "check_table",
    "check_weights_table",
    "draw_paired_deltas",
    "new_figure",
    "paired_summary",
    "plot_group_bars",
    "plot_paired_deltas",
    "plot_success_vs_neps",
    "plot_weights",
    "provenance",
    "save_png",
    "true_spans",
    "zero_nan",
]


def new_figure(width: float, height: float):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), dpi=120)
    FigureCanvasAgg(fig)
    return fig


def provenance(table: pd.DataFrame) -> str:
    names = [n for cell in table["runs"] for n in str(cell).split(";")] if "runs" in table.columns else []
    commits = list(dict.fromkeys(c for cell in table.get("git_commits", []) for c in str(cell).split(";")))
    shown = ", ".join(names[:8]) + (f" (+{len(names) - 8} more)" if len(names) > 8 else "")
    commit_text = ", ".join(c[:10] for c in commits[:4]) + (" ..." if len(commits) > 4 else "")
    return f"runs: {shown or '?'} | git: {commit_text or 'unknown'}"


def save_png(fig, path: str | os.PathLike, footer: str) -> Path:
    """Write ``fig`` as a PNG atomically (temporary file in the same folder, then ``os.replace``)."""
    width, height = fig.get_size_inches()
    lines = textwrap.wrap(footer, width=max(40, int(width * 19))) or [""]  # ~19 characters per inch at 6 pt
    if len(lines) > 1:  # make room: one 6-pt line is about 8 pt high
        extra = (len(lines) - 1) * 8 / 72 / height
        fig.subplots_adjust(bottom=fig.subplotpars.bottom + extra)
    fig.text(0.01, 0.005, "\n".join(lines), fontsize=6, color="0.35", ha="left", va="bottom")
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png")
    return atomic_write(path, lambda f: f.write(buffer.getvalue()), binary=True)


def check_table(table: pd.DataFrame, columns: Sequence[str]) -> None:
    missing = [c for c in columns if c not in table.columns]
    if missing:
        raise ValueError(f"the table is missing the column(s) {missing}; expected a compare() table")
    if len(table) == 0:
        raise ValueError("the comparison table is empty: nothing to plot")


def check_weights_table(weights_df: pd.DataFrame) -> None:
    """Raise ``ValueError`` unless ``weights_df`` has the ``weights.csv`` columns (``tar_rl.runs.WEIGHTS_COLUMNS``)."""
    missing = [c for c in WEIGHTS_COLUMNS if c not in weights_df.columns]
    if missing:
        raise ValueError(f"weights table is missing the column(s) {missing}; expected {list(WEIGHTS_COLUMNS)}")


def zero_nan(value: float) -> float:
    return 0.0 if math.isnan(value) else value


def plot_success_vs_neps(table: pd.DataFrame, path: str | os.PathLike, caption: str | None = None) -> Path:
    """The paper's Fig. 3: success against normalised deployment cost, one marker per (policy, objective).

    x = ``100 x NEPS`` (lower is better), y = success % (overall means over seeds, error bars one std
    over seeds); colour = objective, marker shape = policy, ``uniform`` drawn unfilled. An arrow goes
    from each policy's ``uniform`` point to each of its other objectives. Points with infinite NEPS
    cannot be placed and are named in the footer instead.

    Args:
        table: a :func:`~tar_rl.report.compare` table.
        path: the PNG to write (atomically).
        caption: provenance text for the footer (default: the table's run names and git commits).

    Returns:
        ``path``.

    Raises:
        ValueError: not a :func:`~tar_rl.report.compare` table, or an empty one.
    """
    need = [
        "policy",
        "objective",
        "success_overall_mean",
        "success_overall_std",
        "neps_overall_mean",
        "neps_overall_std",
    ]
    check_table(table, need)
    fig = new_figure(7.0, 5.2)
    fig.subplots_adjust(left=0.1, right=0.97, top=0.92, bottom=0.14)
    ax = fig.add_subplot()
    objectives = sorted(table["objective"].unique(), key=objective_key)
    policies = sorted(table["policy"].unique())
    colours = {o: f"C{i % 10}" for i, o in enumerate(objectives)}
    markers = dict(zip(policies, "osD^vP*X<>" * 4))
    points, hidden = _draw_points(ax, table, colours, markers)
    for (policy, objective), (x, y) in points.items():
        start = points.get((policy, BASELINE))
        if objective == BASELINE or start is None or start == (x, y):
            continue
        ax.annotate(
            "",
            xy=(x, y),
            xytext=start,
            arrowprops={"arrowstyle": "->", "color": colours[objective], "shrinkA": 6, "shrinkB": 6, "lw": 1.2},
        )
    ax.legend(handles=_point_legend(objectives, policies, colours, markers), loc="best", fontsize=8, frameon=True)
    ax.set_xlabel("100 x NEPS (normalised steps per success; lower is better)")
    ax.set_ylabel("success rate (%; higher is better)")
    ax.set_title("Success vs deployment cost (mean over seeds; arrows: uniform -> objective)", fontsize=10)
    ax.grid(True, alpha=0.3)
    footer = caption or provenance(table)
    if hidden:
        footer += f" | not shown (NEPS inf): {', '.join(hidden)}"
    return save_png(fig, path, footer)


def _draw_points(ax, table: pd.DataFrame, colours: dict, markers: dict) -> tuple[dict, list[str]]:
    """One marker with error bars per row of a :func:`~tar_rl.report.compare` table at (NEPS, success).

    Returns:
        ``(policy, objective) -> (x, y)`` of the drawn points, and ``policy/objective`` of the rows
        with a non-finite mean (not drawn).
    """
    hidden, points = [], {}
    for rec in table.to_dict("records"):
        x, y = rec["neps_overall_mean"], rec["success_overall_mean"]
        if not (math.isfinite(x) and math.isfinite(y)):
            hidden.append(f"{rec['policy']}/{rec['objective']}")
            continue
        points[(rec["policy"], rec["objective"])] = (x, y)
        colour = colours[rec["objective"]]
        ax.errorbar(
            x,
            y,
            xerr=zero_nan(rec["neps_overall_std"]),
            yerr=zero_nan(rec["success_overall_std"]),
            fmt="none",
            ecolor=colour,
            alpha=0.4,
            capsize=2,
            linewidth=1,
        )
        ax.plot(
            [x],
            [y],
            linestyle="none",
            marker=markers[rec["policy"]],
            markersize=9,
            markeredgecolor=colour,
            markeredgewidth=1.8,
            markerfacecolor="white" if rec["objective"] == BASELINE else colour,
        )
    return points, hidden


def _point_legend(objectives: list[str], policies: list[str], colours: dict, markers: dict) -> list:
    """Legend entries: a colour per objective (``uniform`` unfilled), and a marker per policy when there are several."""
    from matplotlib.lines import Line2D

    handles = [
        Line2D(
            [],
            [],
            linestyle="none",
            marker="o",
            markersize=8,
            markeredgecolor=colours[o],
            markerfacecolor="white" if o == BASELINE else colours[o],
            label=o,
        )
        for o in objectives
    ]
    if len(policies) > 1:
        handles += [
            Line2D([], [], linestyle="none", marker=markers[p], color="0.3", label=f"policy: {p}") for p in policies
        ]
    return handles


def plot_group_bars(table: pd.DataFrame, path: str | os.PathLike, caption: str | None = None) -> Path:
    """Success per difficulty group (and overall): bars per objective, one panel per policy.

    Bar height is the mean over seeds, the error bar one standard deviation over seeds. Arguments,
    return value and errors as :func:`plot_success_vs_neps`.
    """
    check_table(table, ["policy", "objective", "success_overall_mean"])
    levels = table_levels(table)
    levels = [lv for lv in levels if lv != "overall"] + ["overall"]
    policies = sorted(table["policy"].unique())
    objectives = sorted(table["objective"].unique(), key=objective_key)
    colours = {o: f"C{i % 10}" for i, o in enumerate(objectives)}
    fig = new_figure(max(6.0, 1.1 * len(levels) * len(policies) + 2.0), 4.6)
    fig.subplots_adjust(left=0.08, right=0.98, top=0.88, bottom=0.17, wspace=0.08)
    axes = fig.subplots(1, len(policies), sharey=True, squeeze=False)[0]
    x = np.arange(len(levels))
    for ax, policy in zip(axes, policies):
        rows = table[table["policy"] == policy].set_index("objective")
        present = [o for o in objectives if o in rows.index]
        width = 0.8 / max(len(present), 1)
        for i, objective in enumerate(present):
            rec = rows.loc[objective]
            means = [rec.get(f"success_{lv}_mean", math.nan) for lv in levels]
            stds = [zero_nan(rec.get(f"success_{lv}_std", math.nan)) for lv in levels]
            ax.bar(
                x + (i - (len(present) - 1) / 2) * width,
                np.nan_to_num(means),
                width,
                yerr=stds,
                capsize=2,
                color=colours[objective],
                label=objective,
                error_kw={"elinewidth": 0.8, "alpha": 0.7},
            )
        ax.set_xticks(x, [lv.replace("_", " ") for lv in levels], fontsize=8)
        ax.set_title(f"policy: {policy}", fontsize=9)
        ax.set_ylim(0, 105)
        ax.grid(True, axis="y", alpha=0.3)
    axes[0].set_ylabel("success rate (%)")
    handles = [h for h in axes[0].get_legend_handles_labels()[0]]
    labels = axes[0].get_legend_handles_labels()[1]
    for ax in axes[1:]:
        for h, lab in zip(*ax.get_legend_handles_labels()):
            if lab not in labels:
                handles.append(h)
                labels.append(lab)
    fig.legend(handles, labels, loc="upper center", ncol=min(len(labels), 7), fontsize=8, frameon=False)
    return save_png(fig, path, caption or provenance(table))


def true_spans(mask: np.ndarray) -> list[tuple[int, int]]:
    """``(first, last)`` index pairs of the maximal runs of True in a 1-D boolean array."""
    out, start = [], None
    for i, flag in enumerate(mask):
        if flag and start is None:
            start = i
        elif not flag and start is not None:
            out.append((start, i - 1))
            start = None
    if start is not None:
        out.append((start, len(mask) - 1))
    return out


def plot_weights(
    weights_df: pd.DataFrame,
    path: str | os.PathLike,
    task: str | None = None,
    episode: int | None = None,
    step: int | None = None,
    caption: str | None = None,
) -> Path:
    """The paper's Fig. 5: per-step loss and TAR weight along one demonstration.

    The loss is drawn on the left axis, the weight on the right one (with the unit-mean line
    ``w = 1``); time windows with weight > 1 are shaded, and the first step where the gripper action
    turns closing (> 0 after a step <= 0) is marked.

    Args:
        weights_df: a ``weights.csv`` table (columns :data:`tar_rl.runs.WEIGHTS_COLUMNS`).
        path: the PNG to write (atomically).
        task: the task (default: the first task in name order at ``step``).
        episode: the demonstration (default: the lowest episode of ``task`` at ``step``).
        step: the training step of the recording (default: the largest).
        caption: provenance text for the footer (e.g. run name and git commit).

    Returns:
        ``path``.

    Raises:
        ValueError: missing columns, no rows, or no rows for the requested step, task or episode
            (the message lists the available ones).
    """
    check_weights_table(weights_df)
    if len(weights_df) == 0:
        raise ValueError("weights table has no rows")
    one, task, episode, step = _one_recording(weights_df, task, episode, step)
    t = one["t"].to_numpy()
    loss = one["loss"].to_numpy(dtype=float)
    weight = one["weight"].to_numpy(dtype=float)

    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch
    from matplotlib.ticker import MaxNLocator

    fig = new_figure(8.0, 4.2)
    fig.subplots_adjust(left=0.12, right=0.9, top=0.9, bottom=0.15)
    ax = fig.add_subplot()
    ax_w = ax.twinx()
    ax.plot(t, loss, color="C0", linewidth=1.3)
    ax_w.plot(t, weight, color="C3", linewidth=1.3)
    ax_w.axhline(1.0, color="C3", linestyle=":", linewidth=0.8)
    for a, b in true_spans(weight > 1.0):
        ax.axvspan(t[a] - 0.5, t[b] + 0.5, color="C1", alpha=0.18, linewidth=0)
    handles = [
        Line2D([], [], color="C0", label="per-step loss"),
        Line2D([], [], color="C3", label="TAR weight"),
        Patch(color="C1", alpha=0.18, label="weight > 1"),
    ]
    close = first_gripper_close(one["gripper"].to_numpy())
    if close is not None:
        ax.axvline(t[close], color="k", linestyle="--", linewidth=1)
        handles.append(Line2D([], [], color="k", linestyle="--", label=f"gripper closes (t = {t[close]})"))
    else:
        closed = bool((one["gripper"].to_numpy() > 0).any())
        text = "gripper closing from the start" if closed else "gripper never closes"
        handles.append(Line2D([], [], color="none", label=text))
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlabel("time step t along the demonstration")
    ax.set_ylabel("per-step imitation loss", color="C0")
    ax_w.set_ylabel("TAR weight", color="C3")
    ax.set_ylim(bottom=0)
    ax_w.set_ylim(bottom=0)
    ax.set_title(f"{task}, episode {episode}, training step {step}", fontsize=10)
    ax.legend(handles=handles, loc="upper right", fontsize=8)
    return save_png(fig, path, caption or f"task {task}, episode {episode}, step {step}")


def _one_recording(
    weights_df: pd.DataFrame, task: str | None, episode: int | None, step: int | None
) -> tuple[pd.DataFrame, str, int, int]:
    """The rows of one recorded demonstration in time order, with the task, episode and step chosen.

    Defaults: the largest step, the first task in name order, the lowest episode (see :func:`plot_weights`).
    """
    df = weights_df
    step = int(df["step"].max()) if step is None else step
    df = df[df["step"] == step]
    if not len(df):
        raise ValueError(f"no weights recorded at step {step}; steps: {sorted(weights_df['step'].unique().tolist())}")
    task = sorted(df["task"].unique())[0] if task is None else task
    if task not in set(df["task"]):
        raise ValueError(f"no weights for task {task!r} at step {step}; tasks: {sorted(df['task'].unique())}")
    df = df[df["task"] == task]
    episode = int(df["episode"].min()) if episode is None else episode
    one = df[df["episode"] == episode].sort_values("t")
    if not len(one):
        raise ValueError(
            f"no weights for episode {episode} of {task!r} at step {step}; episodes: {sorted(df['episode'].unique())}"
        )
    return one, task, episode, step


#: Columns of :func:`paired_summary`.
PAIRED_SUMMARY_COLUMNS: tuple[str, ...] = (
    "label",
    "group",
    "n",
    "mean",
    "ci_low",
    "ci_high",
    "higher",
    "lower",
    "seeds",
)


def paired_summary(deltas: pd.DataFrame, confidence: float = 0.95) -> pd.DataFrame:
    """Per label of a table of per-seed paired differences: what :func:`plot_paired_deltas` draws.

    Args:
        deltas: one row per (``label``, ``seed``) with the paired difference ``delta`` (arm - baseline of that
            seed); an optional ``group`` column (the colour of the label's row; default: the label).
        confidence: the level of the interval.

    Returns:
        One row per label, in the order the labels first appear, columns :data:`PAIRED_SUMMARY_COLUMNS`: ``n`` (seeds),
        ``mean``, ``ci_low`` and ``ci_high`` (:func:`~tar_rl.report.paired_t`'s t interval; ``nan`` with one seed),
        ``higher`` and ``lower`` (the seeds whose difference is above / below 0), ``seeds`` (comma-separated).

    Raises:
        ValueError: a missing column, no rows, a seed twice in one label, or a non-finite difference.
    """
    missing = [c for c in ("label", "seed", "delta") if c not in deltas.columns]
    if missing:
        raise ValueError(f"the paired differences are missing the column(s) {missing}; expected label, seed, delta")
    if len(deltas) == 0:
        raise ValueError("no paired differences to summarise")
    twice = deltas[deltas.duplicated(["label", "seed"], keep=False)]
    if len(twice):
        raise ValueError(f"a seed appears twice in one label: {sorted(set(zip(twice['label'], twice['seed'])))}")
    rows = []
    for label in dict.fromkeys(deltas["label"]):
        one = deltas[deltas["label"] == label]
        values = one["delta"].astype(float).tolist()
        stats = paired_t(values, confidence)
        group = one["group"].iloc[0] if "group" in one.columns else label
        rows.append(
            {
                "label": label,
                "group": group,
                "n": stats["n"],
                "mean": stats["mean"],
                "ci_low": stats["ci_low"],
                "ci_high": stats["ci_high"],
                "higher": sum(v > 0 for v in values),
                "lower": sum(v < 0 for v in values),
                "seeds": ",".join(str(s) for s in one["seed"]),
            }
        )
    return pd.DataFrame(rows, columns=list(PAIRED_SUMMARY_COLUMNS))


def draw_paired_deltas(fig, deltas: pd.DataFrame, xlabel: str = "difference", title: str | None = None) -> pd.DataFrame:
    """Draw :func:`plot_paired_deltas`'s one axis onto ``fig``; returns the :func:`paired_summary` it drew.

    One row per label, top to bottom in the order of the table: each seed's difference as an open dot (spread a
    little up and down by seed order, so equal values stay visible), the mean as a black diamond with its 95% t CI
    as a thick bar, and the zero line. The row's label reads ``<label> (k of n higher)``; the mean and its interval
    are written at the right.
    """
    summary = paired_summary(deltas)
    ax = fig.add_subplot()
    groups = list(dict.fromkeys(summary["group"]))
    colours = {g: f"C{i % 10}" for i, g in enumerate(groups)}
    ax.axvline(0.0, color="k", linewidth=0.8, linestyle="--")
    for row, rec in enumerate(summary.to_dict("records")):
        y = -row
        one = deltas[deltas["label"] == rec["label"]]
        k = len(one)
        offsets = np.linspace(-0.18, 0.18, k) if k > 1 else np.zeros(1)
        colour = colours[rec["group"]]
        ax.scatter(one["delta"].astype(float), y + offsets, s=22, facecolors="none", edgecolors=colour, linewidths=1.0)
        if math.isfinite(rec["ci_low"]):
            ax.plot([rec["ci_low"], rec["ci_high"]], [y, y], color="k", linewidth=2.6, solid_capstyle="butt")
        ax.plot([rec["mean"]], [y], linestyle="none", marker="D", markersize=6, color="k")
    labels = [f"{r['label']} ({r['higher']} of {r['n']} higher)" for r in summary.to_dict("records")]
    ax.set_yticks([-i for i in range(len(summary))], labels, fontsize=8)
    ax.set_ylim(-len(summary) + 0.5, 0.5)
    for tick, rec in zip(ax.get_yticklabels(), summary.to_dict("records")):
        tick.set_color(colours[rec["group"]])
    for row, rec in enumerate(summary.to_dict("records")):
        ci = f" [{rec['ci_low']:+.2f}, {rec['ci_high']:+.2f}]" if math.isfinite(rec["ci_low"]) else ""
        ax.annotate(
            f"{rec['mean']:+.2f}{ci}",
            (1.0, -row),
            xycoords=("axes fraction", "data"),
            xytext=(4, 0),
            textcoords="offset points",
            va="center",
            fontsize=7,
        )
    ax.set_xlabel(xlabel, fontsize=9)
    ax.grid(True, axis="x", alpha=0.3)
    if title:
        ax.set_title(title, fontsize=10)
    return summary


def plot_paired_deltas(
    deltas: pd.DataFrame,
    path: str | os.PathLike,
    caption: str,
    xlabel: str = "difference",
    title: str | None = None,
) -> Path:
    """Paired differences at a glance: per label (an arm against its baseline), every seed's difference as a dot and
    their mean with its 95% t CI (:func:`paired_summary`, via :func:`~tar_rl.report.paired_t`) on one axis, a zero
    line, and how many seeds are higher.

    Args:
        deltas: one row per (``label``, ``seed``) with ``delta``; an optional ``group`` colours the rows.
        path: the PNG to write (atomically).
        caption: the footer (provenance).
        xlabel: the axis's label (what the difference is, in its unit).
        title: the title.

    Returns:
        ``path``.

    Raises:
        ValueError: as :func:`paired_summary`.
    """
    paired_summary(deltas)  # refuse a bad table before drawing
    rows = deltas["label"].nunique()
    fig = new_figure(8.0, 1.4 + 0.42 * rows)
    fig.subplots_adjust(left=0.3, right=0.8, top=1 - 0.45 / fig.get_figheight(), bottom=0.7 / fig.get_figheight())
    draw_paired_deltas(fig, deltas, xlabel, title)
    return save_png(fig, path, caption)
