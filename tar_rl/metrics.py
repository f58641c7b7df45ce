"""Evaluation metrics of the TAR paper (Sec. III-A): success rate, Fast20 and NEPS.

Notation. For one task, ``N`` rollouts are run. Rollout ``i`` executes ``s_i`` environment steps
until its first success or until truncation at the horizon ``H`` (MetaWorld: ``H = 500``), and
its normalised step fraction is ``rho_i = s_i / H``, which lies in ``(0, 1]``. ``success_i`` is
1 when the rollout succeeded and 0 otherwise; ``S = sum_i success_i``.

Per task:

* success rate: ``r = S / N``.
* Fast20: mean of the ``K = ceil(0.2 * N)`` smallest ``rho`` values, successful or not
  (``N = 50`` gives ``K = 10``): ``Fast20 = (1 / K) * sum_{j=1..K} rho_(j)`` with
  ``rho_(1) <= rho_(2) <= ...`` the sorted values. ``K`` is computed in integers,
  ``K = (N + 4) // 5 = ceil(N / 5)``, with no floating-point rounding involved.
* NEPS (normalised expected steps per success): ``NEPS = E[rho] / r = sum_i rho_i / S``;
  ``math.inf`` when ``S = 0``.

Aggregation in :func:`summarize` (one table row per task, per group and overall):

* group and overall success rate and Fast20: the UNWEIGHTED mean of the per-task values over the
  tasks in the group (every task counts once, whatever its number of rollouts), as in the paper's
  group and overall columns.
* group and overall NEPS: POOLED over all rollouts of the group,
  ``NEPS_group = sum_{i in group} rho_i / sum_{i in group} success_i = mean(rho) / success fraction``.
  It is ``math.inf`` only when no rollout of the whole group succeeded, so a single task without
  success does not make its group's NEPS infinite (the mean of per-task NEPS would be).

Units. All functions return fractions. The paper reports success rate in percent and Fast20 and
NEPS as ``100 x Fast20`` and ``100 x NEPS``; :func:`as_percent` converts a :func:`summarize` table
to those units (``inf`` stays ``inf``).

Inputs are the values of ONE task as 1-D numpy arrays, lists or torch tensors. Bad input raises
``ValueError``: empty input, NaN, ``rho`` outside ``(0, 1]``, success values other than 0/1 or
True/False, ``rho`` and ``success`` of different lengths, missing DataFrame columns.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import pandas as pd

__all__ = [
    "DEFAULT_GROUP_ORDER",
    "METRIC_COLUMNS",
    "REQUIRED_COLUMNS",
    "SUMMARY_COLUMNS",
    "as_percent",
    "fast20",
    "fast20_k",
    "neps",
    "success_rate",
    "summarize",
]

#: Columns :func:`summarize` needs in its input (one row per rollout).
REQUIRED_COLUMNS: tuple[str, ...] = ("task", "group", "success", "rho")
#: Columns of the table :func:`summarize` returns, in order.
SUMMARY_COLUMNS: tuple[str, ...] = ("level", "name", "n_tasks", "n_rollouts", "success", "fast20", "neps")
#: The metric columns (fractions; :func:`as_percent` multiplies them by 100).
METRIC_COLUMNS: tuple[str, ...] = ("success", "fast20", "neps")
#: Group rows come in this order when present (the paper's MetaWorld columns); other groups follow
#: in their order of first appearance in the input.
DEFAULT_GROUP_ORDER: tuple[str, ...] = ("easy", "medium", "hard", "very_hard")


def _to_1d(values, name: str) -> np.ndarray:
    """``values`` (list, numpy array or torch tensor) as a non-empty 1-D numpy array."""
    if hasattr(values, "detach"):  # torch.Tensor, without importing torch
        values = values.detach().cpu().numpy()
    arr = np.asarray(values)
    if arr.ndim != 1:
        raise ValueError(f"{name} must be 1-D (one value per rollout of one task), got shape {arr.shape}")
    if arr.size == 0:
        raise ValueError(f"{name} is empty: at least one rollout is needed")
    if arr.dtype == object or not (np.issubdtype(arr.dtype, np.number) or arr.dtype == np.bool_):
        raise ValueError(f"{name} must be numeric or boolean, got dtype {arr.dtype}")
    return arr


def _check_rho(rho) -> np.ndarray:
    arr = _to_1d(rho, "rho").astype(np.float64)
    if np.isnan(arr).any():
        raise ValueError(f"rho contains NaN at positions {np.flatnonzero(np.isnan(arr)).tolist()}")
    bad = (arr <= 0.0) | (arr > 1.0)
    if bad.any():
        raise ValueError(
            f"rho must lie in (0, 1] (rho = executed steps / horizon); got {arr[bad][:5].tolist()} "
            f"at positions {np.flatnonzero(bad)[:5].tolist()}"
        )
    return arr


def _check_success(success) -> np.ndarray:
    arr = _to_1d(success, "success")
    if arr.dtype == np.bool_:
        return arr
    arr = arr.astype(np.float64)
    if np.isnan(arr).any():
        raise ValueError(f"success contains NaN at positions {np.flatnonzero(np.isnan(arr)).tolist()}")
    bad = (arr != 0.0) & (arr != 1.0)
    if bad.any():
        raise ValueError(f"success must be True/False or 0/1; got {arr[bad][:5].tolist()}")
    return arr == 1.0


def _check_same_length(rho: np.ndarray, success: np.ndarray) -> None:
    if rho.shape != success.shape:
        raise ValueError(f"rho and success must have one value per rollout each; got {rho.size} and {success.size}")


def success_rate(success) -> float:
    """Fraction of rollouts that succeeded: ``r = S / N``.

    Args:
        success: one entry per rollout of one task, bool or 0/1.

    Returns:
        ``S / N`` in ``[0, 1]``.

    Raises:
        ValueError: empty, not 1-D, NaN or a value other than 0/1.
    """
    ok = _check_success(success)
    return float(ok.sum() / ok.size)


def fast20_k(n: int) -> int:
    """Number of rollouts Fast20 averages: ``K = ceil(0.2 * N) = (N + 4) // 5`` (exact integers)."""
    if n < 1:
        raise ValueError(f"Fast20 needs at least one rollout, got N = {n}")
    return (n + 4) // 5


