"""``tar-rl report``: read training-run directories, print and plot comparisons.

A run directory (written by the offline BC recipe) holds ``config.yaml``, ``summary.json`` (once the run
has finished), ``metrics.csv``, ``eval_rollouts.csv`` and optionally ``weights.csv``. The metrics of a
run are always recomputed from its evaluation rollouts (:func:`tar_rl.metrics.summarize` on the rows of
the largest ``step``), never read back from the summary.

* :func:`load_run` reads one run directory into a :class:`Run`.
* :func:`compare` pools finished runs over seeds, one row per (policy, objective): mean and std of
  success, Fast20 and NEPS in percent (overall and per difficulty group), and the paired difference
  of each objective to ``uniform`` over matched seeds.
* :func:`plot_success_vs_neps` (the paper's Fig. 3), :func:`plot_group_bars` and
  :func:`plot_weights` (Fig. 5) write PNG figures atomically, with the run names and git commits in a
  footer.
* :func:`main` is the body of ``tar-rl report RUN_DIR... [--out DIR]``.
* For the paper's experiments (``benchmarks/paper_experiments.py``): :func:`paired_t` and
  :func:`paired_table` (paired differences over seeds, 95% CI, paired t-test),
  :func:`table_one_markdown` (Table I) and :func:`controls_markdown` (Table III),
  :func:`plot_group_deltas` (Fig. 3(c)), :func:`plot_radar` (Fig. 4), :func:`phase_labels`,
  :func:`phase_weight_mass` and :func:`critical_windows` (where TAR's weight mass lies along a
  demonstration, anchored at the gripper-closing step), :func:`plot_weight_phases` (Fig. 5 with
  phases), :func:`plot_critical_windows`, :func:`plot_lines` and :func:`plot_heatmaps`.

Matplotlib is imported only by the plotting functions, which draw with the Agg canvas directly
(``matplotlib.figure.Figure`` + ``FigureCanvasAgg``): no display is needed and a caller's pyplot
backend is left alone.
"""

from __future__ import annotations

import argparse
import io
import json
import math
import os
import re
import statistics
import sys
import textwrap
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np
import pandas as pd

from tar_rl.io import atomic_write, write_csv_atomic
from tar_rl.metrics import DEFAULT_GROUP_ORDER, METRIC_COLUMNS, REQUIRED_COLUMNS, as_percent, summarize

__all__ = [
    "METRICS_COLUMNS",
    "OBJECTIVE_ORDER",
    "PAIRED_COLUMNS",
    "PHASES",
    "TABLE_I_COLUMNS",
    "WEIGHTS_COLUMNS",
    "Run",
    "compare",
    "controls_markdown",
    "critical_windows",
    "expand_run_dirs",
    "first_gripper_close",
    "load_run",
    "main",
    "paired_t",
    "paired_table",
    "phase_labels",
    "phase_weight_mass",
    "plot_critical_windows",
    "plot_group_bars",
    "plot_group_deltas",
    "plot_heatmaps",
    "plot_lines",
    "plot_radar",
    "plot_success_vs_neps",
    "plot_weight_phases",
    "plot_weights",
    "run_percent",
    "runs_table",
    "table_one_markdown",
]

#: Columns of ``metrics.csv``.
METRICS_COLUMNS: tuple[str, ...] = ("step", "phase", "name", "value")
#: Columns of ``weights.csv``.
WEIGHTS_COLUMNS: tuple[str, ...] = ("step", "task", "episode", "t", "loss", "weight", "gripper")
#: Columns ``eval_rollouts.csv`` must have (the evaluator's columns the report reads, plus ``step``).
ROLLOUT_COLUMNS: tuple[str, ...] = (*REQUIRED_COLUMNS, "step")
#: Row order of the objectives in tables and legends; other objectives follow alphabetically.
OBJECTIVE_ORDER: tuple[str, ...] = ("uniform", "tar", "shuffle", "random", "invert", "perturb_high", "perturb_low")
#: The baseline of the paired differences.
BASELINE = "uniform"

_LABELS = {"success": "success %", "fast20": "100 x Fast20", "neps": "100 x NEPS"}


# -- Loading -----------------------------------------------------------------------------------


@dataclass
class Run:
    """One training run directory, as the report reads it.

    Attributes:
        path: the run directory.
        name: ``summary.json``'s ``run_name`` (the directory's name when there is no summary).
        objective: the weighting (``objective.name`` of the config).
        policy: the policy head (``policy.name`` of the config).
        seed: the training seed.
        config: the resolved config (``config.yaml``).
        final: the final evaluation's :func:`tar_rl.metrics.summarize` table (fractions), recomputed
            from the ``eval_rollouts.csv`` rows of the largest step; ``None`` without evaluation rows.
        metrics: ``metrics.csv`` (columns ``step, phase, name, value``; empty if not written yet).
        weights: ``weights.csv``, or ``None`` when the run recorded no weights.
        finished: the run finished (``summary.json`` says so) and has final evaluation rows.
        steps: training steps done (``summary.json``), ``None`` before the run finished.
        final_step: the training step of the final evaluation (largest ``step`` of the rollouts).
        git_commit: the commit the run was trained at (``summary.json``), ``None`` if unknown.
        eval_settings: what two runs must share to be compared: ``tasks`` (sorted task names of the
            final evaluation), ``eval.rollouts`` (rollouts per task), ``eval.seed`` and ``eval.horizon``.
        notes: why the run is unfinished, or other remarks printed with the report.
    """

    path: Path
    name: str
    objective: str
    policy: str
    seed: int
    config: dict
    final: pd.DataFrame | None
    metrics: pd.DataFrame
    weights: pd.DataFrame | None
    finished: bool
    steps: int | None = None
    final_step: int | None = None
    git_commit: str | None = None
    eval_settings: dict = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)


def _is_run_dir(path: Path) -> bool:
    return path.is_dir() and ((path / "config.yaml").is_file() or (path / "summary.json").is_file())


def _read_yaml(path: Path) -> dict:
    import yaml

    try:
        data = yaml.safe_load(path.read_text())
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as err:
        raise ValueError(f"{path}: cannot read the run's config: {err}") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: the run's config must be a YAML mapping, got {type(data).__name__}")
    return data


def _read_summary(path: Path) -> dict:
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ValueError(f"{path}: cannot read the run summary: {err}") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: the run summary must be a JSON object, got {type(data).__name__}")
    if not isinstance(data.get("finished"), bool):
        raise ValueError(f"{path}: the run summary has no boolean 'finished' entry")
    return data


