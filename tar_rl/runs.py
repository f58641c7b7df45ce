"""Run directories: layout, identity, logs, checkpoints and the printed results table.

A run directory holds the files named below (:data:`CONFIG_FILE`, :data:`CHECKPOINT`,
:data:`METRICS_FILE`, :data:`ROLLOUTS_FILE`, :data:`WEIGHTS_FILE`, :data:`SUMMARY_FILE`): the recipe
(``recipes/offline_bc.py``, through :class:`RunLogs` and :func:`save_checkpoint`) writes them and
``tar_rl.report`` reads them, both through these names. A run is identified by the settings that change
what it computes (:func:`identity`), which names its directory (:func:`run_name`) and decides whether a
checkpoint may be resumed with a config.

torch is imported by the functions that need it, so that reading run directories (``tar-rl report``)
does not import it.
"""

from __future__ import annotations

import copy
import hashlib
import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from tar_rl.io import save_torch_atomic, write_csv_atomic
from tar_rl.metrics import REQUIRED_COLUMNS, as_percent

__all__ = [
    "CHECKOUT_FOLDERS",
    "CHECKPOINT",
    "CHECKPOINT_FORMAT",
    "CHECKPOINT_KEYS",
    "CONFIG_FILE",
    "CONFIG_FOLDERS",
    "CONFIG_PATHS",
    "METRICS_COLUMNS",
    "METRICS_FILE",
    "NOT_IDENTITY",
    "ROLLOUTS_COLUMNS",
    "ROLLOUTS_FILE",
    "SUMMARY_FILE",
    "WEIGHTS_COLUMNS",
    "WEIGHTS_DIM_COLUMN",
    "WEIGHTS_FILE",
    "WEIGHTS_FLOAT_FORMAT",
    "RunLogs",
    "config_differences",
    "git_commit",
    "identity",
    "json_metric",
    "last_metric",
    "load_checkpoint",
    "machine",
    "portable_config",
    "portable_path",
    "portable_summary",
    "print_table",
    "rollout_records",
    "run_name",
    "save_checkpoint",
    "summary_rows",
    "weights_columns",
]

# -- The run directory's files and their columns (written by the recipe, read by the report) ----------
#: The resolved config (YAML), written when the run starts.
CONFIG_FILE = "config.yaml"
#: Model, optimiser and log state for resuming (:func:`save_checkpoint`).
CHECKPOINT = "checkpoint.pt"
CHECKPOINT_FORMAT = 2  # 2: data_info carries the instruction text of every task id
#: What every checkpoint of :data:`CHECKPOINT_FORMAT` holds (its readers index them); a finished run's also
#: holds ``summary``, its ``summary.json``.
CHECKPOINT_KEYS: tuple[str, ...] = (
    "step",
    "finished",
    "config",
    "data_info",
    "policy",
    "ema_policy",
    "objective",
    "optimizer",
    "scheduler",
    "ema",
    "sampler_rng",
    "torch_rng",
    "logs",
    "skipped",
    "train_seconds",
)
#: Training and evaluation scalars, columns :data:`METRICS_COLUMNS`.
METRICS_FILE = "metrics.csv"
METRICS_COLUMNS: tuple[str, ...] = ("step", "phase", "name", "value")
#: Every evaluation rollout: the evaluator's per-rollout columns and the training ``step``.
ROLLOUTS_FILE = "eval_rollouts.csv"
#: The columns every :data:`ROLLOUTS_FILE` has (the ones the metrics read, and ``step``); evaluators add others.
ROLLOUTS_COLUMNS: tuple[str, ...] = (*REQUIRED_COLUMNS, "step")
#: Per-step loss and weight along recorded demonstrations, columns :func:`weights_columns`.
WEIGHTS_FILE = "weights.csv"
#: How :data:`WEIGHTS_FILE` writes its floats: its losses, weights and gripper actions are float32, and nine
#: significant digits are the fewest that give back every float32 exactly (a third smaller than pandas' 17).
WEIGHTS_FLOAT_FORMAT = "%.9g"
#: The columns every :data:`WEIGHTS_FILE` has: the training step of the recording, the task, the demonstration
#: (episode id) and its time step ``t``, the per-step loss, TAR's weight and the gripper (last) action dim.
#: A head whose loss has event dims adds ``loss_dim0`` .. ``loss_dim{A-1}``, each action dim's loss at the step.
WEIGHTS_COLUMNS: tuple[str, ...] = ("step", "task", "episode", "t", "loss", "weight", "gripper")
#: The name of action dim ``i``'s loss column in :data:`WEIGHTS_FILE`.
WEIGHTS_DIM_COLUMN = "loss_dim{}"
#: The final evaluation, timings and provenance, written last (``"finished": true``).
SUMMARY_FILE = "summary.json"

