"""Reading run directories: :class:`Run`, :func:`load_run` and :func:`expand_run_dirs`.

A run directory (written by the offline BC recipe; its files are named in :mod:`tar_rl.runs`) holds
``config.yaml``, ``summary.json`` (once the run has finished), ``metrics.csv``, ``eval_rollouts.csv`` and
optionally ``weights.csv``, each CSV possibly gzip-compressed (``<name>.gz``, as committed results are).
The metrics of a run are always recomputed from its evaluation rollouts (:func:`tar_rl.metrics.summarize`
on the rows of the largest ``step``), never read back from the summary.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd

from tar_rl.metrics import summarize
from tar_rl.runs import (
    CONFIG_FILE,
    METRICS_COLUMNS,
    METRICS_FILE,
    ROLLOUTS_COLUMNS,
    ROLLOUTS_FILE,
    SUMMARY_FILE,
    WEIGHTS_COLUMNS,
    WEIGHTS_FILE,
)

__all__ = ["NOT_EVALUATED", "Run", "expand_run_dirs", "load_run", "run_file"]

#: How the report names a run that finished training without an evaluation.
NOT_EVALUATED = "finished without evaluation (eval.rollouts=0)"


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
        finished: the run finished (``summary.json`` says so) and has final evaluation rows: a run to compare.
        not_evaluated: the run finished training without an evaluation (``eval.rollouts=0``): listed as
            such, never compared (``finished`` is False).
        steps: training steps done (``summary.json``), ``None`` before the run finished.
        final_step: the training step of the final evaluation (largest ``step`` of the rollouts).
        git_commit: the commit the run was trained at (``summary.json``), ``None`` if unknown.
        eval_settings: what two runs must share to be compared: ``tasks`` (sorted task names of the
            final evaluation), ``eval.rollouts`` (rollouts per task), ``eval.seed`` and ``eval.horizon``.
        notes: why the run is unfinished, or other remarks printed with the report.
        summary: the run's ``summary.json`` (empty before the run finished).
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
    not_evaluated: bool = False
    steps: int | None = None
    final_step: int | None = None
    git_commit: str | None = None
    eval_settings: dict = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    summary: dict = field(default_factory=dict)


def _is_run_dir(path: Path) -> bool:
    return path.is_dir() and ((path / CONFIG_FILE).is_file() or (path / SUMMARY_FILE).is_file())


def _read_mapping(path: Path, parse, errors: tuple, what: str, kind: str) -> dict:
    """``parse`` of the file's text, which must be a mapping; errors name the file, ``what`` it is and its ``kind``."""
    try:
        data = parse(path.read_text())
    except (OSError, UnicodeDecodeError, *errors) as err:
        raise ValueError(f"{path}: cannot read the {what}: {err}") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: the {what} must be a {kind}, got {type(data).__name__}")
    return data


def _read_yaml(path: Path) -> dict:
    import yaml

    def parse(text: str):
        try:
            return yaml.safe_load(text)
        except yaml.YAMLError as err:  # the parser's report spans lines (the context, the text, a caret)
            raise ValueError(f"not valid YAML ({_yaml_problem(err)})") from None

    return _read_mapping(path, parse, (ValueError,), "run's config", "YAML mapping")


def _yaml_problem(err) -> str:
    """A YAML parser's error in one line: the problem and where (``expected ',' or ']' at line 3, column 2``)."""
    problem = getattr(err, "problem", None) or str(err).strip().splitlines()[0]
    mark = getattr(err, "problem_mark", None)
    return f"{problem} at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else problem


def _read_summary(path: Path) -> dict:
    data = _read_mapping(path, json.loads, (json.JSONDecodeError,), "run summary", "JSON object")
    if not isinstance(data.get("finished"), bool):
        raise ValueError(f"{path}: the run summary has no boolean 'finished' entry")
    return data


def run_file(run_dir: Path, name: str) -> Path:
    """``run_dir / name``, or its gzip-compressed copy ``name.gz`` when only that exists (committed results)."""
    path = run_dir / name
    packed = run_dir / f"{name}.gz"
    return packed if not path.is_file() and packed.is_file() else path


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


def _read_config_and_summary(path: Path) -> tuple[dict, dict | None]:
    """A run directory's config (``config.yaml``, else the summary's copy) and summary (``None`` before it ends)."""
    if not path.is_dir():
        raise ValueError(f"{path}: not a run directory (no such directory)")
    config_path, summary_path = path / CONFIG_FILE, path / SUMMARY_FILE
    if not _is_run_dir(path):
        raise ValueError(f"{path}: not a run directory (no {CONFIG_FILE} or {SUMMARY_FILE} in it)")
    summary = _read_summary(summary_path) if summary_path.is_file() else None
    if config_path.is_file():
        config = _read_yaml(config_path)
    elif isinstance(summary.get("config"), dict):
        config = summary["config"]
    else:
        raise ValueError(f"{path}: missing {CONFIG_FILE} (and {SUMMARY_FILE} holds no config)")
    return config, summary