def _read_csv(path: Path, columns: Sequence[str]) -> pd.DataFrame:
    try:
        df = pd.read_csv(path)
    except pd.errors.EmptyDataError:
        raise ValueError(f"{path}: the file is empty (not even a header); expected columns {list(columns)}") from None
    except (OSError, UnicodeDecodeError, pd.errors.ParserError) as err:
        raise ValueError(f"{path}: cannot read the CSV file: {err}") from None
    missing = [c for c in columns if c not in df.columns]
    if missing:
        raise ValueError(f"{path}: missing the column(s) {missing}; expected at least {list(columns)}")
    return df


def _config_get(config: dict, dotted: str):
    node: Any = config
    for key in dotted.split("."):
        if not isinstance(node, dict) or key not in node:
            return None
        node = node[key]
    return node


def _eval_settings(config: dict, rows: pd.DataFrame) -> dict:
    """Task set and rollouts per task from the final rows; seed and horizon from the config, else the rows."""
    counts = rows.groupby("task").size()
    rollouts = int(counts.iloc[0]) if counts.nunique() == 1 else tuple(sorted(counts.unique().tolist()))
    seed = _config_get(config, "eval.seed")
    if seed is None and "variation_seed" in rows.columns:
        seed = int(rows["variation_seed"].min())  # rollout j uses seed base + j // 50
    horizon = _config_get(config, "eval.horizon")
    if horizon is None and "steps" in rows.columns:
        horizon = round(float((rows["steps"] / rows["rho"]).median()))  # rho = steps / H
    return {
        "tasks": tuple(sorted(rows["task"].unique())),
        "eval.rollouts": rollouts,
        "eval.seed": seed,
        "eval.horizon": horizon,
    }


def load_run(path: str | os.PathLike) -> Run:
    """Read one run directory.

    A directory with ``config.yaml`` (or ``summary.json``) is a run directory. A run without
    ``summary.json`` is still training (the recipe writes the summary last) and is loaded as unfinished,
    as is one whose summary says ``"finished": false`` or one without final evaluation rows; the reason
    is in :attr:`Run.notes`. Files the run has are always checked.

    Args:
        path: a run directory.

    Returns:
        The :class:`Run`, its ``final`` table recomputed from ``eval_rollouts.csv``.

    Raises:
        ValueError: ``path`` is not a directory, holds neither ``config.yaml`` nor ``summary.json``, or a
            file is corrupt (unreadable YAML/JSON/CSV, missing columns, bad rollout values); a finished
            run without ``metrics.csv``. The message names the path and the file.
    """
    path = Path(path)
    if not path.is_dir():
        raise ValueError(f"{path}: not a run directory (no such directory)")
    config_path, summary_path = path / "config.yaml", path / "summary.json"
    if not _is_run_dir(path):
        raise ValueError(f"{path}: not a run directory (no config.yaml or summary.json in it)")
    summary = _read_summary(summary_path) if summary_path.is_file() else None
    if config_path.is_file():
        config = _read_yaml(config_path)
    elif isinstance(summary.get("config"), dict):
        config = summary["config"]
    else:
        raise ValueError(f"{path}: missing config.yaml (and summary.json holds no config)")

    notes: list[str] = []
    info = summary or {}
    name = str(info.get("run_name") or path.name)
    objective = info.get("objective") or _config_get(config, "objective.name")
    policy = info.get("policy") or _config_get(config, "policy.name")
    seed = info.get("seed", config.get("seed"))
    for key, value in (("objective", objective), ("policy", policy), ("seed", seed)):
        if value is None:
            raise ValueError(f"{path}: the run's {key} is given neither in summary.json nor in config.yaml")
    try:
        seed = int(seed)
    except (TypeError, ValueError):
        raise ValueError(f"{path}: the run's seed must be an integer, got {seed!r}") from None

    finished = summary is not None and summary["finished"]
    if summary is None:
        notes.append("unfinished: no summary.json yet (still training, or stopped)")
    elif not finished:
        notes.append("unfinished: summary.json says finished: false")

    metrics_path = path / "metrics.csv"
    if metrics_path.is_file():
        metrics = _read_csv(metrics_path, METRICS_COLUMNS)
    elif finished:
        raise ValueError(f"{path}: missing metrics.csv (the run's summary says it finished)")
    else:
        metrics = pd.DataFrame({c: pd.Series(dtype=object) for c in METRICS_COLUMNS})

    rollouts_path = path / "eval_rollouts.csv"
    final = final_step = None
    settings: dict = {}
    if rollouts_path.is_file():
        rollouts = _read_csv(rollouts_path, ROLLOUT_COLUMNS)
        if len(rollouts):
            try:
                steps_col = pd.to_numeric(rollouts["step"], errors="raise")
            except (TypeError, ValueError):
                raise ValueError(f"{rollouts_path}: the column 'step' must hold integers") from None
            final_step = int(steps_col.max())
            rows = rollouts[steps_col == final_step]
            try:
                final = summarize(rows)
            except ValueError as err:
                raise ValueError(f"{rollouts_path}: bad evaluation rows at step {final_step}: {err}") from None
            settings = _eval_settings(config, rows)
    if final is None and finished:
        finished = False
        notes.append("unfinished: no final evaluation rows in eval_rollouts.csv")

    steps = info.get("steps")
    if finished and steps is not None and final_step != steps:
        notes.append(f"the last evaluation is at step {final_step}, the summary says {steps} steps were trained")
    if finished and summary.get("final"):
        _check_summary_agrees(summary["final"], final, notes)

    weights_path = path / "weights.csv"
    weights = _read_csv(weights_path, WEIGHTS_COLUMNS) if weights_path.is_file() else None
    if weights is not None and len(weights) == 0:
        weights = None

    return Run(
        path=path,
        name=name,
        objective=str(objective),
        policy=str(policy),
        seed=seed,
        config=config,
        final=final,
        metrics=metrics,
        weights=weights,
        finished=finished,
        steps=None if steps is None else int(steps),
        final_step=final_step,
        git_commit=info.get("git_commit"),
        eval_settings=settings,
        notes=notes,
    )