def fast20(rho) -> float:
    """Mean normalised step fraction of the fastest 20 % of rollouts, successful or not.

    ``Fast20 = (1 / K) * sum_{j=1..K} rho_(j)`` with ``K = ceil(0.2 * N)`` and ``rho_(j)`` the
    ``j``-th smallest value (``N = 50`` gives ``K = 10``). Lower is better.

    Args:
        rho: ``s / H`` per rollout of one task, each in ``(0, 1]``.

    Returns:
        Fast20 as a fraction in ``(0, 1]`` (the paper reports ``100 x Fast20``).

    Raises:
        ValueError: empty, not 1-D, NaN or a value outside ``(0, 1]``.
    """
    arr = _check_rho(rho)
    k = fast20_k(arr.size)
    return float(np.sort(arr)[:k].mean())


def neps(rho, success) -> float:
    """Normalised expected steps per success: ``NEPS = E[rho] / r = sum_i rho_i / S``.

    Failures count with their full step cost (typically ``rho = 1``). Lower is better.

    Args:
        rho: ``s / H`` per rollout of one task, each in ``(0, 1]``.
        success: one entry per rollout, bool or 0/1, aligned with ``rho``.

    Returns:
        NEPS as a fraction (the paper reports ``100 x NEPS``); ``math.inf`` when ``S = 0``.

    Raises:
        ValueError: bad ``rho`` or ``success`` (see :func:`fast20`, :func:`success_rate`) or
            different lengths.
    """
    r = _check_rho(rho)
    ok = _check_success(success)
    _check_same_length(r, ok)
    s = int(ok.sum())
    if s == 0:
        return math.inf
    return float(r.sum() / s)