def _identity(path: Path, config: dict, info: dict) -> tuple[str, str, int]:
    """The run's objective, policy and seed: from its summary ``info``, else from its config."""
    objective = info.get("objective") or _config_get(config, "objective.name")
    policy = info.get("policy") or _config_get(config, "policy.name")
    seed = info.get("seed", config.get("seed"))
    for key, value in (("objective", objective), ("policy", policy), ("seed", seed)):
        if value is None:
            raise ValueError(f"{path}: the run's {key} is given neither in {SUMMARY_FILE} nor in {CONFIG_FILE}")
    try:
        seed = int(seed)
    except (TypeError, ValueError):
        raise ValueError(f"{path}: the run's seed must be an integer, got {seed!r}") from None
    return str(objective), str(policy), seed


def _read_metrics(path: Path, finished: bool) -> pd.DataFrame:
    """``metrics.csv``; an empty table for an unfinished run that has not written it yet."""
    metrics_path = run_file(path, METRICS_FILE)
    if metrics_path.is_file():
        return _read_csv(metrics_path, METRICS_COLUMNS)
    if finished:
        raise ValueError(f"{path}: missing {METRICS_FILE} (the run's summary says it finished)")
    return pd.DataFrame({c: pd.Series(dtype=object) for c in METRICS_COLUMNS})


def _read_final(path: Path, config: dict) -> tuple[pd.DataFrame | None, int | None, dict]:
    """The final evaluation: its ``summarize`` table, its step and its settings (``None, None, {}`` without rows)."""
    rollouts_path = run_file(path, ROLLOUTS_FILE)
    if not rollouts_path.is_file():
        return None, None, {}
    rollouts = _read_csv(rollouts_path, ROLLOUTS_COLUMNS)
    if not len(rollouts):
        return None, None, {}
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
    return final, final_step, _eval_settings(config, rows)


def load_run(path: str | os.PathLike) -> Run:
    """Read one run directory.

    A directory with ``config.yaml`` (or ``summary.json``) is a run directory. A run without
    ``summary.json`` is still training (the recipe writes the summary last) and is loaded as unfinished,
    as is one whose summary says ``"finished": false`` or one without final evaluation rows; the reason
    is in :attr:`Run.notes`. A finished run trained with ``eval.rollouts=0`` has no evaluation rows and is
    :attr:`Run.not_evaluated`. Files the run has are always checked.

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
    config, summary = _read_config_and_summary(path)
    info = summary or {}
    name = str(info.get("run_name") or path.name)
    objective, policy, seed = _identity(path, config, info)

    notes: list[str] = []
    finished = summary is not None and summary["finished"]
    if summary is None:
        notes.append(f"unfinished: no {SUMMARY_FILE} yet (still training, or stopped)")
    elif not finished:
        notes.append(f"unfinished: {SUMMARY_FILE} says finished: false")
    metrics = _read_metrics(path, finished)
    final, final_step, settings = _read_final(path, config)
    not_evaluated = False
    if final is None and finished:
        finished = False
        if _config_get(config, "eval.rollouts") == 0:
            not_evaluated = True
            notes.append(f"{NOT_EVALUATED}: nothing to compare")
        else:
            notes.append(f"unfinished: no final evaluation rows in {ROLLOUTS_FILE}")

    steps = info.get("steps")
    if finished and steps is not None and final_step != steps:
        notes.append(f"the last evaluation is at step {final_step}, the summary says {steps} steps were trained")
    if finished and summary.get("final"):
        _check_summary_agrees(summary["final"], final, notes)

    weights_path = run_file(path, WEIGHTS_FILE)
    weights = _read_csv(weights_path, WEIGHTS_COLUMNS) if weights_path.is_file() else None
    if weights is not None and len(weights) == 0:
        weights = None

    return Run(
        path=path,
        name=name,
        objective=objective,
        policy=policy,
        seed=seed,
        config=config,
        final=final,
        metrics=metrics,
        weights=weights,
        finished=finished,
        not_evaluated=not_evaluated,
        steps=None if steps is None else int(steps),
        final_step=final_step,
        git_commit=info.get("git_commit"),
        eval_settings=settings,
        notes=notes,
        summary=summary or {},
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
            f"{SUMMARY_FILE} gives overall success {written:.4f}, {ROLLOUTS_FILE} gives {recomputed:.4f} "
            f"(the report uses {ROLLOUTS_FILE})"
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
            raise ValueError(
                f"{p}: not a run directory (no {CONFIG_FILE} or {SUMMARY_FILE}) and holds no run directories"
            )
        out.extend(children)
    return out