def _check_summary_agrees(records: Any, final: pd.DataFrame | None, notes: list[str]) -> None:
    """Note when summary.json's overall success differs from the one recomputed from the rollouts."""
    if final is None or not isinstance(records, list):
        return
    overall = [r for r in records if isinstance(r, dict) and r.get("name") == "overall"]
    if not overall:
        return
    try:
        written = float(overall[0]["success"])
    except (KeyError, TypeError, ValueError):
        return
    recomputed = float(final.loc[final["level"] == "overall", "success"].iloc[0])
    if not math.isclose(written, recomputed, abs_tol=1e-9):
        notes.append(
            f"summary.json gives overall success {written:.4f}, eval_rollouts.csv gives {recomputed:.4f} "
            "(the report uses eval_rollouts.csv)"
        )


def expand_run_dirs(paths: Iterable[str | os.PathLike]) -> list[Path]:
    """Run directories named by ``paths``; a folder that is not a run directory gives its run sub-folders.

    Args:
        paths: run directories, or folders (a sweep's ``runs_root``) holding run directories one level down.

    Returns:
        The run directories, in the order given; a folder's runs sorted by name.

    Raises:
        ValueError: a path that does not exist, or a folder that is neither a run directory nor holds any.
    """
    out: list[Path] = []
    for p in map(Path, paths):
        if not p.is_dir():
            raise ValueError(f"{p}: not a run directory (no such directory)")
        if _is_run_dir(p):
            out.append(p)
            continue
        children = sorted(c for c in p.iterdir() if _is_run_dir(c))
        if not children:
            raise ValueError(f"{p}: not a run directory (no config.yaml or summary.json) and holds no run directories")
        out.extend(children)
    return out


# -- Comparison --------------------------------------------------------------------------------


def _objective_key(name: str) -> tuple[int, str]:
    return (OBJECTIVE_ORDER.index(name) if name in OBJECTIVE_ORDER else len(OBJECTIVE_ORDER), name)


def _mean(values: Sequence[float]) -> float:
    """Mean that handles ``inf`` without numpy warnings: ``nan`` if a value is nan or infs of both signs."""
    if not values or any(math.isnan(v) for v in values):
        return math.nan
    infs = {v for v in values if math.isinf(v)}
    if infs:
        return infs.pop() if len(infs) == 1 else math.nan
    return statistics.fmean(values)


def _std(values: Sequence[float]) -> float:
    """Sample standard deviation (ddof = 1); ``nan`` for one value or any non-finite value."""
    if len(values) < 2 or not all(math.isfinite(v) for v in values):
        return math.nan
    return statistics.stdev(values)


def _check_comparable(runs: Sequence[Run]) -> None:
    first = runs[0]
    for run in runs[1:]:
        for key, ref in first.eval_settings.items():
            value = run.eval_settings.get(key)
            if value == ref:
                continue
            if key == "tasks":
                only_first = sorted(set(ref) - set(value or ()))
                only_run = sorted(set(value or ()) - set(ref))
                raise ValueError(
                    f"runs evaluated on different task sets cannot be compared: {first.name} ({first.path}) has "
                    f"{len(ref)} tasks, {run.name} ({run.path}) has {len(value or ())}; only in the first: "
                    f"{only_first}, only in the second: {only_run}"
                )
            raise ValueError(
                f"runs evaluated with different settings cannot be compared: {key} is {ref!r} in {first.name} "
                f"({first.path}) but {value!r} in {run.name} ({run.path})"
            )


def _check_unique(runs: Sequence[Run]) -> None:
    seen: dict[tuple, Run] = {}
    for run in runs:
        key = (run.policy, run.objective, run.seed)
        if key in seen:
            other = seen[key]
            raise ValueError(
                f"two runs with policy {run.policy!r}, objective {run.objective!r} and seed {run.seed}: "
                f"{other.path} and {run.path}; they would be pooled as one seed. Report them separately."
            )
        seen[key] = run


def _levels(runs: Sequence[Run]) -> list[str]:
    groups = list(dict.fromkeys(n for r in runs for n in r.final.loc[r.final["level"] == "group", "name"]))
    ordered = [g for g in DEFAULT_GROUP_ORDER if g in groups] + [g for g in groups if g not in DEFAULT_GROUP_ORDER]
    return ["overall", *ordered]


def _percent_values(run: Run) -> dict[tuple[str, str], float]:
    """``(metric, level name) -> value`` in percent, for the overall and group rows of a run's final table."""
    table = as_percent(run.final[run.final["level"] != "task"])
    return {(m, rec["name"]): float(rec[m]) for rec in table.to_dict("records") for m in METRIC_COLUMNS}


def compare(runs: Sequence[Run], file: IO[str] | None = None) -> pd.DataFrame:
    """Pool finished runs over seeds: one row per (policy, objective), in percent.

    Unfinished runs are left out, each with a note printed to ``file`` (default: standard output) and
    listed in ``table.attrs["excluded"]``.

    Columns: ``policy``, ``objective``, ``n_seeds``, ``seeds`` (comma-separated), ``runs`` and
    ``git_commits`` (semicolon-separated, for provenance); for each level ``L`` in ``overall`` and the
    difficulty groups present (``easy``, ``medium``, ``hard``, ``very_hard``, then any other group) and
    each metric ``M`` in ``success``, ``fast20``, ``neps``: ``M_L_mean`` and ``M_L_std``, the mean and
    the sample standard deviation (ddof 1; ``nan`` with one seed or a non-finite value) over seeds of
    ``100 x`` the metric. Then the paired differences to ``uniform`` of the same policy over the seeds
    both have: ``n_pairs`` and ``delta_success``, ``delta_fast20``, ``delta_neps``, the mean over
    those seeds of (objective - uniform) of the overall metric, in percentage points (``nan`` and
    ``n_pairs = 0`` for ``uniform`` itself and where no seed is shared).

    Args:
        runs: loaded runs (:func:`load_run`).
        file: where to print the notes on unfinished runs.

    Returns:
        The comparison table, sorted by policy and then objective (``uniform``, ``tar``, the controls).

    Raises:
        ValueError: no finished run; finished runs evaluated on different task sets or with a different
            evaluation seed, rollouts per task or horizon (the message names the setting and the runs);
            two finished runs with the same policy, objective and seed.
    """
    out = sys.stdout if file is None else file
    done = [r for r in runs if r.finished]
    excluded = [r for r in runs if not r.finished]
    for run in excluded:
        reason = "; ".join(n for n in run.notes if n.startswith("unfinished")) or "unfinished"
        print(f"note: {run.name} ({run.path}) is left out of the comparison: {reason}", file=out)
    if not done:
        raise ValueError("no finished run to compare" + (f" ({len(excluded)} unfinished)" if excluded else ""))
    _check_comparable(done)
    _check_unique(done)
    levels = _levels(done)
    values = {id(r): _percent_values(r) for r in done}

    by_key: dict[tuple[str, str], list[Run]] = {}
    for run in done:
        by_key.setdefault((run.policy, run.objective), []).append(run)
    keys = sorted(by_key, key=lambda k: (k[0], _objective_key(k[1])))

    rows = []
    for policy, objective in keys:
        members = sorted(by_key[(policy, objective)], key=lambda r: r.seed)
        row: dict[str, Any] = {
            "policy": policy,
            "objective": objective,
            "n_seeds": len(members),
            "seeds": ",".join(str(r.seed) for r in members),
            "runs": ";".join(r.name for r in members),
            "git_commits": ";".join(dict.fromkeys(str(r.git_commit or "unknown") for r in members)),
        }
        for level in levels:
            for metric in METRIC_COLUMNS:
                vals = [values[id(r)][(metric, level)] for r in members if (metric, level) in values[id(r)]]
                row[f"{metric}_{level}_mean"] = _mean(vals)
                row[f"{metric}_{level}_std"] = _std(vals)
        baseline = {r.seed: r for r in by_key.get((policy, BASELINE), [])}
        pairs = [(r, baseline[r.seed]) for r in members if objective != BASELINE and r.seed in baseline]
        row["n_pairs"] = len(pairs)
        for metric in METRIC_COLUMNS:
            deltas = [values[id(a)][(metric, "overall")] - values[id(b)][(metric, "overall")] for a, b in pairs]
            row[f"delta_{metric}"] = _mean(deltas)
        rows.append(row)
    table = pd.DataFrame(rows)
    table.attrs["excluded"] = [r.name for r in excluded]
    return table


