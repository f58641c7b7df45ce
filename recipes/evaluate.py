"""``tar-rl eval``: a saved policy rebuilt from its checkpoint and evaluated on its suite."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import pandas as pd
from tensordict.nn import TensorDictModuleBase

from tar_rl.io import check_writable, write_csv_atomic
from tar_rl.metrics import summarize
from tar_rl.policies import DataInfo
from tar_rl.runs import (
    load_checkpoint,
    print_table,
)

from .builders import make_evaluation_pool, make_evaluator, make_policy
from .config import typed_config
from .errors import ConfigError
from .rundir import migrate_config, with_defaults
from .validate import validate

__all__ = ["evaluate_checkpoint", "policy_from_checkpoint"]


def policy_from_checkpoint(state: dict, path: str | Path = "checkpoint") -> TensorDictModuleBase:
    """Rebuild the saved policy (EMA weights if the run kept them) for inference, on CPU."""
    head = typed_config(migrate_config(state["config"])).policy
    policy = make_policy(head, DataInfo.from_dict(state["data_info"]))
    weights = state["ema_policy"] if state.get("ema_policy") is not None else state["policy"]
    try:
        policy.actor.load_state_dict(weights)
    except RuntimeError as err:
        raise ValueError(
            f"{path}: the saved weights do not fit the policy {head.name!r} built from its config: {err}"
        ) from None
    return policy.actor.eval()


def evaluate_checkpoint(
    path: str | Path,
    tasks: Sequence[str] | None = None,
    rollouts: int | None = None,
    seed: int | None = None,
    horizon: int | None = None,
    workers: int | None = None,
    out: str | Path | None = None,
    progress: bool = True,
) -> pd.DataFrame:
    """Evaluate a saved policy; settings default to the run's ``eval`` config. Prints the table.

    Writes the rollouts to ``out`` (default ``eval-<seed>.csv`` beside the checkpoint) and returns them.

    Raises:
        FileNotFoundError: no checkpoint there. ValueError / ConfigError: not a checkpoint, a
        policy that does not fit it, bad settings (named), or a file for the rollouts that cannot be written
        (checked before the rollouts run).
    """
    path = Path(path)
    state = load_checkpoint(path)
    config = with_defaults(migrate_config(state["config"]))
    # Evaluating a saved policy needs neither its post-training source nor held-out data.
    config["init"] = {"from": None}
    config["diagnostics"]["heldout_demos"] = 0
    section = config["eval"]
    for key, value in (("rollouts", rollouts), ("seed", seed), ("horizon", horizon), ("workers", workers)):
        if value is not None:
            section[key] = value
    if tasks:
        section["tasks"] = list(tasks)
    job = validate(config)
    spec = job.evaluation
    if spec is None:
        raise ConfigError(f"{path}: the run's eval.rollouts is 0; give --rollouts (at least 1) to evaluate it")
    actor = policy_from_checkpoint(state, path)
    target = Path(out) if out else (path if path.is_dir() else path.parent) / f"eval-{spec.seed}.csv"
    try:  # before the rollouts, which a folder that cannot take their file would lose
        check_writable(target.parent)
        if target.is_dir():
            raise IsADirectoryError(f"{target} is a folder")
    except OSError as err:
        raise ConfigError(f"cannot write the rollouts to {target} ({err}); choose a writable file with --out") from None
    with make_evaluation_pool(job.suite) as pool:
        rollouts_df = make_evaluator(spec, job.suite, job.eval_tasks, pool, progress=progress)(actor)
    write_csv_atomic(rollouts_df.assign(step=state["step"]), target)
    print(f"{path} (step {state['step']}), {spec.rollouts} rollouts per task, seed {spec.seed}; rollouts in {target}")
    print_table(summarize(rollouts_df))
    return rollouts_df
