"""Checks of the inputs of every weighting (per-step or per-element losses and their mask) and of the numbers its
parameters hold; imports torch only."""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = ["check_count", "check_finite", "check_number", "check_step_losses"]


def check_step_losses(losses: Tensor, valid: Tensor) -> None:
    """Raise a clear error if ``losses``/``valid`` are not a valid ``[..., L]`` pair.

    Checks types, dtypes and shapes, then that every loss at a valid step is finite (padded
    steps may hold anything). Under ``torch.compile`` the finiteness check becomes an
    in-graph assertion with the same message, so compiled code needs no graph break.
    """
    if not isinstance(losses, Tensor) or not isinstance(valid, Tensor):
        raise TypeError(f"losses and valid must be tensors, got {type(losses).__name__} and {type(valid).__name__}.")
    if not losses.is_floating_point():
        raise TypeError(f"losses must be a floating-point tensor, got dtype {losses.dtype}.")
    if valid.dtype != torch.bool:
        raise TypeError(
            f"valid must be a torch.bool mask (True on real steps, False on padding), got dtype {valid.dtype}."
        )
    if losses.ndim < 1 or losses.shape[-1] < 1:
        raise ValueError(f"losses must have shape [..., L] with L >= 1, got {tuple(losses.shape)}.")
    if losses.shape != valid.shape:
        raise ValueError(
            f"losses and valid must have the same shape [..., L], got {tuple(losses.shape)} and {tuple(valid.shape)}."
        )
    check_finite(losses, valid, "step")


def check_finite(losses: Tensor, valid: Tensor, what: str, quantity: str = "loss") -> None:
    """Raise a ``ValueError`` if a loss where ``valid`` is ``True`` is NaN or inf (``what``: ``step`` or
    ``element``, and ``quantity``, what the values are, for the message). Under ``torch.compile`` the check is an
    in-graph assertion with the same message, so compiled code needs no graph break."""
    bad = valid & ~torch.isfinite(losses.detach())
    message = f"non-finite per-{what} {quantity} at a valid {what}: the weights would be NaN."
    if torch.compiler.is_compiling():
        torch._assert_async(~bad.any(), message)
        return
    if bad.any():
        first = tuple(int(i) for i in bad.nonzero()[0])
        raise ValueError(
            f"{message} {int(bad.sum())} of {int(valid.sum())} valid {what}s are NaN or inf "
            f"(first at index {first}, value {losses.detach()[first].item()})."
        )


def check_number(name: str, value: object, rule: str, ok) -> None:
    """Raise a ``ValueError`` naming the parameter ``name`` unless ``value`` is a finite real number (not a bool)
    for which ``ok(value)`` holds; ``rule`` says the range in words (``"a number in [0, 1)"``)."""
    finite = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if not (finite and ok(value)):
        raise ValueError(f"{name} must be {rule}, got {value!r}.")


def check_count(name: str, value: object, low: int) -> None:
    """Raise a ``ValueError`` naming the parameter ``name`` unless ``value`` is an int (not a bool) ``>= low``."""
    if not (isinstance(value, int) and not isinstance(value, bool) and value >= low):
        raise ValueError(f"{name} must be an integer >= {low}, got {value!r}.")
