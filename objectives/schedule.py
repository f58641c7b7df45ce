"""The schedule that turns TAR on during training (paper Sec. III-B).

TAR is off for the first ``start`` optimisation steps, then mixed in over ``ramp`` steps with a
coefficient alpha that goes from 0 to 1; the weighting functions take it as ``mix`` and form
``(1 - alpha) * 1 + alpha * w`` before the cap. The paper uses ``start=20_000``,
``ramp=30_000`` of 100K steps. alpha is a pure function of the step count; the objective keeps
that count in its state so that a resumed run continues the same schedule.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

__all__ = ["SCHEDULE_SHAPES", "MixSchedule", "mix_at"]

SCHEDULE_SHAPES: tuple[str, ...] = ("linear", "cosine")


def _check(start: int, ramp: int, shape: str) -> None:
    for name, value in (("start", start), ("ramp", ramp)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise ValueError(f"schedule {name} must be an int >= 0 (a step count), got {value!r}.")
    if shape not in SCHEDULE_SHAPES:
        raise ValueError(f"schedule shape must be one of {SCHEDULE_SHAPES}, got {shape!r}.")


def mix_at(step: int | Tensor, *, start: int, ramp: int, shape: str = "linear") -> float | Tensor:
    """alpha at optimisation step ``step`` (0-based): 0 before ``start``, 1 from ``start + ramp``.

    Between them alpha rises as ``x = (step - start) / ramp`` (``"linear"``) or
    ``(1 - cos(pi x)) / 2`` (``"cosine"``). ``ramp=0`` is a switch at ``start``. Works on a Python
    int (returns a float) and on an integer tensor (returns a float32 tensor, without a host
    sync, so it can live inside a compiled graph).
    """
    _check(start, ramp, shape)
    if isinstance(step, Tensor):
        if ramp == 0:
            return (step >= start).to(torch.float32)
        x = ((step.to(torch.float32) - start) / ramp).clamp(0.0, 1.0)
        return x if shape == "linear" else (1 - torch.cos(math.pi * x)) / 2
    if ramp == 0:
        return 1.0 if step >= start else 0.0
    x = min(max((step - start) / ramp, 0.0), 1.0)
    return x if shape == "linear" else (1 - math.cos(math.pi * x)) / 2


@dataclass(frozen=True)
class MixSchedule:
    """When TAR is on: off for ``start`` steps, then ramped in over ``ramp`` steps.

    Attributes:
        start: steps of plain uniform averaging before TAR begins (paper: 20_000).
        ramp: steps over which alpha rises from 0 to 1 (paper: 30_000); 0 switches at once.
        shape: ``"linear"`` (default) or ``"cosine"``.

    The default, ``MixSchedule()``, is TAR at full strength from the first step.

    Examples:
        >>> s = MixSchedule(start=20_000, ramp=30_000)
        >>> s(0), s(20_000), s(35_000), s(50_000), s(99_999)
        (0.0, 0.0, 0.5, 1.0, 1.0)
    """

    start: int = 0
    ramp: int = 0
    shape: Literal["linear", "cosine"] = "linear"

    def __post_init__(self) -> None:
        _check(self.start, self.ramp, self.shape)

    def __call__(self, step: int | Tensor) -> float | Tensor:
        return mix_at(step, start=self.start, ramp=self.ramp, shape=self.shape)