# -- Printing ----------------------------------------------------------------------------------


def _fmt(value: float, digits: int = 1) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    return "inf" if math.isinf(value) else f"{value:.{digits}f}"


def _fmt_pm(mean: float, std: float) -> str:
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
            "status": "finished" if run.finished else "unfinished",
        }
        overall = _percent_values(run) if run.finished else {}
        for metric in METRIC_COLUMNS:
            row[_LABELS[metric]] = _fmt(overall.get((metric, "overall"), math.nan))
        rows.append(row)
    return pd.DataFrame(rows)


def _table_levels(table: pd.DataFrame) -> list[str]:
    """The levels (``overall``, then groups) of a :func:`compare` table, from its ``success_<level>_mean`` columns."""
    prefix, suffix = "success_", "_mean"
    return [c[len(prefix) : -len(suffix)] for c in table.columns if c.startswith(prefix) and c.endswith(suffix)]


def _display_comparison(table: pd.DataFrame) -> pd.DataFrame:
    levels = _table_levels(table)
    rows = []
    for rec in table.to_dict("records"):
        row = {"policy": rec["policy"], "objective": rec["objective"], "seeds": rec["n_seeds"]}
        for metric in METRIC_COLUMNS:
            row[_LABELS[metric]] = _fmt_pm(rec[f"{metric}_overall_mean"], rec[f"{metric}_overall_std"])
        for level in levels[1:]:
            row[f"success {level}"] = _fmt_pm(rec[f"success_{level}_mean"], rec[f"success_{level}_std"])
        rows.append(row)
    return pd.DataFrame(rows)


def _display_pairs(table: pd.DataFrame) -> pd.DataFrame:
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


# -- Figures -----------------------------------------------------------------------------------


def _new_figure(width: float, height: float):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), dpi=120)
    FigureCanvasAgg(fig)
    return fig


def _provenance(table: pd.DataFrame) -> str:
    names = [n for cell in table["runs"] for n in str(cell).split(";")] if "runs" in table.columns else []
    commits = list(dict.fromkeys(c for cell in table.get("git_commits", []) for c in str(cell).split(";")))
    shown = ", ".join(names[:8]) + (f" (+{len(names) - 8} more)" if len(names) > 8 else "")
    commit_text = ", ".join(c[:10] for c in commits[:4]) + (" ..." if len(commits) > 4 else "")
    return f"runs: {shown or '?'} | git: {commit_text or 'unknown'}"


def _save_png(fig, path: str | os.PathLike, footer: str) -> Path:
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


def _check_table(table: pd.DataFrame, columns: Sequence[str]) -> None:
    missing = [c for c in columns if c not in table.columns]
    if missing:
        raise ValueError(f"the table is missing the column(s) {missing}; expected a compare() table")
    if len(table) == 0:
        raise ValueError("the comparison table is empty: nothing to plot")


def _zero_nan(value: float) -> float:
    return 0.0 if math.isnan(value) else value


def plot_success_vs_neps(table: pd.DataFrame, path: str | os.PathLike, caption: str | None = None) -> Path:
    """The paper's Fig. 3: success against normalised deployment cost, one marker per (policy, objective).

    x = ``100 x NEPS`` (lower is better), y = success % (overall means over seeds, error bars one std
    over seeds); colour = objective, marker shape = policy, ``uniform`` drawn unfilled. An arrow goes
    from each policy's ``uniform`` point to each of its other objectives. Points with infinite NEPS
    cannot be placed and are named in the footer instead.

    Args:
        table: a :func:`compare` table.
        path: the PNG to write (atomically).
        caption: provenance text for the footer (default: the table's run names and git commits).

    Returns:
        ``path``.

    Raises:
        ValueError: not a :func:`compare` table, or an empty one.
    """
    need = [
        "policy",
        "objective",
        "success_overall_mean",
        "success_overall_std",
        "neps_overall_mean",
        "neps_overall_std",
    ]
    _check_table(table, need)
    from matplotlib.lines import Line2D

    fig = _new_figure(7.0, 5.2)
    fig.subplots_adjust(left=0.1, right=0.97, top=0.92, bottom=0.14)
    ax = fig.add_subplot()
    objectives = sorted(table["objective"].unique(), key=_objective_key)
    policies = sorted(table["policy"].unique())
    colours = {o: f"C{i % 10}" for i, o in enumerate(objectives)}
    markers = dict(zip(policies, "osD^vP*X<>" * 4))
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
            xerr=_zero_nan(rec["neps_overall_std"]),
            yerr=_zero_nan(rec["success_overall_std"]),
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
    ax.legend(handles=handles, loc="best", fontsize=8, frameon=True)
    ax.set_xlabel("100 x NEPS (normalised steps per success; lower is better)")
    ax.set_ylabel("success rate (%; higher is better)")
    ax.set_title("Success vs deployment cost (mean over seeds; arrows: uniform -> objective)", fontsize=10)
    ax.grid(True, alpha=0.3)
    footer = caption or _provenance(table)
    if hidden:
        footer += f" | not shown (NEPS inf): {', '.join(hidden)}"
    return _save_png(fig, path, footer)


