"""TAR's control variants (shuffle, random, invert, the supervision perturbations), ``window_weights``,
the hyper-parameters of every weighting (``WeightingParams``) and the registry of weightings.

TAR itself (paper Eqs. 3-8, ``tar_weights``) lives in :mod:`~tar_rl.objectives.tar`; the controls
reuse its building blocks. The baselines from the literature (tilted, truncate, keyframe, focal,
dro_time) live in :mod:`~tar_rl.objectives.baselines` and share :mod:`~tar_rl.objectives.tar`'s
conventions (shapes, mask polarity, unit mean) and this module's parameters and registry.

Every function here is pure: it reads ``losses`` and ``valid`` and returns a new tensor of
weights. Nothing is differentiated through the weights.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

from .checks import check_step_losses
from .registry import Registry
from .tar import (
    DEFAULT_EPS,
    DEFAULT_GAMMA,
    DEFAULT_W_MAX,
    HALF_DTYPES,
    CapMode,
    check_tar_params,
    tar_weights,
    weights_from_scores,
)

__all__ = [
    "DEFAULT_DRO_BINS",
    "DEFAULT_DRO_ETA",
    "DEFAULT_FOCAL_BETA",
    "DEFAULT_GRIPPER_DIMS",
    "DEFAULT_KEYFRAME_FACTOR",
    "DEFAULT_KEYFRAME_FRACTION",
    "DEFAULT_TILT",
    "DEFAULT_TRUNCATE_FRACTION",
    "WEIGHTINGS",
    "Weighting",
    "WeightingParams",
    "get_weighting",
    "invert_weights",
    "perturb_mask",
    "random_weights",
    "shuffle_weights",
    "tar_weights",  # defined in .tar; re-exported with its controls
    "uniform_weights",
    "window_weights",
]

#: Tilt ``t`` of the ``tilted`` baseline (:func:`~tar_rl.objectives.baselines.tilted_weights`).
DEFAULT_TILT = 1.0
#: Fraction ``q`` of a segment's valid steps that the ``truncate`` baseline drops.
DEFAULT_TRUNCATE_FRACTION = 0.1
#: Fraction ``f`` of a segment's valid steps that the ``keyframe`` baseline up-weights.
DEFAULT_KEYFRAME_FRACTION = 0.3
#: How many times the weight of the other steps the ``keyframe`` baseline gives its selected steps.
DEFAULT_KEYFRAME_FACTOR = 5.0
#: Exponent ``beta`` of the ``focal`` baseline.
DEFAULT_FOCAL_BETA = 1.0
#: Step size ``eta`` of the ``dro_time`` baseline's group weights: 0.01, the step size of Sagawa et al.
#: (ICLR 2020) for their group DRO experiments.
DEFAULT_DRO_ETA = 0.01
#: Groups of the ``dro_time`` baseline: bins of normalised episode time.
DEFAULT_DRO_BINS = 10
#: ``tar_arm``'s gripper dims: the last action dim (MetaWorld's and LIBERO's gripper).
DEFAULT_GRIPPER_DIMS: tuple[int, ...] = (-1,)


def _finite_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


@dataclass(frozen=True)
class WeightingParams:
    """The hyper-parameters of every registered weighting, checked once when built.

    TAR and its controls read ``gamma``, ``w_max``, ``eps`` and ``cap``; each baseline of
    :mod:`~tar_rl.objectives.baselines` reads its own fields (``focal`` also ``w_max``).

    Attributes:
        gamma: softmax temperature on the z-scores (Eq. 6), ``> 0``.
        w_max: cap on a step's weight (Eq. 8), ``> 0``; ``math.inf`` disables the cap.
            ``cap="exact"`` needs ``w_max >= 1`` (weights of mean 1 cannot all lie below 1).
        eps: stabiliser added to the standard deviation (Eq. 5), ``> 0``.
        cap: ``"paper"`` clips once and renormalises (Eq. 8 as printed: after it a weight may
            end above ``w_max``); ``"exact"`` finds the unit-mean weights
            ``min(c * w, w_max)`` for which the cap holds exactly.
        tilt: ``t`` of ``tilted``, a finite number ``> 0``. Default ``1.0``.
        truncate_fraction: ``q`` of ``truncate``, in ``[0, 1)``. Default ``0.1``.
        keyframe_fraction: ``f`` of ``keyframe``, in ``(0, 1)``. Default ``0.3``.
        keyframe_factor: ``K`` of ``keyframe``, a finite number ``>= 1``. Default ``5.0``.
        focal_beta: ``beta`` of ``focal``, a finite number ``>= 0``. Default ``1.0``.
        dro_eta: ``eta`` of ``dro_time``, the step size of its group weights, a finite number ``> 0``.
            Default ``0.01``.
        dro_bins: ``G`` of ``dro_time``, the number of bins of normalised episode time, an integer
            ``>= 1``. Default ``10``.
        gripper_dims: the gripper's action dims (indices along the last axis of per-element
            losses; negative counts from the end) that ``tar_arm`` averages uniformly: a
            non-empty tuple of distinct ints. Default ``(-1,)``.
    """

    gamma: float = DEFAULT_GAMMA
    w_max: float = DEFAULT_W_MAX
    eps: float = DEFAULT_EPS
    cap: CapMode = "paper"
    tilt: float = DEFAULT_TILT
    truncate_fraction: float = DEFAULT_TRUNCATE_FRACTION
    keyframe_fraction: float = DEFAULT_KEYFRAME_FRACTION
    keyframe_factor: float = DEFAULT_KEYFRAME_FACTOR
    focal_beta: float = DEFAULT_FOCAL_BETA
    dro_eta: float = DEFAULT_DRO_ETA
    dro_bins: int = DEFAULT_DRO_BINS
    gripper_dims: tuple[int, ...] = DEFAULT_GRIPPER_DIMS

    def __post_init__(self) -> None:
        check_tar_params(gamma=self.gamma, w_max=self.w_max, eps=self.eps, cap=self.cap)
        for name, ok, rule in (
            ("tilt", lambda v: v > 0, "a finite number > 0"),
            ("truncate_fraction", lambda v: 0 <= v < 1, "a number in [0, 1)"),
            ("keyframe_fraction", lambda v: 0 < v < 1, "a number in (0, 1)"),
            ("keyframe_factor", lambda v: v >= 1, "a finite number >= 1"),
            ("focal_beta", lambda v: v >= 0, "a finite number >= 0"),
            ("dro_eta", lambda v: v > 0, "a finite number > 0"),
        ):
            value = getattr(self, name)
            if not (_finite_number(value) and ok(value)):
                raise ValueError(f"{name} must be {rule}, got {value!r}.")
        bins = self.dro_bins
        if not (isinstance(bins, int) and not isinstance(bins, bool) and bins >= 1):
            raise ValueError(f"dro_bins must be an integer >= 1, got {bins!r}.")
        dims = self.gripper_dims
        if not (
            isinstance(dims, tuple)
            and dims
            and all(isinstance(d, int) and not isinstance(d, bool) for d in dims)
            and len(set(dims)) == len(dims)
        ):
            raise ValueError(f"gripper_dims must be a non-empty tuple of distinct ints, got {dims!r}.")

    def tar_kwargs(self) -> dict:
        """TAR's hyper-parameters as keyword arguments of :func:`~tar_rl.objectives.tar.tar_weights`."""
        return {"gamma": self.gamma, "w_max": self.w_max, "eps": self.eps, "cap": self.cap}


