"""Per-step loss and TAR weight along whole demonstrations (``weights.csv``, the paper's Fig. 5)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import fields

import numpy as np
import torch
from tensordict import TensorDict

from tar_rl.data import DemoDataset
from tar_rl.objectives import TARLoss, TARParams, window_weights

__all__ = ["demo_episodes", "record_weights"]


def record_weights(
    objective: TARLoss, episodes: list[tuple[str, int, TensorDict]], slice_len: int, step: int
) -> list[tuple]:
    """Per-step loss and TAR weight along whole demonstrations (rows of ``weights.csv``, the paper's Fig. 5).

    A row is ``(step, task, episode, t, loss, weight, gripper, loss_dim0, ..., loss_dim{A-1})``
    (:func:`tar_rl.runs.weights_columns`). The loss is the head's per-step loss at the current
    weights; the weight is :func:`tar_rl.objectives.window_weights` of what TAR ranks (those losses, or
    the head's ranking signal with ``objective.signal``) with the objective's gamma, w_max, eps and cap at
    full strength, whatever the run's own weighting and schedule; the gripper is the last action dim of the
    demonstration's action; ``loss_dim<i>`` is action dim ``i``'s loss at that step
    (:meth:`tar_rl.TARLoss.inspect_steps`, from the same pass of the head), absent for a head with one loss per
    step. A demonstration with a non-finite loss or signal (a run whose steps were all skipped by
    ``optim.skip_nonfinite``) has no TAR weights: its weights are NaN.
    """
    rows = []
    was_training = objective.training
    objective.eval()
    tar = TARParams(
        **{f.name: getattr(objective.params, f.name) for f in fields(TARParams) if hasattr(objective.params, f.name)}
    )
    try:
        with torch.no_grad():
            for task, episode, td in episodes:
                losses, dims, ranked = objective.inspect_steps(td.unsqueeze(0))
                losses, ranked = losses.squeeze(0).float().cpu(), ranked.squeeze(0).float().cpu()
                if bool(torch.isfinite(losses).all() and torch.isfinite(ranked).all()):
                    weight = window_weights(ranked, slice_len, **tar.tar_kwargs())
                else:
                    weight = torch.full_like(losses, float("nan"))
                gripper = td["action"][..., -1].float().cpu()
                per_dim = [()] * losses.shape[0] if dims is None else dims.squeeze(0).float().cpu().tolist()
                rows += [
                    (step, task, episode, t, float(losses[t]), float(weight[t]), float(gripper[t]), *per_dim[t])
                    for t in range(losses.shape[0])
                ]
    finally:
        objective.train(was_training)
    return rows


def demo_episodes(
    dataset: DemoDataset, tasks: Sequence[str], per_task: int, keys, device
) -> list[tuple[str, int, TensorDict]]:
    data = dataset.data
    episode = data["episode"].numpy()
    task_id = data["task_id"].numpy()
    out = []
    for task in tasks:
        ids = np.unique(episode[task_id == dataset.metadata["task_ids"][task]])[:per_task]
        for e in ids:
            idx = np.flatnonzero(episode == e)
            td = data[int(idx[0]) : int(idx[-1]) + 1]
            td = td.select(*keys) if keys is not None else td
            out.append((task, int(e), td.clone().to(device)))
    return out