# Settings that do not change what a run computes: left out of the run's identity (its directory
# name and the check made when resuming).
NOT_IDENTITY = (
    ("objective", "compile"),
    ("data", "workers"),
    ("data", "root"),
    ("eval", "workers"),
    ("logging", "progress"),
    ("diagnostics",),
    ("init", "from"),
    ("threads",),
    ("runs_root",),
    ("run_dir",),
)


# -- Paths in tracked files: relative to the repository, never the machine's --------------------------------
#: The folders a checkout holds when it runs the default job from its root: ``data.root``, ``runs_root`` and
#: ``tar-rl report``'s output (the repository's ``.gitignore`` lists them).
CHECKOUT_FOLDERS: tuple[str, ...] = ("datasets", "runs", "report")
#: The settings of a config that name the machine's files; none is part of a run's identity (:data:`NOT_IDENTITY`).
CONFIG_PATHS: tuple[tuple[str, ...], ...] = (("data", "root"), ("runs_root",), ("init", "from"), ("run_dir",))
#: The folder settings of a config and the default job's folder each stands for.
CONFIG_FOLDERS: dict[tuple[str, ...], str] = {("data", "root"): "datasets", ("runs_root",): "runs"}


def portable_path(path: str, root: str | Path) -> str:
    """``path`` as a tracked file records it: relative to the repository's root, ``root``.

    A relative path is kept. An absolute path inside ``root`` is written relative to it; any other absolute path
    from its first component that names a folder of a checkout (an entry of ``root`` or one of
    :data:`CHECKOUT_FOLDERS`): ``/elsewhere/datasets`` is ``datasets``, ``/other/checkout/benchmarks/results`` is
    ``benchmarks/results``, ``/elsewhere/study/runs/<run>`` is ``runs/<run>``.

    Raises:
        ValueError: ``path`` is absolute, outside ``root``, and names no folder of a checkout.
    """
    pure = Path(path)
    if not pure.is_absolute():
        return path
    root = Path(root)
    if pure.is_relative_to(root):
        return pure.relative_to(root).as_posix() or "."
    entries = root.iterdir() if root.is_dir() else ()
    folders = {*CHECKOUT_FOLDERS, *(p.name for p in entries if not p.name.startswith("."))}
    for i, part in enumerate(pure.parts):
        if part in folders:
            return Path(*pure.parts[i:]).as_posix()
    raise ValueError(
        f"{path} lies outside the repository ({root}) and in none of a checkout's folders "
        f"({', '.join(sorted(folders))}): a tracked file cannot name it relative to the repository"
    )


def _portable_setting(keys: tuple[str, ...], value: str, root: str | Path, runs_root) -> str:
    """The path setting ``keys`` of a config whose ``runs_root`` is ``runs_root``, by :func:`portable_config`'s rule."""
    try:
        return portable_path(value, root)
    except ValueError as err:
        if keys in CONFIG_FOLDERS:
            return CONFIG_FOLDERS[keys]
        if isinstance(runs_root, str) and runs_root and Path(value).is_relative_to(runs_root):
            return (Path(CONFIG_FOLDERS[("runs_root",)]) / Path(value).relative_to(runs_root)).as_posix()
        raise ValueError(f"{'.'.join(keys)}: {err}") from None