def _rand_like(x: Tensor, generator: torch.Generator | None, normal: bool) -> Tensor:
    """Random numbers shaped like ``x``, drawn on the generator's device, moved to ``x``'s."""
    device = generator.device if generator is not None else x.device
    draw = torch.randn if normal else torch.rand
    return draw(x.shape, generator=generator, device=device, dtype=torch.float32).to(x.device)


# ---------------------------------------------------------------------------------------------
# Public weightings
# ---------------------------------------------------------------------------------------------


def window_weights(losses: Tensor, slice_len: int, **params) -> Tensor:
    """TAR's weight of each step of a whole trajectory, averaged over the windows that contain it.

    Training draws segments of ``slice_len`` steps from a trajectory; a step's weight depends on
    the segment around it. This gives, for each step ``t`` of a ``[T]`` trajectory of per-step
    losses, the mean of :func:`tar_weights` at ``t`` over every window of ``slice_len``
    consecutive steps that contains ``t`` (all steps valid): the weight the step gets on average
    when a training segment contains it (the paper's Fig. 5 plots this kind of curve). A
    trajectory shorter than ``slice_len`` is one window.

    Args:
        losses: ``[T]`` per-step losses (finite).
        slice_len: the training segment length ``L`` (>= 1).
        **params: ``gamma``, ``w_max``, ``eps``, ``cap``, ``mix`` as for :func:`tar_weights`.

    Returns:
        ``[T]`` weights in ``losses``' float dtype.
    """
    if losses.ndim != 1 or losses.shape[0] == 0:
        raise ValueError(f"losses must be a non-empty [T] tensor, got shape {list(losses.shape)}")
    if slice_len < 1:
        raise ValueError(f"slice_len must be >= 1, got {slice_len}")
    n = losses.shape[0]
    width = min(slice_len, n)
    windows = losses.detach().unfold(0, width, 1)  # [n - width + 1, width]
    w = tar_weights(windows, torch.ones_like(windows, dtype=torch.bool), **params)
    starts = torch.arange(windows.shape[0], device=losses.device)
    index = (starts[:, None] + torch.arange(width, device=losses.device)).reshape(-1)
    total = torch.zeros(n, dtype=w.dtype, device=losses.device).index_add_(0, index, w.reshape(-1))
    count = torch.zeros(n, dtype=w.dtype, device=losses.device).index_add_(0, index, torch.ones_like(w).reshape(-1))
    return total / count


