"""TAR on per-element losses: ``tar_arm`` and ``tar_dimnorm``, two variants that isolate what drives its weights.

A head's per-step loss is the mean of per-element losses over its event dims (the action
dims, and a chunk's horizon for chunked heads). TAR scores a step by that mean, so a dimension
with large errors (in MetaWorld the gripper, whose target jumps between -1 and 1) can decide
which steps TAR up-weights. The two variants score the steps otherwise and keep the rest of
TAR (z-score, softmax, unit mean, schedule, cap) unchanged:

* ``tar_arm``: TAR's weights come from the arm's dims only (every action dim but the gripper's,
  ``gripper_dims``; MetaWorld's xyz) and apply to those dims' losses; the gripper's loss is
  averaged uniformly. It asks whether TAR helps once the gripper no longer steers it.
* ``tar_dimnorm``: each element's loss is divided by its action dimension's mean loss over the
  batch's valid elements before the step's score is taken, so every dimension has mean 1 and
  none dominates the score; the weights apply to the whole step loss.

Conventions (shared by every element weighting, ``Weighting.elementwise``):

* ``losses``: floating ``[B, L, *event, A]`` per-element losses, ``A`` the action dims (last, as
  every head of tar-rl lays them out). Detached here; half precision is scored in float32.
* ``valid``: ``torch.bool`` of the same shape, ``True`` on a real element of a real step. A step
  is real when any of its elements is.
* the weights: per element, shape and dtype of ``losses``, ``>= 0``, ``0`` on invalid elements.
  ``TARLoss`` takes each step's loss as the mean over its valid elements of ``weight * loss``
  and averages the steps of a segment uniformly, so an element weighting that gives every
  element of a step the weight ``w_t`` is exactly the step weighting ``w_t``. A segment's step
  weights (each the mean of its valid elements' weights) have mean 1 over its valid steps.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from .checks import check_finite
from .tar import (
    DEFAULT_EPS,
    DEFAULT_GAMMA,
    DEFAULT_W_MAX,
    HALF_DTYPES,
    CapMode,
    TARParams,
    weights_from_scores,
)
from .weighting import WEIGHTINGS, Weighting

__all__ = [
    "TARArmParams",
    "check_element_losses",
    "check_gripper_dims",
    "element_mean",
    "masked_mean",
    "tar_arm_weights",
    "tar_dimnorm_weights",
]


@dataclass(frozen=True)
class TARArmParams(TARParams):
    """``tar_arm``'s parameters: TAR's (:class:`~tar_rl.objectives.tar.TARParams`) and the gripper's dims.

    Attributes:
        gripper_dims: the gripper's action dims (indices along the last axis of per-element losses; negative
            counts from the end) that ``tar_arm`` averages uniformly, a non-empty tuple of distinct ints.
            Default ``(-1,)``, the last dim (MetaWorld's and LIBERO's gripper).
    """

    gripper_dims: tuple[int, ...] = (-1,)

    def __post_init__(self) -> None:
        super().__post_init__()
        dims = self.gripper_dims
        if not (
            isinstance(dims, tuple)
            and dims
            and all(isinstance(d, int) and not isinstance(d, bool) for d in dims)
            and len(set(dims)) == len(dims)
        ):
            raise ValueError(f"gripper_dims must be a non-empty tuple of distinct ints, got {dims!r}.")


def check_element_losses(losses: Tensor, valid: Tensor) -> None:
    """Raise a clear error unless ``losses``/``valid`` are a ``[B, L, *event, A]`` pair, finite where valid."""
    if not isinstance(losses, Tensor) or not isinstance(valid, Tensor):
        raise TypeError(f"losses and valid must be tensors, got {type(losses).__name__} and {type(valid).__name__}.")
    if not losses.is_floating_point():
        raise TypeError(f"losses must be a floating-point tensor, got dtype {losses.dtype}.")
    if valid.dtype != torch.bool:
        raise TypeError(f"valid must be a torch.bool mask (True on real elements), got dtype {valid.dtype}.")
    if losses.ndim < 3:
        raise ValueError(
            f"an element weighting needs per-element losses [B, L, ..., A] (the action dims last), got shape "
            f"{tuple(losses.shape)}: the head's loss returns one loss per step, so score its steps with a step "
            "weighting such as 'tar'."
        )
    if losses.shape != valid.shape:
        raise ValueError(
            f"losses and valid must have the same shape, got {tuple(losses.shape)} and {tuple(valid.shape)}."
        )
    check_finite(losses, valid, "element")


def masked_mean(x: Tensor, valid: Tensor, axes: tuple[int, ...]) -> Tensor:
    """The mean of ``x`` over ``axes`` where ``valid`` is ``True``, 0 where no entry is (``x`` may be NaN
    elsewhere); with no axes, ``x`` where valid and 0 elsewhere."""
    kept = torch.where(valid, x, torch.zeros((), dtype=x.dtype, device=x.device))
    if not axes:
        return kept
    return kept.sum(axes) / valid.sum(axes).clamp_min(1).to(x.dtype)


def element_mean(x: Tensor, valid: Tensor, batch_dims: int = 2) -> Tensor:
    """Per step, the mean of ``x`` over the step's valid elements: ``[B, L, *event] -> [B, L]``; 0 if none.

    ``batch_dims`` counts the leading dims that index steps (``[B, L]``: 2).
    """
    return masked_mean(x, valid, tuple(range(batch_dims, x.ndim)))


def _prepare(losses: Tensor, valid: Tensor) -> tuple[Tensor, Tensor]:
    """Detached losses (float32 for half inputs, 0 on invalid elements) and the ``[B, L]`` step mask."""
    x = losses.detach()
    x = x.float() if x.dtype in HALF_DTYPES else x
    x = torch.where(valid, x, torch.zeros((), dtype=x.dtype, device=x.device))  # padding may hold NaN
    return x, valid.flatten(2).any(-1)


def check_gripper_dims(gripper_dims: tuple[int, ...], n_dims: int) -> None:
    """Refuse ``gripper_dims`` (``tar_arm``'s) that name dims outside ``n_dims`` action dims or leave no arm dim."""
    bad = [d for d in gripper_dims if not -n_dims <= d < n_dims]
    if bad:
        raise ValueError(
            f"gripper_dims {list(gripper_dims)} name dims outside the loss's {n_dims} action dims: {bad} "
            f"(valid: -{n_dims} .. {n_dims - 1})."
        )
    if len({d % n_dims for d in gripper_dims}) == n_dims:
        raise ValueError(
            f"gripper_dims {list(gripper_dims)} cover all {n_dims} action dims: no arm dim is left to score."
        )


def _gripper_mask(n_dims: int, gripper_dims: tuple[int, ...], device: torch.device) -> Tensor:
    """``[A]`` bool, ``True`` on the gripper's dims (:func:`check_gripper_dims` first)."""
    check_gripper_dims(gripper_dims, n_dims)
    gripper = torch.zeros(n_dims, dtype=torch.bool, device=device)
    gripper[[d % n_dims for d in gripper_dims]] = True
    return gripper


def _tar_arm(losses: Tensor, valid: Tensor, params: TARArmParams, mix: float | Tensor, generator) -> Tensor:
    check_element_losses(losses, valid)
    x, step_valid = _prepare(losses, valid)
    gripper = _gripper_mask(x.shape[-1], params.gripper_dims, x.device)
    arm_valid = valid & ~gripper
    w = weights_from_scores(element_mean(x, arm_valid), step_valid, mix=mix, **params.tar_kwargs())  # [B, L]
    w = w.reshape(w.shape + (1,) * (x.ndim - 2))
    return torch.where(arm_valid, w, valid.to(x.dtype)).to(losses.dtype)


def _tar_dimnorm(losses: Tensor, valid: Tensor, params: TARParams, mix: float | Tensor, generator) -> Tensor:
    check_element_losses(losses, valid)
    x, step_valid = _prepare(losses, valid)
    m = valid.to(x.dtype)
    flat_x, flat_m = x.reshape(-1, x.shape[-1]), m.reshape(-1, x.shape[-1])
    scale = flat_x.sum(0) / flat_m.sum(0).clamp_min(1)  # [A]: each dimension's mean loss over the batch
    # A dimension whose losses are all 0 scores 0 (0 / tiny), whatever its scale.
    normalised = x / scale.clamp_min(torch.finfo(x.dtype).tiny)
    w = weights_from_scores(element_mean(normalised, valid), step_valid, mix=mix, **params.tar_kwargs())  # [B, L]
    w = w.reshape(w.shape + (1,) * (x.ndim - 2))
    return (w * m).to(losses.dtype)


def tar_arm_weights(
    losses: Tensor,
    valid: Tensor,
    *,
    gripper_dims: tuple[int, ...] = TARArmParams.gripper_dims,
    gamma: float = DEFAULT_GAMMA,
    w_max: float = DEFAULT_W_MAX,
    eps: float = DEFAULT_EPS,
    cap: CapMode = "paper",
    mix: float | Tensor = 1.0,
) -> Tensor:
    """TAR's weights from the arm's dims, on the arm's dims; the gripper's dims weigh 1.

    A step's score is the mean loss over its valid arm elements (every action dim but
    ``gripper_dims``); TAR (Eqs. 4-8, with the schedule's ``mix``) turns the scores of a
    segment's valid steps into weights ``w_t``; each valid arm element of step ``t`` gets
    ``w_t``, each valid gripper element ``1``, each invalid element ``0``.

    Args:
        losses: ``[B, L, *event, A]`` floating per-element losses (action dims last).
        valid: bool of the same shape, ``True`` on real elements of real steps.

    Keyword Args:
        gripper_dims: the gripper's indices along the last axis (negative counts from the end);
            default ``(-1,)``, the last dim (MetaWorld's and LIBERO's gripper). At least one dim
            must remain for the arm.
        gamma, w_max, eps, cap, mix: as for :func:`tar_rl.objectives.tar_weights`.

    Returns:
        Per-element weights of the shape and dtype of ``losses``.

    Examples:
        >>> import torch
        >>> losses = torch.tensor([[[0.0, 9.0], [2.0, 0.0]]])  # [B=1, L=2, A=2]; dim 1 is the gripper
        >>> tar_arm_weights(losses, torch.ones(1, 2, 2, dtype=torch.bool), w_max=float("inf"))[0, :, 1].tolist()
        [1.0, 1.0]
    """
    params = TARArmParams(gamma=gamma, w_max=w_max, eps=eps, cap=cap, gripper_dims=gripper_dims)
    return _tar_arm(losses, valid, params, mix, None)


def tar_dimnorm_weights(
    losses: Tensor,
    valid: Tensor,
    *,
    gamma: float = DEFAULT_GAMMA,
    w_max: float = DEFAULT_W_MAX,
    eps: float = DEFAULT_EPS,
    cap: CapMode = "paper",
    mix: float | Tensor = 1.0,
) -> Tensor:
    """TAR's weights from per-dimension normalised losses, on the whole step.

    Each valid element's loss is divided by its action dimension's mean loss over every valid
    element of the batch (all segments, steps and chunk entries); a step's score is the mean of
    its normalised elements; TAR turns a segment's scores into weights ``w_t``, which every valid
    element of step ``t`` gets (invalid elements ``0``). The scale is the batch's, not the
    segment's, so that a dimension whose losses are uniformly small in one segment is not blown
    up to the others' size; the weights are therefore not a function of one segment alone.

    Args, Keyword Args: as for :func:`tar_arm_weights`, without ``gripper_dims``.

    Returns:
        Per-element weights of the shape and dtype of ``losses``.
    """
    params = TARParams(gamma=gamma, w_max=w_max, eps=eps, cap=cap)
    return _tar_dimnorm(losses, valid, params, mix, None)


for _w in (
    Weighting(
        "tar_arm",
        _tar_arm,
        TARArmParams,
        elementwise=True,
        summary="TAR scored and applied on the arm's action dims; the gripper's loss averaged uniformly",
    ),
    Weighting(
        "tar_dimnorm",
        _tar_dimnorm,
        TARParams,
        elementwise=True,
        summary="TAR scored on per-element losses normalised by their action dimension's batch mean",
    ),
):
    WEIGHTINGS.register(_w.name, _w)
