"""Fit diagnostics of a training run (``summary.json``'s ``fit`` entry), from the trained policy.

Held-out demonstrations are collected like the training ones, from ``diagnostics.heldout_seed``
(disjoint from the training and evaluation seeds, checked by :func:`check_heldout_seeds`), and only
for MetaWorld datasets collected by the recipe (an imported dataset or another suite has none:
the held-out entries are then ``None``). The numbers are computed by :mod:`tar_rl.diagnostics`.
"""

from __future__ import annotations

from collections.abc import Sequence

import pandas as pd

from tar_rl import diagnostics
from tar_rl.collectors import tasks as mw_tasks
from tar_rl.data import DemoDataset, build_dataset
from tar_rl.objectives import TARLoss

__all__ = ["check_heldout_seeds", "fit_summary", "heldout_dataset", "step_table"]


def _collects_heldout(config: dict) -> bool:
    return (
        config["diagnostics"]["heldout_demos"] > 0
        and not config["data"]["path"]
        and (config["data"]["suite"] == "metaworld")
    )


def check_heldout_seeds(config: dict) -> None:
    """Refuse held-out variations that may meet the training demonstrations' or the evaluation's.

    Raises:
        ValueError: naming the shared seeds.
    """
    if not _collects_heldout(config):
        return
    diag, data, ev = config["diagnostics"], config["data"], config["eval"]
    heldout = mw_tasks.variation_seeds(diag["heldout_seed"], 3 * diag["heldout_demos"] + 5)
    train = mw_tasks.variation_seeds(data["seed"], 3 * data["n_demos"] + 5)
    evaluation = mw_tasks.variation_seeds(ev["seed"], ev["rollouts"])
    for other, what in ((train, "data.seed"), (evaluation, "eval.seed")):
        shared = sorted(set(heldout) & set(other))
        if shared:
            raise ValueError(
                f"diagnostics.heldout_seed={diag['heldout_seed']} shares the seeds {shared} with {what}; "
                "choose a held-out seed that neither training nor evaluation uses"
            )


def heldout_dataset(config: dict, tasks: Sequence[str], progress: bool) -> DemoDataset | None:
    """The held-out demonstrations of the training tasks (collected once, cached), or ``None``."""
    if not _collects_heldout(config):
        return None
    data, diag = config["data"], config["diagnostics"]
    return build_dataset(
        data["root"],
        list(tasks),
        n_demos=diag["heldout_demos"],
        seed=diag["heldout_seed"],
        chunk_horizon=data["chunk_horizon"],
        history=data["history"],
        image_size=data["image_size"],
        workers=data["workers"],
        progress=progress,
        verbose=False,
    )


def step_table(rows: list[tuple], value: str) -> pd.DataFrame:
    """:data:`tar_rl.diagnostics.STEP_COLUMNS` from ``record_weights`` rows (``value``: ``loss`` or ``weight``)."""
    df = pd.DataFrame(rows, columns=["step", "task", "episode", "t", "loss", "weight", "gripper"])
    df["episode"] = df["task"].astype(str) + "/" + df["episode"].astype(str)
    df["length"] = df.groupby("episode")["t"].transform("max") + 1
    return df.assign(value=df[value])[list(diagnostics.STEP_COLUMNS)]


def fit_summary(
    config: dict,
    objective: TARLoss,
    dataset: DemoDataset,
    heldout: DemoDataset | None,
    tasks: Sequence[str],
    metrics: list[tuple],
    episodes_of,
    record,
) -> dict:
    """The ``fit`` entry of ``summary.json``.

    Args:
        config: the run's config.
        objective: the trained objective (its head's per-step loss and TAR's settings).
        dataset: the training demonstrations.
        heldout: the held-out demonstrations, or ``None``.
        tasks: the training tasks.
        metrics: the run's ``metrics.csv`` rows.
        episodes_of: ``(dataset, tasks, per_task) -> [(task, episode, TensorDict)]`` whole demonstrations.
        record: ``(objective, episodes) -> rows`` of per-step loss and TAR weight along them.

    Returns:
        ``passes``, ``demo_steps``, ``final_uniform_loss`` (mean over the last 5% of the steps),
        ``train_loss`` (mean per-step loss along the training demonstrations used below),
        ``heldout`` (``seed``, ``episodes``, ``loss``, ``loss_by_phase``; ``None`` without held-out
        data) and ``alignment`` (:func:`tar_rl.diagnostics.alignment`; ``None`` without held-out data).
    """
    data, diag, steps = config["data"], config["diagnostics"], config["optim"]["steps"]
    rows = record(objective, episodes_of(dataset, tasks, diag["train_episodes"]))
    train, train_loss = step_table(rows, "weight"), step_table(rows, "loss")
    out = {
        "passes": diagnostics.passes(steps, data["batch_segments"], data["slice_len"], int(dataset.data.shape[0])),
        "demo_steps": int(dataset.data.shape[0]),
        "final_uniform_loss": diagnostics.tail_mean(metrics, "uniform_loss", steps),
        "train_loss": float(train_loss["value"].mean()),
        "heldout": None,
        "alignment": None,
    }
    if heldout is not None:
        losses = step_table(record(objective, episodes_of(heldout, tasks, diag["heldout_demos"])), "loss")
        out["heldout"] = {
            "seed": diag["heldout_seed"],
            "episodes": int(losses["episode"].nunique()),
            "loss": float(losses["value"].mean()),
            "loss_by_phase": diagnostics.phase_means(losses),
        }
        out["alignment"] = {"bins": diag["bins"], **diagnostics.alignment(train, losses, diag["bins"])}
    return out