def portable_config(config: dict, root: str | Path) -> dict:
    """A copy of ``config`` with its :data:`CONFIG_PATHS` written relative to the repository ``root`` (what a
    tracked copy of a run's config records; the run's identity, which leaves them out, is unchanged).

    Each is written by :func:`portable_path`; where that cannot place it, ``data.root`` and ``runs_root`` are the
    default job's folders they stand for (:data:`CONFIG_FOLDERS`), and a run directory under ``runs_root``
    (``init.from``, ``run_dir``) is written under ``runs``.

    Raises:
        ValueError: a run directory outside ``runs_root`` cannot be placed either, naming the setting.
    """
    runs_root = config.get("runs_root")
    config = copy.deepcopy(config)
    for keys in CONFIG_PATHS:
        node = config
        for key in keys[:-1]:
            node = node.get(key) if isinstance(node, dict) else None
        if isinstance(node, dict) and isinstance(node.get(keys[-1]), str) and node[keys[-1]]:
            node[keys[-1]] = _portable_setting(keys, node[keys[-1]], root, runs_root)
    return config


def portable_summary(summary: dict, root: str | Path) -> dict:
    """A copy of a run's summary (:data:`SUMMARY_FILE`) with the paths it records written relative to the
    repository ``root``: its config's (:func:`portable_config`), a post-training run's source checkpoint
    (``init.from``, by the same rule as the config's) and the training dataset's folder (``data.path``: the
    folder of the cache ``data.root`` when the config names no dataset folder of its own, written under that
    setting's portable form; a folder the config names, by :func:`portable_path`).

    Raises:
        ValueError: one of them cannot be placed, naming the setting.
    """
    summary = copy.deepcopy(summary)
    config = summary.get("config")
    runs_root = config.get("runs_root") if isinstance(config, dict) else None
    data_cfg = (config.get("data") or {}) if isinstance(config, dict) else {}
    if isinstance(config, dict):
        summary["config"] = portable_config(config, root)
    init = summary.get("init")
    if isinstance(init, dict) and isinstance(init.get("from"), str) and init["from"]:
        init["from"] = _portable_setting(("init", "from"), init["from"], root, runs_root)
    data = summary.get("data")
    if isinstance(data, dict) and isinstance(data.get("path"), str) and data["path"]:
        if not data_cfg.get("path") and isinstance(data_cfg.get("root"), str) and data_cfg["root"]:
            folder = _portable_setting(("data", "root"), data_cfg["root"], root, runs_root)
            data["path"] = (Path(folder) / Path(data["path"]).name).as_posix()
        else:
            try:
                data["path"] = portable_path(data["path"], root)
            except ValueError as err:
                raise ValueError(f"data.path: {err}") from None
    return summary


def _differences(config: dict, defaults: dict) -> dict:
    """The entries of ``config`` whose value differs from ``defaults`` (nested dicts compared entry by entry;
    an entry ``defaults`` lacks always differs, one ``config`` lacks never does)."""
    out = {}
    for key, value in config.items():
        default = defaults.get(key, _ABSENT) if isinstance(defaults, dict) else _ABSENT
        if isinstance(value, dict) and isinstance(default, dict):
            nested = _differences(value, default)
            if nested:
                out[key] = nested
        elif value != default:
            out[key] = copy.deepcopy(value)
    return out


_ABSENT = object()


def identity(config: dict, defaults: dict) -> dict:
    """The settings that determine what a run computes, measured against the default job: the entries of
    ``config`` that differ from ``defaults`` (the default config of the same objective and head), without
    :data:`NOT_IDENTITY`.

    Measuring against the defaults keeps names stable when a setting is added with a default that
    computes what runs computed before it; changing a default changes the name of every run that
    relied on it, as it should. A post-training run (``init.from``) is identified by its source
    run's name, ``init.source`` (which holds the source's own identity hash), not by its path.

    Raises:
        ValueError: ``init.from`` is set but ``init.source`` has not been filled in (the recipe's
            ``validate`` does that from the source checkpoint).
    """
    init = config.get("init") or {}
    if init.get("from") and not init.get("source"):
        raise ValueError("init.from is set but init.source is not: validate the config first")
    ident = _differences(config, defaults)
    for path in NOT_IDENTITY:
        node = ident
        for key in path[:-1]:
            node = node.get(key, {})
        node.pop(path[-1], None)
    return {k: v for k, v in ident.items() if v != {}}