def uniform_weights(losses: Tensor, valid: Tensor) -> Tensor:
    """Eq. 1: every valid step weighs ``1``, padding ``0`` (the plain masked mean)."""
    check_step_losses(losses, valid)
    return valid.to(losses.dtype)


def invert_weights(losses: Tensor, valid: Tensor, *, mix: float | Tensor = 1.0, **params) -> Tensor:
    """TAR's emphasis reversed: TAR's construction applied to the negated losses.

    The z-score of ``-l`` is ``-s``, so the softmax favours the steps TAR disfavours, with the
    same temperature, unit mean, mixing and cap (``**params`` as in :func:`tar_weights`).
    """
    check_step_losses(losses, valid)
    return weights_from_scores(-losses.detach(), valid, mix=mix, **WeightingParams(**params).tar_kwargs())


def random_weights(
    losses: Tensor,
    valid: Tensor,
    *,
    mix: float | Tensor = 1.0,
    generator: torch.Generator | None = None,
    **params,
) -> Tensor:
    """Random scores (standard normal, one per step) through TAR's normalisation.

    The losses are used only for their shape, dtype and validity: the weights keep TAR's
    unit mean, temperature, mixing and cap but carry no information about the steps.
    """
    check_step_losses(losses, valid)
    scores = _rand_like(losses, generator, normal=True).to(losses.dtype)
    return weights_from_scores(scores, valid, mix=mix, **WeightingParams(**params).tar_kwargs())


def _random_order(valid: Tensor, generator: torch.Generator | None) -> Tensor:
    """Per row, a uniformly random order of the valid positions, followed by the padded ones."""
    keys = _rand_like(valid, generator, normal=False).masked_fill(~valid, 2.0)
    return keys.argsort(dim=-1)


def shuffle_weights(
    losses: Tensor,
    valid: Tensor,
    *,
    mix: float | Tensor = 1.0,
    generator: torch.Generator | None = None,
    **params,
) -> Tensor:
    """TAR's weights, permuted uniformly at random among the valid steps of each segment.

    Same multiset of weights per segment as :func:`tar_weights`, at random times.
    """
    weights = tar_weights(losses, valid, mix=mix, **params)
    # Valid positions in time order, then padded ones; and a random order of the same sets.
    in_order = torch.where(valid, 0, 1).to(torch.int8).argsort(dim=-1, stable=True)
    shuffled = _random_order(valid, generator)
    return torch.zeros_like(weights).scatter(-1, in_order, weights.gather(-1, shuffled))


def perturb_mask(
    losses: Tensor,
    valid: Tensor,
    *,
    fraction: float | Tensor,
    which: Literal["high", "low"],
    generator: torch.Generator | None = None,
) -> Tensor:
    """The steps whose supervision the ``perturb_high`` / ``perturb_low`` controls corrupt.

    Within a segment TAR's weights are an increasing function of the step loss (the z-score
    and the softmax are monotone; the cap only merges the top into ties), so "the steps TAR
    would up-weight" are the steps with the largest losses. Selects, per segment,
    ``floor(fraction * M + 1/2)`` valid steps (halves round up): the highest-loss ones for
    ``which="high"``, the lowest-loss ones for ``which="low"``; ties are broken at random.

    Returns:
        ``[..., L]`` bool, ``True`` on the selected steps (never on padding).
    """
    check_step_losses(losses, valid)
    if which not in ("high", "low"):
        raise ValueError(f"which must be 'high' or 'low', got {which!r}.")
    if isinstance(fraction, (int, float)) and not 0 <= fraction <= 1:
        raise ValueError(f"fraction must lie in [0, 1], got {fraction!r}.")
    x = losses.detach()
    x = x.float() if x.dtype in HALF_DTYPES else x  # rank in the losses' own precision (float64 stays)
    x = -x if which == "high" else x
    x = x.masked_fill(~valid, math.inf)
    # Random tie-breaking: visit the steps in a random order, then sort stably by loss.
    tiebreak = _random_order(torch.ones_like(valid), generator)
    ranked = tiebreak.gather(-1, x.gather(-1, tiebreak).argsort(dim=-1, stable=True))
    rank = torch.empty_like(ranked).scatter_(-1, ranked, torch.arange(x.shape[-1], device=x.device).expand_as(ranked))
    n_pick = torch.floor(fraction * valid.sum(-1, keepdim=True) + 0.5)
    return (rank < n_pick) & valid


