"""Post-training: a run that starts from a trained policy's weights (``init.from=<run dir or checkpoint>``).

The source is a finished run of the same head with the same sizes. What the new run takes from it:
every entry of the policy's state dict (the network and its normalisation statistics), except the
task-conditioning rows of tasks the source never trained (:meth:`TaskEncoder.task_rows`): those keep
the new run's fresh initialisation, as a pretrained policy's unused rows carry nothing learned.
What starts fresh: the optimiser, the learning-rate schedule, the objective's schedule and the
sampler. The source's run name (which holds its identity hash) becomes ``init.source``, part of the
new run's identity; its path is not, so moving the source folder keeps the new run's name.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch

from tar_rl.policies import DataInfo, Policy
from tar_rl.policies.common import TaskEncoder
from tar_rl.runs import CHECKPOINT, load_checkpoint

from .rundir import migrate_config, run_name

__all__ = ["InitError", "Source", "apply_init", "check_fits", "load_source"]


class InitError(ValueError):
    """``init.from`` names no usable source policy (reported before any work)."""


@dataclass(frozen=True)
class Source:
    """A trained policy to start from.

    Attributes:
        path: the checkpoint file.
        name: the source run's name (``<objective>-<policy>-s<seed>-<hash>`` of its config).
        step: the step the source finished at.
        config: the source run's config.
        info: the source's :class:`DataInfo` (dimensions, statistics, task ids' instructions).
        weights: the policy's state dict (the EMA weights when the source kept them).
        task_ids: the task ids the source was trained on.
        git_commit: the commit the source was trained at (``None`` if unknown).
    """

    path: Path
    name: str
    step: int
    config: dict
    info: DataInfo
    weights: dict[str, torch.Tensor]
    task_ids: tuple[int, ...]
    git_commit: str | None

    def provenance(self) -> dict:
        """What ``summary.json`` records of the source."""
        return {
            "from": str(self.path),
            "source": self.name,
            "source_step": self.step,
            "source_git_commit": self.git_commit,
        }


def load_source(where: str) -> Source:
    """Open and check the source of ``init.from=where`` (a run directory or its checkpoint file).

    Raises:
        InitError: no such path, no checkpoint, an unreadable or corrupt one, an unfinished run, or a
            checkpoint that does not record its training tasks; the message names ``init.from``.
    """
    path = Path(where)
    if not path.exists():
        raise InitError(f"init.from={where}: no such run directory or checkpoint")
    file = path / CHECKPOINT if path.is_dir() else path
    try:
        state = load_checkpoint(file)
    except (FileNotFoundError, ValueError) as err:
        raise InitError(f"init.from={where}: {err}") from None
    if not state.get("finished"):
        total = state.get("config", {}).get("optim", {}).get("steps", "?")
        raise InitError(
            f"init.from={where}: the source run is unfinished (step {state.get('step')} of {total}); "
            "finish it (run its command again) or choose a finished run"
        )
    try:
        weights = state["ema_policy"] if state.get("ema_policy") is not None else state["policy"]
        task_ids = tuple(int(i) for i in state["task_ids"])
        info = DataInfo.from_dict(state["data_info"])
        config = migrate_config(state["config"])
        name = run_name(config)
    except (KeyError, TypeError, ValueError) as err:
        raise InitError(
            f"init.from={where}: the checkpoint lacks {err} (the policy, its data description or the task ids it "
            "was trained on); train the source again with this version of tar-rl"
        ) from None
    return Source(file, name, int(state["step"]), config, info, weights, task_ids, state.get("git_commit"))


def check_fits(source: Source, policy_name: str, policy: Policy, info: DataInfo) -> None:
    """Refuse a source of another head, other sizes or other task ids.

    Raises:
        InitError: naming the first differing setting or parameter (with both shapes).
    """
    if source.config["policy"]["name"] != policy_name:
        raise InitError(
            f"init.from={source.path}: the source is a {source.config['policy']['name']!r} policy, this run trains "
            f"{policy_name!r}; post-training needs the same head"
        )
    if source.info.n_tasks != info.n_tasks or source.info.instructions != info.instructions:
        raise InitError(
            f"init.from={source.path}: the source's task ids ({source.info.n_tasks} ids) do not mean the same tasks "
            f"as this dataset's ({info.n_tasks} ids); post-training needs the same task numbering"
        )
    target = policy.actor.state_dict()
    for key, value in target.items():
        if key in source.weights and tuple(source.weights[key].shape) != tuple(value.shape):
            raise InitError(
                f"init.from={source.path}: parameter {key} has shape {tuple(source.weights[key].shape)} in the source "
                f"and {tuple(value.shape)} here (policy sizes differ)"
            )
    missing = sorted(set(target) - set(source.weights))
    extra = sorted(set(source.weights) - set(target))
    if missing or extra:
        what = f"parameter {missing[0]} is not in the source" if missing else f"the source has {extra[0]}, this has not"
        raise InitError(f"init.from={source.path}: the policies differ: {what} (same head, other settings?)")


def apply_init(policy: Policy, source: Source) -> None:
    """Load the source's weights into ``policy`` (freshly initialised), keeping the fresh task rows of
    tasks the source never trained. Call :func:`check_fits` first."""
    fresh = policy.actor.state_dict()
    weights = {k: v.clone() for k, v in source.weights.items()}
    for prefix, module in policy.actor.named_modules():
        if isinstance(module, TaskEncoder):
            for name, trained in module.task_rows(source.task_ids).items():
                key = f"{prefix}.{name}" if prefix else name
                rows = trained.to(weights[key].device).view(-1, *([1] * (weights[key].dim() - 1)))
                weights[key] = torch.where(rows, weights[key], fresh[key].to(weights[key].device))
    policy.actor.load_state_dict(weights)