def plot_group_bars(table: pd.DataFrame, path: str | os.PathLike, caption: str | None = None) -> Path:
    """Success per difficulty group (and overall): bars per objective, one panel per policy.

    Bar height is the mean over seeds, the error bar one standard deviation over seeds.

    Args:
        table: a :func:`compare` table.
        path: the PNG to write (atomically).
        caption: provenance text for the footer (default: the table's run names and git commits).

    Returns:
        ``path``.

    Raises:
        ValueError: not a :func:`compare` table, or an empty one.
    """
    _check_table(table, ["policy", "objective", "success_overall_mean"])
    levels = _table_levels(table)
    levels = [lv for lv in levels if lv != "overall"] + ["overall"]
    policies = sorted(table["policy"].unique())
    objectives = sorted(table["objective"].unique(), key=_objective_key)
    colours = {o: f"C{i % 10}" for i, o in enumerate(objectives)}
    fig = _new_figure(max(6.0, 1.1 * len(levels) * len(policies) + 2.0), 4.6)
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
            stds = [_zero_nan(rec.get(f"success_{lv}_std", math.nan)) for lv in levels]
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
    return _save_png(fig, path, caption or _provenance(table))


def _runs_of(mask: np.ndarray) -> list[tuple[int, int]]:
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


def first_gripper_close(gripper: Sequence[float]) -> int | None:
    """Index of the first step where the gripper action turns closing (> 0) after a non-closing step.

    A demonstration whose gripper is closing from its first step has no such step (``None``), as has
    one that never closes.
    """
    g = np.asarray(gripper, dtype=float)
    hits = np.flatnonzero((g[1:] > 0) & (g[:-1] <= 0))
    return int(hits[0]) + 1 if hits.size else None


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
        weights_df: a ``weights.csv`` table (columns :data:`WEIGHTS_COLUMNS`).
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
    missing = [c for c in WEIGHTS_COLUMNS if c not in weights_df.columns]
    if missing:
        raise ValueError(f"weights table is missing the column(s) {missing}; expected {list(WEIGHTS_COLUMNS)}")
    if len(weights_df) == 0:
        raise ValueError("weights table has no rows")
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
    t = one["t"].to_numpy()
    loss = one["loss"].to_numpy(dtype=float)
    weight = one["weight"].to_numpy(dtype=float)

    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch
    from matplotlib.ticker import MaxNLocator

    fig = _new_figure(8.0, 4.2)
    fig.subplots_adjust(left=0.12, right=0.9, top=0.9, bottom=0.15)
    ax = fig.add_subplot()
    ax_w = ax.twinx()
    ax.plot(t, loss, color="C0", linewidth=1.3)
    ax_w.plot(t, weight, color="C3", linewidth=1.3)
    ax_w.axhline(1.0, color="C3", linestyle=":", linewidth=0.8)
    for a, b in _runs_of(weight > 1.0):
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
    return _save_png(fig, path, caption or f"task {task}, episode {episode}, step {step}")


# -- Command line ------------------------------------------------------------------------------


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="tar-rl report",
        description="Compare training runs: a table per run, the comparison pooled over seeds, and figures.",
    )
    parser.add_argument(
        "runs", nargs="+", metavar="RUN_DIR", help="run directories, or folders holding run directories (a sweep)"
    )
    parser.add_argument("--out", metavar="DIR", help="folder for comparison.csv and the figures (default: ./report)")
    return parser


def _file_stem(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name) or "run"


def _print_frame(df: pd.DataFrame) -> None:
    print(df.to_string(index=False) if len(df) else "(none)")


def main(argv: list[str] | None = None) -> int:
    """``tar-rl report RUN_DIR... [--out DIR]``.

    Loads the runs (a folder holding run directories is expanded to them), prints one line per run
    (objective, policy, seed, overall success, 100 x Fast20, 100 x NEPS), notes on unfinished runs,
    the comparison pooled over seeds and the paired differences to ``uniform``; writes
    ``comparison.csv``, ``success_vs_neps.png``, ``group_success.png`` and ``weights_<run>.png`` for
    each run with ``weights.csv`` into ``--out``. With no finished run it prints the runs, writes
    only the weight figures and ends with a line saying so, returning 1.

    Args:
        argv: the arguments after ``report`` (default: ``sys.argv[1:]``).

    Returns:
        0, or 1 when no run is finished (nothing was compared).

    Raises:
        SystemExit: bad arguments, a bad run directory or runs that cannot be compared (the message says why).
    """
    args = _parser().parse_args(argv)
    out_dir = Path(args.out) if args.out else Path.cwd() / "report"
    try:
        runs = [load_run(p) for p in expand_run_dirs(args.runs)]
    except ValueError as err:
        raise SystemExit(f"tar-rl report: {err}") from None

    print(f"{len(runs)} run(s):")
    _print_frame(runs_table(runs))
    for run in runs:
        for note in run.notes:
            if run.finished:  # the unfinished ones are noted by compare()
                print(f"note: {run.name}: {note}")
    written: list[Path] = []
    print()
    if any(r.finished for r in runs):
        try:
            table = compare(runs)
        except ValueError as err:
            raise SystemExit(f"tar-rl report: {err}") from None
        print("\nComparison over seeds (mean ± std; success %, 100 x Fast20, 100 x NEPS; lower cost is better):")
        _print_frame(_display_comparison(table))
        print(f"\nPaired differences to {BASELINE} over matched seeds (objective - {BASELINE}, overall):")
        _print_frame(_display_pairs(table))
        written.append(write_csv_atomic(table, out_dir / "comparison.csv"))
        written.append(plot_success_vs_neps(table, out_dir / "success_vs_neps.png"))
        written.append(plot_group_bars(table, out_dir / "group_success.png"))
    else:
        for run in runs:
            print(f"note: {run.name} ({run.path}): {'; '.join(run.notes)}")
    used: set[str] = set()
    for run in runs:
        if run.weights is None:
            continue
        stem = _file_stem(run.name)
        while stem in used:
            stem += "_"
        used.add(stem)
        commit = (run.git_commit or "unknown")[:10]
        written.append(
            plot_weights(run.weights, out_dir / f"weights_{stem}.png", caption=f"run {run.name} | git: {commit}")
        )
    if written:
        print("\nwrote: " + ", ".join(str(p) for p in written))
    if not any(r.finished for r in runs):
        print(
            f"tar-rl report: no finished run among the {len(runs)} run(s) of {' '.join(args.runs)}: nothing to "
            "compare; let the runs finish (run a stopped run's tar-rl train command again to resume it)",
            file=sys.stderr,
        )
        return 1
    return 0