# ---------------------------------------------------------------------------------------------
# The registry
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Weighting:
    """A named way of averaging per-step losses over a segment.

    Attributes:
        name: the registry name a recipe uses.
        weights: ``(losses, valid, params, mix, generator, **inputs) -> weights``, pure. ``inputs`` is
            empty unless the fields below say otherwise: a weighting that ``reads_time`` also gets
            ``step`` and ``episode_length`` (integer tensors shaped like ``losses``: each step's index in
            its episode and that episode's length); a stateful one (``initial_state`` set) also gets
            ``state`` (its current state, not modified) and ``reduce`` (``None``, or a function that
            sums a tensor over the ranks of a distributed job, for the batch statistics its update
            reads) and returns ``(weights, new_state)``.
        perturb: ``"high"``/``"low"`` for the supervision-perturbation controls: the objective
            corrupts the expert actions of the steps :func:`perturb_mask` selects and averages
            uniformly; ``None`` otherwise.
        stochastic: whether the weighting draws random numbers (from ``generator``).
        summary: one line for listings and error messages.
        check: ``(params) -> None``, raises a ``ValueError`` naming the parameter when
            ``params`` (valid in general) do not suit this weighting; ``None``: all do.
        reads_time: whether ``weights`` reads each step's position in its episode (``step``,
            ``episode_length``).
        initial_state: ``(params) -> state``, the state a stateful weighting starts from (a tensor
            that :class:`~tar_rl.objectives.TARLoss` holds as a buffer, so that it is part of its
            ``state_dict()``, and replaces with ``new_state`` after each training step); ``None``
            for a weighting without state.
        elementwise: ``weights`` scores per-element losses ``[B, L, *event, A]`` with a mask of
            that shape and returns per-element weights (:mod:`~tar_rl.objectives.elementwise`);
            ``False``: per-step losses ``[..., L]`` in, per-step weights out.
    """

    name: str
    weights: Callable[..., Tensor | tuple[Tensor, Tensor]]
    perturb: Literal["high", "low"] | None = None
    stochastic: bool = False
    summary: str = ""
    check: Callable[[WeightingParams], None] | None = None
    reads_time: bool = False
    initial_state: Callable[[WeightingParams], Tensor] | None = None
    elementwise: bool = False


def _uniform(losses, valid, params, mix, generator):
    return uniform_weights(losses, valid)


def _tar(losses, valid, params, mix, generator):
    check_step_losses(losses, valid)
    return weights_from_scores(losses.detach(), valid, mix=mix, **params.tar_kwargs())


def _invert(losses, valid, params, mix, generator):
    return invert_weights(losses, valid, mix=mix, **params.tar_kwargs())


def _random(losses, valid, params, mix, generator):
    return random_weights(losses, valid, mix=mix, generator=generator, **params.tar_kwargs())


def _shuffle(losses, valid, params, mix, generator):
    return shuffle_weights(losses, valid, mix=mix, generator=generator, **params.tar_kwargs())


WEIGHTINGS: Registry[Weighting] = Registry("weighting")
for _w in (
    Weighting("uniform", _uniform, summary="uniform temporal mean over valid steps (Eq. 1)"),
    Weighting("tar", _tar, summary="time-adaptive reweighting (Eqs. 3-8)"),
    Weighting("shuffle", _shuffle, stochastic=True, summary="TAR's weights permuted among a segment's valid steps"),
    Weighting("random", _random, stochastic=True, summary="random scores through TAR's normalisation"),
    Weighting("invert", _invert, summary="TAR's emphasis reversed (TAR on the negated losses)"),
    Weighting(
        "perturb_high",
        _uniform,
        perturb="high",
        stochastic=True,
        summary="noise on the expert actions of the steps TAR up-weights, uniform mean",
    ),
    Weighting(
        "perturb_low",
        _uniform,
        perturb="low",
        stochastic=True,
        summary="noise on the expert actions of the steps TAR down-weights, uniform mean",
    ),
):
    WEIGHTINGS.register(_w.name, _w)


def get_weighting(name: str) -> Weighting:
    """The registered weighting called ``name``; a clear error listing the names otherwise."""
    return WEIGHTINGS.get(name)
