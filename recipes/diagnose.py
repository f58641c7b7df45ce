"""Fit diagnostics of a training run (``summary.json``'s ``fit`` entry), from the trained policy.

Held-out demonstrations are collected like the training ones, by the job's suite, from
``diagnostics.heldout_seed`` (disjoint from the training and evaluation seeds, checked by
:func:`check_heldout_seeds`); a job on a given dataset (``data.path``) or with a suite that collects
nothing has none, and the held-out entries are then ``None``. The numbers are computed by :mod:`tar_rl.diagnostics`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import pandas as pd

from tar_rl import diagnostics
from tar_rl.collectors.suites import SUITES, Suite
from tar_rl.data import DemoDataset
from tar_rl.objectives import TARLoss
from tar_rl.runs import WEIGHTS_COLUMNS

from .config import TrainConfig

__all__ = ["check_heldout_seeds", "fit_summary", "heldout_dataset", "step_table"]


def _heldout_suite(cfg: TrainConfig) -> Suite | None:
    """The suite that collects the held-out demonstrations: the job's, when it collects its own data."""
    if cfg.diagnostics.heldout_demos < 1 or cfg.data.path:
        return None
    suite = SUITES.get(cfg.data.suite)
    return suite if suite.collects else None


def check_heldout_seeds(cfg: TrainConfig) -> None:
    """Refuse held-out demonstrations whose seeds may meet the training demonstrations' or the evaluation's.

    Raises:
        ValueError: naming the shared seeds.
    """
    suite = _heldout_suite(cfg)
    if suite is None:
        return
    diag, data, ev = cfg.diagnostics, cfg.data, cfg.eval
    heldout = suite.demo_seeds(diag.heldout_seed, diag.heldout_demos)
    train = suite.demo_seeds(data.seed, data.n_demos)
    evaluation = suite.eval_seeds(ev.seed, ev.rollouts)
    for other, what in ((train, "data.seed"), (evaluation, "eval.seed")):
        shared = sorted(heldout & other)
        if shared:
            raise ValueError(
                f"diagnostics.heldout_seed={diag.heldout_seed} shares the seeds {shared[:5]} with {what}; "
                "choose a held-out seed that neither training nor evaluation uses"
            )


def heldout_dataset(cfg: TrainConfig, tasks: Sequence[str], progress: bool) -> DemoDataset | None:
    """The held-out demonstrations of the training tasks (collected once, cached), or ``None``."""
    suite = _heldout_suite(cfg)
    if suite is None:
        return None
    diag = cfg.diagnostics
    return suite.build_dataset(cfg.data, tasks, diag.heldout_demos, diag.heldout_seed, progress)


def step_table(rows: list[tuple], value: str) -> pd.DataFrame:
    """:data:`tar_rl.diagnostics.STEP_COLUMNS` from ``record_weights`` rows (``value``: ``loss`` or ``weight``)."""
    df = pd.DataFrame([row[: len(WEIGHTS_COLUMNS)] for row in rows], columns=list(WEIGHTS_COLUMNS))
    df["episode"] = df["task"].astype(str) + "/" + df["episode"].astype(str)
    df["length"] = df.groupby("episode")["t"].transform("max") + 1
    return df.assign(value=df[value])[list(diagnostics.STEP_COLUMNS)]


def fit_summary(
    cfg: TrainConfig,
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
        cfg: the run's typed config.
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
        data) and ``alignment`` (:func:`tar_rl.diagnostics.alignment`; ``None`` without held-out data). A mean
        that is not finite (a policy whose losses are not) is ``None``.
    """
    data, diag, steps = cfg.data, cfg.diagnostics, cfg.optim.steps
    rows = record(objective, episodes_of(dataset, tasks, diag.train_episodes))
    train, train_loss = step_table(rows, "weight"), step_table(rows, "loss")
    out = {
        "passes": diagnostics.passes(steps, data.batch_segments, data.slice_len, int(dataset.data.shape[0])),
        "demo_steps": int(dataset.data.shape[0]),
        "final_uniform_loss": diagnostics.tail_mean(metrics, "uniform_loss", steps),
        "train_loss": float(train_loss["value"].mean()),
        "heldout": None,
        "alignment": None,
    }
    if heldout is not None:
        losses = step_table(record(objective, episodes_of(heldout, tasks, diag.heldout_demos)), "loss")
        out["heldout"] = {
            "seed": diag.heldout_seed,
            "episodes": int(losses["episode"].nunique()),
            "loss": float(losses["value"].mean()),
            "loss_by_phase": diagnostics.phase_means(losses),
        }
        out["alignment"] = {"bins": diag.bins, **diagnostics.alignment(train, losses, diag.bins)}
    return _finite(out)


def _finite(value):
    """``value`` with every non-finite float replaced by ``None`` (a policy with non-finite losses has no mean
    loss), so that ``summary.json`` stays strict JSON."""
    if isinstance(value, dict):
        return {key: _finite(item) for key, item in value.items()}
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value
