"""Run folders of the training job: the run's name and identity, and the checks made before writing into a folder.

They read the plain dict of a job's settings, the run folder's format (a run's saved config, or
:func:`~tar_rl.recipes.config.config_dict` of a typed one).
"""

from __future__ import annotations

import copy
from pathlib import Path

from tar_rl import runs
from tar_rl.io import check_writable
from tar_rl.runs import (
    CHECKPOINT,
    config_differences,
    load_checkpoint,
)

from .config import default_config, objective_section
from .errors import ConfigError

__all__ = [
    "check_resumable",
    "check_same_run",
    "identity",
    "identity_differences",
    "last_checkpoint",
    "prepare_run_dir",
    "run_name",
    "started_config",
    "with_defaults",
]


def _own(config: dict) -> dict:
    """``config`` without other weightings' parameters at their defaults (:func:`objective_section`)."""
    return {**config, "objective": objective_section(config["objective"])}


def with_defaults(saved: dict) -> dict:
    """A saved config completed with the defaults of settings it does not hold (other weightings' parameters at
    their defaults left out)."""

    def merge(base: dict, over: dict) -> dict:
        out = dict(base)
        for key, value in over.items():
            out[key] = merge(base[key], value) if isinstance(value, dict) and isinstance(base.get(key), dict) else value
        return out

    return merge(default_config(saved["objective"]["name"], saved["policy"]["name"]), copy.deepcopy(_own(saved)))


def run_name(config: dict) -> str:
    """The run's directory name: ``<objective>-<policy>-s<seed>-<hash>`` (:func:`tar_rl.runs.run_name` measured
    against the default job of its objective and head; other weightings' parameters at their defaults, which a
    saved config may list, are not part of it)."""
    return runs.run_name(_own(config), default_config(config["objective"]["name"], config["policy"]["name"]))


def identity(config: dict) -> dict:
    """The settings that make the run differ from the default job (:func:`tar_rl.runs.identity`)."""
    return runs.identity(_own(config), default_config(config["objective"]["name"], config["policy"]["name"]))


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
    """
    path = run_dir / CHECKPOINT
    if not path.exists():
        check_same_run(run_dir, started_config(run_dir), config)
        return None
    try:
        state = load_checkpoint(path)
    except ValueError as err:
        raise ConfigError(
            f"{str(err).splitlines()[0]}; remove {path} to start the run again from step 0, or choose another run_dir"
        ) from err
    check_same_run(run_dir, state["config"], config)
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