def run_name(config: dict, defaults: dict) -> str:
    """``<objective>-<policy>-s<seed>-<hash>``, the hash over :func:`identity` (the settings that change the
    result, measured against ``defaults``)."""
    digest = hashlib.sha256(json.dumps(identity(config, defaults), sort_keys=True).encode()).hexdigest()[:8]
    return f"{config['objective']['name']}-{config['policy']['name']}-s{config['seed']}-{digest}"


def config_differences(old: Any, new: Any, prefix: str = "") -> list[str]:
    """``key.path: old -> new`` for every setting that differs between two nested config dicts."""
    if isinstance(old, dict) and isinstance(new, dict):
        out = []
        for key in sorted(set(old) | set(new), key=str):
            out += config_differences(old.get(key, "<absent>"), new.get(key, "<absent>"), f"{prefix}{key}.")
        return out
    return [] if old == new else [f"{prefix[:-1]}: {old!r} -> {new!r}"]


def weights_columns(width: int) -> list[str]:
    """The :data:`WEIGHTS_FILE` columns of rows of ``width`` values: :data:`WEIGHTS_COLUMNS`, then one
    :data:`WEIGHTS_DIM_COLUMN` per further value (``loss_dim0``, ``loss_dim1``, ...)."""
    extra = width - len(WEIGHTS_COLUMNS)
    if extra < 0:
        raise ValueError(f"a weights row has at least {len(WEIGHTS_COLUMNS)} values ({WEIGHTS_COLUMNS}), got {width}")
    return [*WEIGHTS_COLUMNS, *(WEIGHTS_DIM_COLUMN.format(i) for i in range(extra))]


def summary_rows(step: int, table: pd.DataFrame) -> list[tuple]:
    """``metrics.csv`` rows (step, "eval", "<metric>/<group>", value) of a ``summarize`` table's groups and overall."""
    rows = []
    for rec in table[table["level"] != "task"].itertuples():
        for metric in ("success", "fast20", "neps"):
            rows.append((step, "eval", f"{metric}/{rec.name}", float(getattr(rec, metric))))
    return rows


def json_metric(value: float):
    """A metric for JSON: an infinite NEPS becomes the string ``"inf"``."""
    return "inf" if math.isinf(value) else value


def print_table(table: pd.DataFrame, file=None) -> None:
    """Success, 100 x Fast20 and 100 x NEPS per difficulty group and overall, as the paper reports them."""
    pct = as_percent(table[table["level"] != "task"])
    lines = [f"{'group':<11}{'tasks':>6}{'rollouts':>10}{'success %':>11}{'Fast20':>9}{'NEPS':>9}"]
    for rec in pct.itertuples():
        lines.append(
            f"{rec.name:<11}{rec.n_tasks:>6}{rec.n_rollouts:>10}{rec.success:>11.1f}{rec.fast20:>9.1f}{rec.neps:>9.1f}"
        )
    print("\n".join(lines), file=file or sys.stdout)


