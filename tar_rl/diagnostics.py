"""Fit diagnostics: which regime a training run is in (pure functions over logged numbers and tables).

A run memorising a few demonstrations (hundreds of passes over the data, per-step losses near
zero) and a run making a few passes over rich data differ in what TAR's weights mean. These
numbers tell them apart:

* :func:`passes`: per-step losses computed / demonstration steps stored;
* :func:`tail_mean`: the final uniform training loss, averaged over the last 5% of the steps;
* the held-out per-step loss, overall and per phase (:func:`phase_means`), on demonstrations never
  trained on;
* :func:`alignment`: over bins of normalised episode time, the rank correlation between TAR's mean
  weight on the training demonstrations and the mean held-out per-step loss. Positive: TAR
  emphasises the moments where the policy generalises worst; 0: unrelated; negative: the opposite;
* :func:`within_segment_correlation` and :func:`top_step_agreement`: how alike two draws of a stochastic
  per-step loss (a flow head's sampled time and noise, ACT's sampled latent) order the steps of the same
  segments, which is all TAR's within-segment z-score reads.

Tables of per-step values (:data:`STEP_COLUMNS`) hold one row per step of a whole demonstration:
``episode`` (an id), ``t`` (its step index), ``length`` (the episode's length ``T``), ``value`` and
``gripper`` (the gripper action, for the phase labels of :func:`tar_rl.report.phase_labels`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import pandas as pd

from tar_rl.report.phases import PHASES, phase_column

__all__ = [
    "STEP_COLUMNS",
    "alignment",
    "binned_means",
    "passes",
    "phase_means",
    "rank_correlation",
    "tail_mean",
    "time_bins",
    "top_step_agreement",
    "within_segment_correlation",
]

STEP_COLUMNS = ("episode", "t", "length", "value", "gripper")


def passes(steps: int, batch_segments: int, slice_len: int, demo_steps: int) -> float:
    """Per-step losses a run computes (``steps x batch_segments x slice_len``) per stored demonstration step."""
    if demo_steps < 1:
        raise ValueError(f"the dataset must hold at least one step, got {demo_steps}")
    return steps * batch_segments * slice_len / demo_steps


def tail_mean(rows: Sequence[tuple], name: str, steps: int, fraction: float = 0.05) -> float | None:
    """Mean of the logged training metric ``name`` over the rows of the last ``fraction`` of ``steps``.

    ``rows`` are ``metrics.csv`` rows ``(step, phase, name, value)``; a row logged at step ``s``
    counts when ``s > steps - ceil(fraction * steps)`` (each row is the mean of its logging window).
    ``None`` when no such row exists.
    """
    if not 0 < fraction <= 1:
        raise ValueError(f"fraction must lie in (0, 1], got {fraction}")
    first = steps - math.ceil(fraction * steps)
    values = [float(r[3]) for r in rows if r[1] == "train" and r[2] == name and int(r[0]) > first]
    return float(np.mean(values)) if values else None


def time_bins(t: np.ndarray, length: np.ndarray, bins: int) -> np.ndarray:
    """The bin ``floor(bins * t / length)`` of normalised episode time of each step (``0 .. bins - 1``)."""
    t, length = np.asarray(t, dtype=np.int64), np.asarray(length, dtype=np.int64)
    if bins < 1:
        raise ValueError(f"bins must be >= 1, got {bins}")
    if np.any(length < 1) or np.any(t < 0) or np.any(t >= length):
        raise ValueError("every step needs 0 <= t < length")
    return (bins * t) // length


def binned_means(steps: pd.DataFrame, bins: int) -> np.ndarray:
    """``[bins]`` mean ``value`` per bin of normalised episode time, pooled over episodes (``nan`` where empty)."""
    which = time_bins(steps["t"].to_numpy(), steps["length"].to_numpy(), bins)
    values = steps["value"].to_numpy(dtype=np.float64)
    sums = np.bincount(which, weights=values, minlength=bins)
    counts = np.bincount(which, minlength=bins)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(counts > 0, sums / np.maximum(counts, 1), np.nan)


def rank_correlation(x: Sequence[float], y: Sequence[float]) -> float:
    """Spearman's rank correlation of paired values (average ranks for ties; pairs with a ``nan`` left out).

    ``nan`` with fewer than 3 pairs or when either side is constant.
    """
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    if x.shape != y.shape:
        raise ValueError(f"x and y must pair up, got shapes {x.shape} and {y.shape}")
    keep = np.isfinite(x) & np.isfinite(y)
    if keep.sum() < 3:
        return math.nan
    rx = pd.Series(x[keep]).rank(method="average").to_numpy()
    ry = pd.Series(y[keep]).rank(method="average").to_numpy()
    rx, ry = rx - rx.mean(), ry - ry.mean()
    denom = math.sqrt(float((rx**2).sum() * (ry**2).sum()))
    return float((rx * ry).sum() / denom) if denom > 0 else math.nan


def phase_means(steps: pd.DataFrame) -> dict[str, float | None]:
    """Mean ``value`` per phase (:data:`tar_rl.report.PHASES`, labelled per episode from its gripper action);
    ``None`` for a phase no step falls in."""
    labels = phase_column(steps, ["episode"])
    values = steps["value"].to_numpy(dtype=np.float64)
    return {p: (float(values[labels == p].mean()) if np.any(labels == p) else None) for p in PHASES}


def alignment(train_weights: pd.DataFrame, heldout_losses: pd.DataFrame, bins: int = 10) -> dict:
    """How TAR's weights on training demonstrations line up with the held-out loss over episode time.

    Args:
        train_weights: per-step TAR weights along training demonstrations (:data:`STEP_COLUMNS`).
        heldout_losses: per-step losses along held-out demonstrations (:data:`STEP_COLUMNS`).
        bins: bins of normalised episode time.

    Returns:
        ``spearman`` (:func:`rank_correlation` of the two per-bin means), ``weight_by_bin`` and
        ``heldout_loss_by_bin`` (lists of ``bins`` values, ``None`` for an empty bin).
    """
    w, loss = binned_means(train_weights, bins), binned_means(heldout_losses, bins)

    def plain(a: np.ndarray) -> list:
        return [float(v) if np.isfinite(v) else None for v in a]

    r = rank_correlation(w, loss)
    return {
        "spearman": r if math.isfinite(r) else None,
        "weight_by_bin": plain(w),
        "heldout_loss_by_bin": plain(loss),
    }


def _segment_pairs(a, b, valid) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``a``, ``b`` as float arrays ``[N, L]`` and ``valid`` as bool, checked; rows with fewer than two valid steps
    are left out (their steps have no within-segment order)."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    valid = np.asarray(valid)
    if valid.dtype != np.bool_:
        raise TypeError(f"valid must be a bool mask (True = real step), got dtype {valid.dtype}")
    if not (a.shape == b.shape == valid.shape) or a.ndim != 2:
        raise ValueError(f"a, b and valid must share one [N, L] shape, got {a.shape}, {b.shape}, {valid.shape}")
    if not (np.isfinite(a[valid]).all() and np.isfinite(b[valid]).all()):
        raise ValueError("a and b must be finite at every valid step")
    keep = valid.sum(axis=1) >= 2
    return a[keep], b[keep], valid[keep]


def within_segment_correlation(a, b, valid) -> float:
    """Pearson correlation of two draws ``a`` and ``b`` of per-step values over the same segments, each draw's
    segment mean removed first: how much of the within-segment variation the draws share.

    Args:
        a, b: ``[N, L]`` values (e.g. per-step losses of one policy on the same ``N`` segments under two random
            draws); only valid steps are read.
        valid: ``[N, L]`` bool, ``True`` on real steps. A segment with fewer than two valid steps is left out.

    Returns:
        ``1`` when the draws differ by at most a per-segment offset and a common positive scale; about
        ``var(s) / (var(s) + var(e))`` when each draw is a shared within-segment signal ``s`` plus independent
        noise ``e``; ``nan`` when either side has no within-segment variation.
    """
    a, b, valid = _segment_pairs(a, b, valid)
    n = valid.sum(axis=1, keepdims=True)  # at least 2 on every kept segment

    def centred(x: np.ndarray) -> np.ndarray:
        return np.where(valid, x - np.where(valid, x, 0.0).sum(axis=1, keepdims=True) / n, 0.0)

    da, db = centred(a), centred(b)
    denom = math.sqrt(float((da**2).sum() * (db**2).sum()))
    return float((da * db).sum() / denom) if denom > 0 else math.nan


def top_step_agreement(a, b, valid) -> float:
    """Fraction of segments whose largest valid value falls on the same step in both draws (``[N, L]`` values,
    ``valid`` as :func:`within_segment_correlation`; ties go to the first step). Chance level is about
    ``1 / L`` for unrelated draws of segments of ``L`` valid steps; ``nan`` without a segment of two valid
    steps."""
    a, b, valid = _segment_pairs(a, b, valid)
    if not len(a):
        return math.nan
    top_a = np.where(valid, a, -np.inf).argmax(axis=1)
    top_b = np.where(valid, b, -np.inf).argmax(axis=1)
    return float((top_a == top_b).mean())