# -- Paper experiments: paired statistics, Tables I and III, Fig. 4, phases, critical windows ---------

#: Phases of a demonstration, in time order (see :func:`phase_labels`).
PHASES: tuple[str, ...] = ("approach", "contact_onset", "transport", "completion")
#: Columns of :func:`paired_table`.
PAIRED_COLUMNS: tuple[str, ...] = (
    "policy",
    "baseline",
    "objective",
    "metric",
    "level",
    "n_pairs",
    "seeds",
    "baseline_mean",
    "baseline_std",
    "objective_mean",
    "objective_std",
    "delta_mean",
    "delta_std",
    "ci_low",
    "ci_high",
    "t",
    "p_value",
)
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


def run_percent(run: Run) -> dict[tuple[str, str], float]:
    """A finished run's final metrics in ``100 x`` units: ``(metric, level) -> value``, level ``overall`` or a group."""
    if run.final is None:
        raise ValueError(f"{run.name} ({run.path}) has no final evaluation")
    return _percent_values(run)


def paired_t(deltas: Sequence[float], confidence: float = 0.95) -> dict[str, float]:
    """Paired t statistics of per-seed differences (treatment - baseline).

    Args:
        deltas: one difference per matched seed, shape ``[n]``; all finite.
        confidence: level of the two-sided confidence interval of the mean difference.

    Returns:
        ``n``; ``mean``; ``std`` (sample, ddof 1); ``ci_low`` and ``ci_high``, the interval
        ``mean -+ t_{(1 + confidence) / 2, n - 1} * std / sqrt(n)``; ``t = mean / (std / sqrt(n))`` and
        the two-sided ``p_value`` of the paired t-test (H0: mean difference 0). With ``n < 2`` every
        entry but ``n`` and ``mean`` is ``nan``. With ``std = 0`` the interval is the point
        ``[mean, mean]``; ``t`` is ``+-inf`` and ``p = 0`` for a non-zero mean, ``t = nan`` and
        ``p = 1`` for a zero one.

    Raises:
        ValueError: a non-finite difference, or a confidence outside (0, 1).
    """
    from scipy import stats

    if not 0 < confidence < 1:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    values = [float(d) for d in deltas]
    if not all(math.isfinite(v) for v in values):
        raise ValueError(f"paired differences must be finite, got {values}")
    n = len(values)
    nan = math.nan
    out = {"n": n, "mean": statistics.fmean(values) if n else nan}
    out.update(std=nan, ci_low=nan, ci_high=nan, t=nan, p_value=nan)
    if n < 2:
        return out
    std = statistics.stdev(values)
    mean = out["mean"]
    out["std"] = std
    if std == 0:
        out.update(ci_low=mean, ci_high=mean, t=math.copysign(math.inf, mean) if mean else nan)
        out["p_value"] = 0.0 if mean else 1.0
        return out
    se = std / math.sqrt(n)
    q = float(stats.t.ppf((1 + confidence) / 2, n - 1))
    t = mean / se
    out.update(ci_low=mean - q * se, ci_high=mean + q * se, t=t, p_value=float(2 * stats.t.sf(abs(t), n - 1)))
    return out


def paired_table(
    runs: Sequence[Run], baseline: str = BASELINE, objectives: Sequence[str] | None = None, file: IO[str] | None = None
) -> pd.DataFrame:
    """Paired comparison of objectives to a baseline over matched seeds, per policy, metric and level.

    For each policy, each objective other than ``baseline`` (or those in ``objectives``), each metric
    (``success``, ``fast20``, ``neps``, in ``100 x`` units) and each level (``overall`` and the
    difficulty groups), the seeds both runs have and where both values are finite are paired; the
    row gives the means and sample stds of both over those seeds, and :func:`paired_t` of the
    differences (objective - baseline). Unfinished runs are left out with a note (see :func:`compare`).

    Args:
        runs: loaded runs.
        baseline: the objective differences are taken to.
        objectives: the objectives to compare (default: every other one present).
        file: where notes on unfinished runs are printed.

    Returns:
        One row per (policy, objective, metric, level), columns :data:`PAIRED_COLUMNS`; ``seeds``
        lists the paired seeds (comma-separated). A cell without pairs has ``n_pairs = 0`` and ``nan``.

    Raises:
        ValueError: as :func:`compare` (no finished run, runs evaluated differently, duplicate seeds).
    """
    out = sys.stdout if file is None else file
    done = [r for r in runs if r.finished]
    for run in runs:
        if not run.finished:
            print(f"note: {run.name} ({run.path}) is left out: {'; '.join(run.notes) or 'unfinished'}", file=out)
    if not done:
        raise ValueError("no finished run to compare")
    _check_comparable(done)
    _check_unique(done)
    levels = _levels(done)
    values = {id(r): _percent_values(r) for r in done}
    rows = []
    for policy in sorted({r.policy for r in done}):
        mine = [r for r in done if r.policy == policy]
        base = {r.seed: r for r in mine if r.objective == baseline}
        present = sorted({r.objective for r in mine if r.objective != baseline}, key=_objective_key)
        for objective in present if objectives is None else [o for o in objectives if o in present]:
            treat = {r.seed: r for r in mine if r.objective == objective}
            shared = sorted(set(base) & set(treat))
            for metric in METRIC_COLUMNS:
                for level in levels:
                    key = (metric, level)
                    pairs = [
                        (s, values[id(base[s])].get(key, math.nan), values[id(treat[s])].get(key, math.nan))
                        for s in shared
                    ]
                    pairs = [(s, b, t) for s, b, t in pairs if math.isfinite(b) and math.isfinite(t)]
                    stats_ = paired_t([t - b for _, b, t in pairs])
                    rows.append(
                        {
                            "policy": policy,
                            "baseline": baseline,
                            "objective": objective,
                            "metric": metric,
                            "level": level,
                            "n_pairs": len(pairs),
                            "seeds": ",".join(str(s) for s, _, _ in pairs),
                            "baseline_mean": _mean([b for _, b, _ in pairs]),
                            "baseline_std": _std([b for _, b, _ in pairs]),
                            "objective_mean": _mean([t for _, _, t in pairs]),
                            "objective_std": _std([t for _, _, t in pairs]),
                            "delta_mean": stats_["mean"],
                            "delta_std": stats_["std"],
                            "ci_low": stats_["ci_low"],
                            "ci_high": stats_["ci_high"],
                            "t": stats_["t"],
                            "p_value": stats_["p_value"],
                        }
                    )
    return pd.DataFrame(rows, columns=list(PAIRED_COLUMNS))