def summarize(rollouts: pd.DataFrame, groups: Sequence[str] | None = None) -> pd.DataFrame:
    """Tidy table of success rate, Fast20 and NEPS per task, per group and overall.

    Per task: :func:`success_rate`, :func:`fast20`, :func:`neps`. Per group and overall
    (``T`` tasks, rollouts ``i`` pooled over them):

    * ``success = (1 / T) * sum_t r_t`` and ``fast20 = (1 / T) * sum_t Fast20_t`` (unweighted
      means over tasks);
    * ``neps = sum_i rho_i / sum_i success_i`` (pooled; ``inf`` only if no rollout succeeded).

    Args:
        rollouts: one row per rollout, with at least the columns ``task``, ``group``, ``success``
            (bool or 0/1) and ``rho`` (in ``(0, 1]``). Each task must belong to one group.
        groups: order of the group rows. Groups in ``groups`` that are absent from the data are
            skipped; groups present but not listed follow in order of first appearance. Default:
            :data:`DEFAULT_GROUP_ORDER` (``easy, medium, hard, very_hard``).

    Returns:
        DataFrame with columns :data:`SUMMARY_COLUMNS`: ``level`` (``"task"``, ``"group"`` or
        ``"overall"``), ``name`` (task name, group name or ``"overall"``), ``n_tasks``,
        ``n_rollouts``, ``success``, ``fast20``, ``neps``, as fractions (see :func:`as_percent`).
        Task rows come first sorted by name, then group rows, then the ``overall`` row.

    Raises:
        ValueError: not a DataFrame, no rows, missing columns (named), a missing task or group
            name, a task listed under two groups, or bad values (see :func:`neps`).
    """
    if not isinstance(rollouts, pd.DataFrame):
        raise ValueError(f"rollouts must be a pandas DataFrame, got {type(rollouts).__name__}")
    missing = [c for c in REQUIRED_COLUMNS if c not in rollouts.columns]
    if missing:
        raise ValueError(f"rollouts is missing the column(s) {missing}; required: {list(REQUIRED_COLUMNS)}")
    if len(rollouts) == 0:
        raise ValueError("rollouts is empty: at least one rollout is needed")
    for col in ("task", "group"):
        if rollouts[col].isna().any():
            raise ValueError(f"column {col!r} has missing values")

    group_per_task = rollouts.groupby("task", sort=True)["group"].unique()
    ambiguous = {t: list(g) for t, g in group_per_task.items() if len(g) != 1}
    if ambiguous:
        raise ValueError(f"each task must belong to exactly one group; got {ambiguous}")

    rows = []
    task_metrics: dict[str, tuple[float, float]] = {}
    for task, frame in rollouts.groupby("task", sort=True):
        try:
            sr = success_rate(frame["success"].to_numpy())
            f20 = fast20(frame["rho"].to_numpy())
            ne = neps(frame["rho"].to_numpy(), frame["success"].to_numpy())
        except ValueError as err:
            raise ValueError(f"task {task!r}: {err}") from None
        task_metrics[task] = (sr, f20)
        rows.append(("task", task, 1, len(frame), sr, f20, ne))

    def aggregate(level: str, name: str, frame: pd.DataFrame) -> tuple:
        tasks = sorted(frame["task"].unique())
        sr = float(np.mean([task_metrics[t][0] for t in tasks]))
        f20 = float(np.mean([task_metrics[t][1] for t in tasks]))
        pooled = neps(frame["rho"].to_numpy(), frame["success"].to_numpy())
        return (level, name, len(tasks), len(frame), sr, f20, pooled)

    if isinstance(groups, str):
        groups = [groups]
    order = list(DEFAULT_GROUP_ORDER if groups is None else groups)
    present = list(dict.fromkeys(rollouts["group"]))
    ordered = [g for g in order if g in present] + [g for g in present if g not in order]
    for group in ordered:
        rows.append(aggregate("group", group, rollouts[rollouts["group"] == group]))
    rows.append(aggregate("overall", "overall", rollouts))

    table = pd.DataFrame(rows, columns=list(SUMMARY_COLUMNS))
    return table.astype({"n_tasks": "int64", "n_rollouts": "int64", **dict.fromkeys(METRIC_COLUMNS, "float64")})


def as_percent(table: pd.DataFrame) -> pd.DataFrame:
    """A copy of a :func:`summarize` table in the paper's units: ``100 x`` success, Fast20, NEPS.

    ``inf`` NEPS stays ``inf``; other columns are unchanged.

    Raises:
        ValueError: ``table`` lacks one of the columns ``success``, ``fast20``, ``neps``.
    """
    missing = [c for c in METRIC_COLUMNS if c not in table.columns]
    if missing:
        raise ValueError(f"table is missing the column(s) {missing}; expected a summarize() table")
    out = table.copy()
    for col in METRIC_COLUMNS:
        out[col] = out[col].astype(np.float64) * 100.0
    return out
