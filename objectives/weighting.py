"""TAR's control variants (shuffle, random, invert, the supervision perturbations), ``window_weights``
and the registry of weightings, each entry naming the frozen dataclass of its own parameters.

TAR itself (paper Eqs. 3-8, ``tar_weights``, its parameters ``TARParams``) lives in
:mod:`~tar_rl.objectives.tar`; the controls reuse its building blocks and its parameters. The
baselines from the literature (tilted, truncate, keyframe, focal, dro_time) live in
:mod:`~tar_rl.objectives.baselines`, each with its own parameters, and share
:mod:`~tar_rl.objectives.tar`'s conventions (shapes, mask polarity, unit mean) and this registry.

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

from .checks import check_number, check_step_losses
from .registry import Registry
from .tar import (
    HALF_DTYPES,
    TARParams,
    tar_weights,
    weights_from_scores,
)

__all__ = [
    "WEIGHTINGS",
    "NoParams",
    "PerturbParams",
    "Weighting",
    "get_weighting",
    "invert_weights",
    "perturb_mask",
    "random_weights",
    "shuffle_weights",
    "tar_weights",  # defined in .tar; re-exported with its controls
    "uniform_weights",
    "window_weights",
]


@dataclass(frozen=True)
class NoParams:
    """The parameters of a weighting that has none (``uniform``)."""


@dataclass(frozen=True)
class PerturbParams:
    """The parameters of the supervision-perturbation controls ``perturb_high`` and ``perturb_low``
    (:class:`~tar_rl.objectives.supervision.PerturbedTarget`), checked when built. The paper gives neither.

    Attributes:
        perturb_fraction: the fraction of each segment's valid steps whose expert target is corrupted at
            full schedule strength (scaled by the schedule's alpha), in ``[0, 1]``. Default ``0.25``.
        perturb_scale: the standard deviation of the Gaussian noise added to those targets, in target units,
            a finite number ``>= 0``. Default ``0.1``.
    """

    perturb_fraction: float = 0.25
    perturb_scale: float = 0.1

    def __post_init__(self) -> None:
        check_number("perturb_fraction", self.perturb_fraction, "a number in [0, 1]", lambda v: 0 <= v <= 1)
        check_number("perturb_scale", self.perturb_scale, "a finite number >= 0", lambda v: v >= 0)


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
    return weights_from_scores(-losses.detach(), valid, mix=mix, **TARParams(**params).tar_kwargs())


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
    return weights_from_scores(scores, valid, mix=mix, **TARParams(**params).tar_kwargs())


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
        weights: ``(losses, valid, params, mix, generator, **inputs) -> weights``, pure; ``params`` is an
            instance of ``params``. ``inputs`` is empty unless the fields below say otherwise: a weighting
            that ``reads_time`` also gets ``step`` and ``episode_length`` (integer tensors shaped like
            ``losses``: each step's index in its episode and that episode's length); a stateful one
            (``initial_state`` set) also gets ``state`` (its current state, not modified) and ``reduce``
            (``None``, or a function that sums a tensor over the ranks of a distributed job, for the batch
            statistics its update reads) and returns ``(weights, new_state)``.
        params: the frozen dataclass of the weighting's parameters (its defaults are the weighting's; its
            ``__post_init__`` refuses a value out of range, naming the field). The recipe's config group of
            the weighting is generated from its fields.
        perturb: ``"high"``/``"low"`` for the supervision-perturbation controls, whose inner loss is the head's
            wrapped in :class:`~tar_rl.objectives.supervision.PerturbedTarget` of that kind (the training job
            builds it; it corrupts the expert targets of the steps :func:`perturb_mask` selects) and whose
            ``weights`` are the uniform mean; ``None`` otherwise.
        stochastic: whether ``weights`` draws random numbers (from ``generator``).
        summary: one line for listings and error messages.
        reads_time: whether ``weights`` reads each step's position in its episode (``step``,
            ``episode_length``).
        initial_state: ``(params) -> state``, the state a stateful weighting starts from (a tensor that
            :class:`~tar_rl.objectives.tar_loss.WeightingState` holds as a buffer, so that it is part of the
            objective's ``state_dict()``, and replaces with ``new_state`` after each training step); ``None``
            for a weighting without state.
        elementwise: ``weights`` scores per-element losses ``[B, L, *event, A]`` with a mask of that shape and
            returns per-element weights (:mod:`~tar_rl.objectives.elementwise`); ``False``: per-step losses
            ``[..., L]`` in, per-step weights out.
        compilable: ``False`` for a weighting not worth compiling (``uniform``: nothing to fuse); see
            :attr:`eager`.
    """

    name: str
    weights: Callable[..., Tensor | tuple[Tensor, Tensor]]
    params: type = NoParams
    perturb: Literal["high", "low"] | None = None
    stochastic: bool = False
    summary: str = ""
    reads_time: bool = False
    initial_state: Callable[..., Tensor] | None = None
    elementwise: bool = False
    compilable: bool = True

    @property
    def eager(self) -> bool:
        """Whether ``weights`` always runs eagerly, never through ``torch.compile``: it draws random numbers, reads
        time, holds state, or is not :attr:`compilable`."""
        return not self.compilable or self.stochastic or self.reads_time or self.initial_state is not None


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
    Weighting("uniform", _uniform, summary="uniform temporal mean over valid steps (Eq. 1)", compilable=False),
    Weighting("tar", _tar, TARParams, summary="time-adaptive reweighting (Eqs. 3-8)"),
    Weighting(
        "shuffle",
        _shuffle,
        TARParams,
        stochastic=True,
        summary="TAR's weights permuted among a segment's valid steps",
    ),
    Weighting("random", _random, TARParams, stochastic=True, summary="random scores through TAR's normalisation"),
    Weighting("invert", _invert, TARParams, summary="TAR's emphasis reversed (TAR on the negated losses)"),
    Weighting(
        "perturb_high",
        _uniform,
        PerturbParams,
        perturb="high",
        summary="noise on the expert actions of the steps TAR up-weights, uniform mean",
        compilable=False,
    ),
    Weighting(
        "perturb_low",
        _uniform,
        PerturbParams,
        perturb="low",
        summary="noise on the expert actions of the steps TAR down-weights, uniform mean",
        compilable=False,
    ),
):
    WEIGHTINGS.register(_w.name, _w)


def get_weighting(name: str) -> Weighting:
    """The registered weighting called ``name``; a clear error listing the names otherwise."""
    return WEIGHTINGS.get(name)