def _fmt_p(p: float) -> str:
    if p is None or math.isnan(p):
        return "-"
    return "<0.001" if p < 0.001 else f"{p:.3f}"


def _cell(paired: pd.DataFrame, policy: str, objective: str, metric: str, level: str) -> dict | None:
    match = paired[
        (paired["policy"] == policy)
        & (paired["objective"] == objective)
        & (paired["metric"] == metric)
        & (paired["level"] == level)
    ]
    return None if match.empty else match.iloc[0].to_dict()


def table_one_markdown(paired: pd.DataFrame, objective: str = "tar") -> str:
    """The paper's Table I from a :func:`paired_table`: per policy, baseline, objective and their difference.

    Three rows per policy: the baseline and the objective (mean ± std over the paired seeds), then
    ``Δ`` (objective - baseline; mean and 95% CI over seeds) and a row of paired t-test p-values.
    Columns: success per difficulty group and overall (%), 100 x Fast20 and 100 x NEPS (lower is
    better). ``-``: no finite pair (e.g. NEPS with no success).

    Args:
        paired: a :func:`paired_table`.
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
                return _fmt_pm(c["baseline_mean"], c["baseline_std"])
            if kind == "obj":
                return _fmt_pm(c["objective_mean"], c["objective_std"])
            if kind == "delta":
                ci = "" if math.isnan(c["ci_low"]) else f" [{c['ci_low']:+.2f}, {c['ci_high']:+.2f}]"
                return f"{c['delta_mean']:+.2f}{ci}"
            return _fmt_p(c["p_value"])

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
        paired: a :func:`paired_table` (differences to ``uniform``).
        table: a :func:`compare` table of the same runs (means ± std over each objective's seeds).
        policy: the policy family shown.

    Returns:
        A markdown table: one row per objective (``uniform`` first), success % per difficulty group
        and overall (mean ± std over seeds), the seeds, and the paired difference of the overall
        success to ``uniform`` with its 95% CI and p-value.
    """
    levels = [lv for lv in _table_levels(table) if lv != "overall"] + ["overall"]
    header = "| objective | seeds | " + " | ".join(lv.replace("_", " ") for lv in levels)
    lines = [header + " | Δ overall vs uniform [95% CI] | p |", "|" + "---|" * (4 + len(levels))]
    rows = table[table["policy"] == policy]
    for rec in rows.to_dict("records"):
        cells = [
            _fmt_pm(rec.get(f"success_{lv}_mean", math.nan), rec.get(f"success_{lv}_std", math.nan)) for lv in levels
        ]
        c = _cell(paired, policy, rec["objective"], "success", "overall")
        if c is None or c["n_pairs"] == 0:
            delta, p = "-", "-"
        else:
            ci = "" if math.isnan(c["ci_low"]) else f" [{c['ci_low']:+.2f}, {c['ci_high']:+.2f}]"
            delta, p = f"{c['delta_mean']:+.2f}{ci} (n={c['n_pairs']})", _fmt_p(c["p_value"])
        lines.append(f"| {rec['objective']} | {rec['n_seeds']} | " + " | ".join(cells) + f" | {delta} | {p} |")
    return "\n".join(lines)


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
        table: a :func:`compare` table holding ``uniform`` and ``objective`` rows.
        path: the PNG to write (atomically).
        objective: the treatment drawn against ``uniform``.
        caption: provenance text for the footer.

    Returns:
        ``path``.

    Raises:
        ValueError: not a :func:`compare` table, or no policy with both objectives.
    """
    _check_table(table, ["policy", "objective", "success_overall_mean", "fast20_overall_mean", "neps_overall_mean"])
    short = {"overall": "O", "easy": "E", "medium": "M", "hard": "H", "very_hard": "VH"}
    levels = _table_levels(table)
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
    fig = _new_figure(6.0, 6.0)
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
    return _save_png(fig, path, caption or _provenance(rows))


def phase_labels(gripper: Sequence[float], onset: float = 0.1, completion: float = 0.15) -> np.ndarray:
    """Phase of every step of one demonstration, from its gripper action (action[3], > 0 = closing).

    The anchor is the gripper-closing step ``c`` (:func:`first_gripper_close`). With ``T`` steps,
    ``w = max(1, ceil(onset * T))`` and ``k = max(1, ceil(completion * T))``:

    * ``approach``: ``[0, c - w)``;
    * ``contact_onset``: ``[max(0, c - w), min(T, c + w))``, the window around the closing step;
    * ``transport``: ``[c + w, max(c + w, T - k))``;
    * ``completion``: the last ``k`` steps that are not in the onset window.

    Without a closing step (a task that never grasps, or a gripper closed from the start) there is
    no anchor: the last ``k`` steps are ``completion`` and every other step ``approach``.

    Args:
        gripper: the gripper action along the demonstration, shape ``[T]``.
        onset: half-width of the contact-onset window, as a fraction of ``T``.
        completion: length of the completion window, as a fraction of ``T``.

    Returns:
        ``[T]`` array of phase names (:data:`PHASES`).

    Raises:
        ValueError: an empty signal, or fractions outside [0, 1].
    """
    for name, value in (("onset", onset), ("completion", completion)):
        if not 0 <= value <= 1:
            raise ValueError(f"{name} must be a fraction in [0, 1], got {value}")
    g = np.asarray(gripper, dtype=float)
    T = len(g)
    if T == 0:
        raise ValueError("the gripper signal is empty")
    w, k = max(1, math.ceil(onset * T)), max(1, math.ceil(completion * T))
    labels = np.full(T, "approach", dtype=object)
    c = first_gripper_close(g)
    if c is None:
        labels[max(0, T - k) :] = "completion"
        return labels
    a, b = max(0, c - w), min(T, c + w)
    labels[a:b] = "contact_onset"
    labels[b:] = "transport"
    labels[max(b, T - k) :] = "completion"
    return labels


def phase_weight_mass(weights_df: pd.DataFrame, step: int | None = None, **phase_kw) -> pd.DataFrame:
    """Share of steps and of TAR weight mass in each phase, per recorded demonstration.

    Args:
        weights_df: ``weights.csv`` rows (:data:`WEIGHTS_COLUMNS`), optionally with a ``run`` column
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
    missing = [c for c in WEIGHTS_COLUMNS if c not in weights_df.columns]
    if missing:
        raise ValueError(f"weights table is missing the column(s) {missing}; expected {list(WEIGHTS_COLUMNS)}")
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
    fig = _new_figure(8.0, max(2.8, 0.38 * n + 1.8))
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
    return _save_png(fig, path, caption or "critical windows")


