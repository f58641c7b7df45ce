"""Run folders of the training job: the run's name and identity, and the checks made before writing into a folder.

They read the plain dict of a job's settings, the run folder's format (a run's saved config, or
:func:`~tar_rl.recipes.config.config_dict` of a typed one). A config saved by an older version is read through
:func:`migrate_config` where a run folder or checkpoint is read (resuming, ``init.from``, ``tar-rl eval``, a study's
``collect``); ``benchmarks/migrate_configs.py`` applied it once to the committed runs.
"""

from __future__ import annotations

import copy
import dataclasses
from pathlib import Path

from tar_rl import runs
from tar_rl.io import check_writable
from tar_rl.objectives import WEIGHTINGS
from tar_rl.runs import (
    CHECKPOINT,
    config_differences,
    load_checkpoint,
)

from .config import ObjectiveConfig, default_config, objective_config
from .errors import ConfigError

__all__ = [
    "check_resumable",
    "check_same_run",
    "identity",
    "identity_differences",
    "last_checkpoint",
    "migrate_config",
    "prepare_run_dir",
    "run_name",
    "started_config",
    "with_defaults",
]


def _other_defaults() -> dict:
    """Every registered weighting's parameters at their defaults, as config values."""
    common = {f.name for f in dataclasses.fields(ObjectiveConfig)}
    return {
        key: value
        for name in WEIGHTINGS
        for key, value in dataclasses.asdict(objective_config(name)()).items()
        if key not in common
    }


def migrate_config(saved: dict) -> dict:
    """A saved config as this version writes it: its objective section without the parameters of other weightings
    that hold their defaults.

    tar-rl versions before each weighting owned its parameters saved every registered weighting's parameters in
    every run's objective section; the ones its weighting does not have, at their defaults, change nothing it
    computes. A parameter of another weighting at another value stays (a typed config refuses it; a run's name
    keeps it). A config of today's format, or one naming no registered weighting, comes back as it is (a copy).
    """
    config = copy.deepcopy(saved)
    objective = config.get("objective") if isinstance(config, dict) else None
    if not isinstance(objective, dict) or objective.get("name") not in WEIGHTINGS:
        return config
    own = {f.name for f in dataclasses.fields(objective_config(objective["name"]))}
    other = _other_defaults()
    config["objective"] = {
        key: value for key, value in objective.items() if key in own or key not in other or other[key] != value
    }
    return config


def with_defaults(saved: dict) -> dict:
    """A saved config completed with the defaults of settings it does not hold."""

    def merge(base: dict, over: dict) -> dict:
        out = dict(base)
        for key, value in over.items():
            out[key] = merge(base[key], value) if isinstance(value, dict) and isinstance(base.get(key), dict) else value
        return out

    return merge(default_config(saved["objective"]["name"], saved["policy"]["name"]), copy.deepcopy(saved))


def run_name(config: dict) -> str:
    """The run's directory name: ``<objective>-<policy>-s<seed>-<hash>`` (:func:`tar_rl.runs.run_name` measured
    against the default job of its objective and head)."""
    return runs.run_name(config, default_config(config["objective"]["name"], config["policy"]["name"]))


def identity(config: dict) -> dict:
    """The settings that make the run differ from the default job (:func:`tar_rl.runs.identity`)."""
    return runs.identity(config, default_config(config["objective"]["name"], config["policy"]["name"]))


def identity_differences(old: dict, new: dict) -> list[str]:
    """``key.path: old -> new`` for every setting of a run's identity that differs between two configs (settings
    a config lacks read as their defaults); empty when both name the same run."""
    return config_differences(runs.identity(with_defaults(old), {}), runs.identity(with_defaults(new), {}))


def prepare_run_dir(run_dir: Path) -> None:
    try:
        check_writable(run_dir)
    except OSError as err:
        raise ConfigError(f"cannot write to the run directory {run_dir}: {err}") from None


def last_checkpoint(run_dir: Path) -> str:
    """Where a stopped run resumes from, in words: the last checkpoint's step and file, or that there is none."""
    path = run_dir / CHECKPOINT
    try:
        step = load_checkpoint(path)["step"]
    except FileNotFoundError:
        return f"no checkpoint was written yet in {run_dir}"
    except ValueError:
        return f"{path} cannot be read"
    return f"the last good checkpoint (step {step}) is kept in {path}"


def check_resumable(run_dir: Path, config: dict) -> dict | None:
    """The checkpoint to resume from (None for a new run); refuses a folder whose run has other settings.

    Before its first checkpoint a started run is known by its ``config.yaml``, which is compared the same way.
    A run started by an older version is compared as :func:`migrate_config` reads its config.
    """
    path = run_dir / CHECKPOINT
    if not path.exists():
        started = started_config(run_dir)
        check_same_run(run_dir, None if started is None else migrate_config(started), config)
        return None
    try:
        state = load_checkpoint(path)
    except ValueError as err:
        raise ConfigError(
            f"{str(err).splitlines()[0]}; remove {path} to start the run again from step 0, or choose another run_dir"
        ) from err
    check_same_run(run_dir, migrate_config(state["config"]), config)
    return state


def started_config(run_dir: Path) -> dict | None:
    """The config a started run wrote into ``run_dir/config.yaml`` (None if there is none)."""
    path = run_dir / "config.yaml"
    if not path.exists():
        return None
    import yaml

    try:
        # YAML's safe loader: plain values only (no Python tags), and no interpolation of ${...}.
        saved = yaml.safe_load(path.read_text())
        if not isinstance(saved, dict):
            raise ValueError(f"it holds a {type(saved).__name__}, not a config")
    except (OSError, UnicodeDecodeError, ValueError, yaml.YAMLError) as err:
        first = str(err).splitlines()[0] if str(err) else type(err).__name__
        raise ConfigError(f"{path} cannot be read ({first}); remove it or choose another run_dir") from err
    return saved


def check_same_run(run_dir: Path, saved: dict | None, config: dict) -> None:
    if saved is None:
        return
    diff = identity_differences(saved, config)
    if diff:
        raise ConfigError(
            f"{run_dir} holds a run with other settings ({'; '.join(diff)}); choose another run_dir or remove it"
        )