class RunLogs:
    """Everything a run logs, kept in memory (and in the checkpoint) and written out atomically.

    Files (in ``run_dir``): :data:`METRICS_FILE` (:data:`METRICS_COLUMNS`), :data:`ROLLOUTS_FILE` (the
    evaluator's columns and step), :data:`WEIGHTS_FILE` (:func:`weights_columns` of its longest row: the
    per-dim losses when the head has them; a shorter row, e.g. one recorded before a resume by a version
    that recorded no per-dim losses, has them empty).
    """

    def __init__(self, run_dir: Path, metrics=None, rollouts=None, weights=None):
        self.run_dir = run_dir
        self.metrics: list[tuple] = list(metrics or [])
        self.rollouts: list[dict] = list(rollouts or [])
        self.weights: list[tuple] = list(weights or [])

    def state(self) -> dict:
        return {"metrics": self.metrics, "rollouts": self.rollouts, "weights": self.weights}

    def write(self) -> None:
        write_csv_atomic(pd.DataFrame(self.metrics, columns=list(METRICS_COLUMNS)), self.run_dir / METRICS_FILE)
        if self.rollouts:
            write_csv_atomic(pd.DataFrame(self.rollouts), self.run_dir / ROLLOUTS_FILE)
        if self.weights:
            width = max(len(row) for row in self.weights)
            rows = [(*row, *[math.nan] * (width - len(row))) for row in self.weights]
            df = pd.DataFrame(rows, columns=weights_columns(width))
            write_csv_atomic(df, self.run_dir / WEIGHTS_FILE, float_format=WEIGHTS_FLOAT_FORMAT)


def rollout_records(step: int, df: pd.DataFrame) -> list[dict]:
    """Rows of an evaluator table with the training ``step`` added, as plain Python values."""
    df = df.assign(step=step)
    return [
        {k: (v.item() if isinstance(v, np.generic) else v) for k, v in rec.items()} for rec in df.to_dict("records")
    ]


def load_checkpoint(path: str | Path) -> dict:
    """Read a checkpoint written by :func:`save_checkpoint`.

    Raises:
        FileNotFoundError: no file at ``path`` (a run directory is accepted and its checkpoint read).
        ValueError: the file is not a tar-rl checkpoint of a known format, or lacks one of :data:`CHECKPOINT_KEYS`.
    """
    path = Path(path)
    if path.is_dir():
        path = path / CHECKPOINT
    if not path.is_file():
        raise FileNotFoundError(f"no checkpoint at {path}")
    import torch

    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:
        raise ValueError(f"{path} is not a readable tar-rl checkpoint: {err}") from None
    if not isinstance(state, dict) or state.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(f"{path} is not a tar-rl checkpoint of format {CHECKPOINT_FORMAT}")
    missing = [key for key in CHECKPOINT_KEYS if key not in state]
    if missing or not isinstance(state["config"], dict) or not isinstance(state["step"], int):
        what = f"lacks {missing}" if missing else "holds no config or step"
        raise ValueError(f"{path} is a tar-rl checkpoint of format {CHECKPOINT_FORMAT} that {what} (incomplete)")
    return state


def save_checkpoint(state: dict, run_dir: str | Path) -> Path:
    """Write ``state`` (plus the format tag) as ``run_dir/checkpoint.pt`` atomically.

    ``state`` must hold only what ``torch.load(weights_only=True)`` reads back: tensors, numbers,
    strings, lists, tuples and dicts of them.
    """
    return save_torch_atomic({**state, "format": CHECKPOINT_FORMAT}, Path(run_dir) / CHECKPOINT)


def last_metric(rows: list[tuple], name: str) -> float | None:
    """The last logged value of the training metric ``name`` (None if never logged)."""
    values = [r[3] for r in rows if r[1] == "train" and r[2] == name]
    return values[-1] if values else None


def git_commit() -> str | None:
    """The commit of the checkout this code runs from (None outside git)."""
    import subprocess

    try:
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=Path(__file__).parent, capture_output=True, text=True, timeout=5
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() or None if out.returncode == 0 else None


def machine() -> dict:
    """The machine a run trains on: host name, cores, platform and accelerator (for ``summary.json``)."""
    import os
    import platform
    import socket

    import torch

    return {
        "hostname": socket.gethostname(),
        "cores": os.cpu_count(),
        "platform": platform.platform(),
        "device": torch.cuda.get_device_name(0) if torch.cuda.is_available() else "cpu",
    }
