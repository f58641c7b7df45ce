"""Phases of a MetaWorld demonstration from its gripper action (action[3], > 0 = closing).

The first step where the gripper turns closing (:func:`first_gripper_close`) anchors the phases
(:data:`PHASES`, :func:`phase_labels`): approach, contact onset around the closing step, transport,
completion. The fit diagnostics and the paper's critical-window analysis group per-step values by them.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

__all__ = ["PHASES", "first_gripper_close", "phase_labels"]


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