def plot_weight_phases(
    weights_df: pd.DataFrame,
    path: str | os.PathLike,
    tasks: Sequence[str],
    step: int | None = None,
    caption: str = "",
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
        **phase_kw: ``onset`` and ``completion`` of :func:`phase_labels`.

    Returns:
        ``path``.

    Raises:
        ValueError: no tasks, missing columns, or a task without a recording (the available ones are listed).
    """
    missing = [c for c in WEIGHTS_COLUMNS if c not in weights_df.columns]
    if missing:
        raise ValueError(f"weights table is missing the column(s) {missing}; expected {list(WEIGHTS_COLUMNS)}")
    if not tasks:
        raise ValueError("name at least one task to plot")
    step = int(weights_df["step"].max()) if step is None else step
    df = weights_df[weights_df["step"] == step]
    for task in tasks:
        if task not in set(df["task"]):
            raise ValueError(f"no weights for task {task!r} at step {step}; tasks: {sorted(df['task'].unique())}")
    from matplotlib.patches import Patch

    height = 2.6 * len(tasks) + 1.2
    fig = _new_figure(8.0, height)
    fig.subplots_adjust(left=0.12, right=0.9, top=1 - 0.5 / height, bottom=0.75 / height, hspace=0.55)
    axes = fig.subplots(len(tasks), 1, squeeze=False)[:, 0]
    for ax, task in zip(axes, tasks):
        tdf = df[df["task"] == task]
        one = tdf[tdf["episode"] == tdf["episode"].min()].sort_values("t")
        t = one["t"].to_numpy()
        loss, weight = one["loss"].to_numpy(dtype=float), one["weight"].to_numpy(dtype=float)
        labels = phase_labels(one["gripper"].to_numpy(), **phase_kw)
        ax_w = ax.twinx()
        for a, b in _runs_of(weight > 1.0):
            ax.axvspan(t[a] - 0.5, t[b] + 0.5, color="C1", alpha=0.2, linewidth=0)
        top = max(float(loss.max()), 1e-12)
        for phase in PHASES:
            for a, b in _runs_of(labels == phase):
                ax.axvspan(
                    t[a] - 0.5, t[b] + 0.5, ymin=0, ymax=0.05, color=_PHASE_COLOURS[phase], alpha=0.9, linewidth=0
                )
        ax.plot(t, loss, color="C0", linewidth=1.1)
        ax_w.plot(t, weight, color="C3", linewidth=1.1)
        ax_w.axhline(1.0, color="C3", linestyle=":", linewidth=0.8)
        close = first_gripper_close(one["gripper"].to_numpy())
        if close is not None:
            ax.axvline(t[close], color="k", linestyle="--", linewidth=0.9)
        ax.set_ylim(0, top * 1.1)
        ax_w.set_ylim(bottom=0)
        ax.set_ylabel("loss", color="C0", fontsize=8)
        ax_w.set_ylabel("TAR weight", color="C3", fontsize=8)
        anchor = f"gripper closes at t = {t[close]}" if close is not None else "no gripper closing: no contact anchor"
        ax.set_title(f"{task}, episode {int(one['episode'].iloc[0])} ({anchor})", fontsize=9)
    axes[-1].set_xlabel(f"time step t along the demonstration (weights at training step {step})")
    handles = [Patch(color="C1", alpha=0.2, label="weight > 1")]
    handles += [Patch(color=_PHASE_COLOURS[p], label=p.replace("_", " ")) for p in PHASES]
    fig.legend(handles=handles, loc="upper center", ncol=5, fontsize=8, frameon=False)
    return _save_png(fig, path, caption or f"weights at step {step}")


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
    fig = _new_figure(6.5, 4.4)
    fig.subplots_adjust(left=0.12, right=0.97, top=0.9, bottom=0.16)
    ax = fig.add_subplot()
    for i, (objective, odf) in enumerate(sorted(df.groupby("objective"), key=lambda kv: _objective_key(kv[0]))):
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
    return _save_png(fig, path, caption or title)


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
    fig = _new_figure(max(4.5, 3.6 * len(panels) + 1.0), 4.0)
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
    return _save_png(fig, path, caption or title)


def plot_group_deltas(
    paired: pd.DataFrame, path: str | os.PathLike, objective: str = "tar", caption: str | None = None
) -> Path:
    """The paper's Fig. 3(c): per difficulty group, Δ success (bars) and Δ 100 x Fast20 (line).

    Bars: the paired difference of success (objective - baseline, percentage points), averaged over
    policies; error bars: the 95% CI over seeds with one policy, the std over policies with several
    (the paper's across-family variability). Line (right axis): baseline - objective of 100 x Fast20
    (positive = the objective is faster), averaged over policies.

    Args:
        paired: a :func:`paired_table`.
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
            errs.append(_zero_nan(float(s["ci_high"].iloc[0] - s["delta_mean"].iloc[0])))
        else:
            errs.append(_zero_nan(float(s["delta_mean"].std(ddof=1))) if len(s) > 1 else 0.0)
        line.append(-float(f["delta_mean"].mean()) if len(f) else math.nan)
    fig = _new_figure(6.5, 4.2)
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
    return _save_png(fig, path, caption or f"paired differences, {len(policies)} policies")
