"""Phases of a MetaWorld demonstration from its gripper action (action[3], > 0 = closing), and its gripper switches.

The first step where the gripper turns closing (:func:`first_gripper_close`) anchors the phases
(:data:`PHASES`, :func:`phase_labels`): approach, contact onset around the closing step, transport,
completion. A gripper switch is a step where the action turns closing or stops closing (:func:`switch_steps`).
:func:`phase_column` and :func:`label_steps` label the steps of many demonstrations in one table; the fit
diagnostics, the paper's critical-window analysis and the R3 diagnosis group per-step values by them.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import pandas as pd

__all__ = ["PHASES", "first_gripper_close", "label_steps", "near", "phase_column", "phase_labels", "switch_steps"]


#: Phases of a demonstration, in time order (see :func:`phase_labels`).
PHASES: tuple[str, ...] = ("approach", "contact_onset", "transport", "completion")


def first_gripper_close(gripper: Sequence[float]) -> int | None:
    """Index of the first step where the gripper action turns closing (> 0) after a non-closing step.

    A demonstration whose gripper is closing from its first step has no such step (``None``), as has
    one that never closes.
    """
    g = np.asarray(gripper, dtype=float)
    hits = np.flatnonzero((g[1:] > 0) & (g[:-1] <= 0))
    return int(hits[0]) + 1 if hits.size else None


def phase_labels(gripper: Sequence[float], onset: float = 0.1, completion: float = 0.15) -> np.ndarray:
    """Phase of every step of one demonstration, from its gripper action (action[3], > 0 = closing).

    The anchor is the gripper-closing step ``c`` (:func:`first_gripper_close`). With ``T`` steps,
    ``w = max(1, ceil(onset * T))`` and ``k = max(1, ceil(completion * T))``:

    * ``approach``: ``[0, c - w)``;
    * ``contact_onset``: ``[max(0, c - w), min(T, c + w))``, the window around the closing step;
    * ``transport``: ``[c + w, max(c + w, T - k))``;
    * ``completion``: the last ``k`` steps that are not in the onset window.

    Without a closing step (a task that never grasps, or a gripper closed from the start) there is
    no anchor: the last ``k`` steps are ``completion`` and every other step ``approach``.

    Args:
        gripper: the gripper action along the demonstration, shape ``[T]``.
        onset: half-width of the contact-onset window, as a fraction of ``T``.
        completion: length of the completion window, as a fraction of ``T``.

    Returns:
        ``[T]`` array of phase names (:data:`PHASES`).

    Raises:
        ValueError: an empty signal, or fractions outside [0, 1].
    """
    for name, value in (("onset", onset), ("completion", completion)):
        if not 0 <= value <= 1:
            raise ValueError(f"{name} must be a fraction in [0, 1], got {value}")
    g = np.asarray(gripper, dtype=float)
    T = len(g)
    if T == 0:
        raise ValueError("the gripper signal is empty")
    w, k = max(1, math.ceil(onset * T)), max(1, math.ceil(completion * T))
    labels = np.full(T, "approach", dtype=object)
    c = first_gripper_close(g)
    if c is None:
        labels[max(0, T - k) :] = "completion"
        return labels
    a, b = max(0, c - w), min(T, c + w)
    labels[a:b] = "contact_onset"
    labels[b:] = "transport"
    labels[max(b, T - k) :] = "completion"
    return labels


def switch_steps(gripper: Sequence[float]) -> np.ndarray:
    """Gripper-switch steps of one demonstration: the gripper action changes sign from the previous step.

    The sign is taken as closing (``> 0``) or not (``<= 0``, zero counting as open, as in
    :func:`first_gripper_close`): a step is a switch step when it is closing and the previous step is not, or the
    reverse. The first step is never a switch step.
    """
    closing = np.asarray(gripper, dtype=float) > 0
    out = np.zeros(len(closing), dtype=bool)
    out[1:] = closing[1:] != closing[:-1]
    return out


def near(flags: np.ndarray, window: int) -> np.ndarray:
    """Steps within ``window`` steps (either side) of a flagged step, the flagged steps included."""
    out = flags.copy()
    for k in range(1, window + 1):
        out[k:] |= flags[:-k]
        out[:-k] |= flags[k:]
    return out


def phase_column(steps: pd.DataFrame, by: Sequence[str]) -> np.ndarray:
    """The phase of every row of ``steps`` (a table of per-step rows with ``t`` and ``gripper``), each
    demonstration (the rows of one value of ``by``) labelled in time order; aligned with the rows as given."""
    labels = np.empty(len(steps), dtype=object)
    t, gripper = steps["t"].to_numpy(), steps["gripper"].to_numpy()
    for idx in steps.groupby(list(by), sort=False).indices.values():
        order = idx[np.argsort(t[idx], kind="stable")]
        labels[order] = phase_labels(gripper[order])
    return labels


def label_steps(steps: pd.DataFrame, by: Sequence[str], window: int) -> pd.DataFrame:
    """``steps`` sorted by (``by``, ``t``) with each step's ``phase`` (:func:`phase_labels`), ``switch``
    (:func:`switch_steps`) and ``near_switch`` (within ``window`` steps of a switch, :func:`near`), each
    demonstration (the rows of one value of ``by``) on its own."""
    df = steps.sort_values([*by, "t"], kind="stable").reset_index(drop=True)
    switch = np.zeros(len(df), dtype=bool)
    nearby = np.zeros(len(df), dtype=bool)
    gripper = df["gripper"].to_numpy()
    for idx in df.groupby(list(by), sort=False).indices.values():
        switch[idx] = switch_steps(gripper[idx])
        nearby[idx] = near(switch[idx], window)
    return df.assign(phase=phase_column(df, by), switch=switch, near_switch=nearby)
