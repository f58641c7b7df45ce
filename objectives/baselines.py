"""Temporal weightings from the literature, as baselines beside TAR: tilted, truncate, keyframe, focal, dro_time.

Each reweights the steps of a segment with another rule than TAR's; each tests one of TAR's
choices. They share :mod:`~tar_rl.objectives.tar`'s conventions:

* ``losses``: floating ``[..., L]`` per-step losses, any leading dims; detached here (no
  gradient flows through the weights). Half-precision losses are weighted in float32 and the
  weights cast back.
* ``valid``: ``torch.bool`` ``[..., L]``, ``True`` on real steps, ``False`` on padding.
* the weights: shape and dtype of ``losses``, ``>= 0``, ``0`` on padding, mean ``1`` over the
  valid steps of a segment that has one, all ``0`` in a segment that has none; ``1`` on a lone
  valid step; all ``1`` when a segment's valid losses are equal (except ``dro_time``, whose
  weights depend on where the steps lie in their episodes, not on their own losses).
* ``mix``: the schedule's alpha, blended as for TAR: ``(1 - mix) * 1 + mix * w`` on the valid
  steps (before ``focal``'s cap, as TAR's is applied after its blend).

``tilted``, ``truncate``, ``keyframe`` and ``focal`` reweight the steps of a segment by their own
losses. ``tilted`` and ``focal`` divide by a segment's mean loss and need losses ``>= 0`` (every
imitation loss of tar-rl's heads is a squared or absolute error); a negative loss at a valid
step is refused. ``truncate`` and ``keyframe`` rank the steps by loss; steps of equal loss at
the boundary of the selection share it equally (below), so that every weight is a function of
the step's loss and of the segment's multiset of losses: the weights are equivariant under
any permutation of the steps, ties included.

``dro_time`` is group DRO over time: it weights a step by the group weight of its bin of
normalised episode time, which it learns online from the losses of every batch (its state, the
``[G]`` log group weights, is carried from step to step; :class:`~tar_rl.objectives.TARLoss`
holds it). It needs each step's position in its episode (the dataset's ``step`` and the
episode's length) and is not permutation equivariant. It divides by the batch's mean loss and
needs losses ``>= 0`` too.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from .checks import check_count, check_number, check_step_losses
from .tar import (
    DEFAULT_W_MAX,
    HALF_DTYPES,
    cap_exact,
    mix_uniform,
    unit_mean_softmax,
)
from .weighting import WEIGHTINGS, Weighting

__all__ = [
    "COUNT_TOLERANCE",
    "DROTimeParams",
    "FocalParams",
    "KeyframeParams",
    "TiltedParams",
    "TruncateParams",
    "dro_time_weights",
    "focal_weights",
    "keyframe_count",
    "keyframe_weights",
    "tilted_weights",
    "time_bins",
    "truncate_count",
    "truncate_weights",
]

#: Added to ``q * n`` (``f * n + 1/2``) before rounding down, so that a product that is an
#: integer on paper but falls just below it in binary (``0.29 * 100 = 28.999...``) rounds as on paper.
COUNT_TOLERANCE = 1e-9


# ---------------------------------------------------------------------------------------------
# Each baseline's parameters, checked when built
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class TiltedParams:
    """``tilted``'s parameters.

    Attributes:
        tilt: ``t`` of ``M * softmax(t * l / mean l)``, a finite number ``> 0``. Default ``1.0``.
    """

    tilt: float = 1.0

    def __post_init__(self) -> None:
        check_number("tilt", self.tilt, "a finite number > 0", lambda v: v > 0)


@dataclass(frozen=True)
class TruncateParams:
    """``truncate``'s parameters.

    Attributes:
        truncate_fraction: ``q``, the fraction of a segment's valid steps, by loss from the top, that weigh 0
            (``floor(q * M)`` steps), in ``[0, 1)``. Default ``0.1``.
    """

    truncate_fraction: float = 0.1

    def __post_init__(self) -> None:
        check_number("truncate_fraction", self.truncate_fraction, "a number in [0, 1)", lambda v: 0 <= v < 1)


@dataclass(frozen=True)
class KeyframeParams:
    """``keyframe``'s parameters.

    Attributes:
        keyframe_fraction: ``f``, the fraction of a segment's valid steps, by loss from the top, that are
            up-weighted (``floor(f * M + 1/2)`` steps, at least 1), in ``(0, 1)``. Default ``0.3``.
        keyframe_factor: ``K``, how many times the others' weight those steps get, a finite number ``>= 1``.
            Default ``5.0``.
    """

    keyframe_fraction: float = 0.3
    keyframe_factor: float = 5.0

    def __post_init__(self) -> None:
        check_number("keyframe_fraction", self.keyframe_fraction, "a number in (0, 1)", lambda v: 0 < v < 1)
        check_number("keyframe_factor", self.keyframe_factor, "a finite number >= 1", lambda v: v >= 1)


@dataclass(frozen=True)
class FocalParams:
    """``focal``'s parameters.

    Attributes:
        focal_beta: ``beta`` of ``(l / mean l) ** beta``, a finite number ``>= 0``. Default ``1.0``.
        w_max: the exact cap on a weight, ``>= 1`` (weights of mean 1 cannot all lie below 1; ``math.inf``:
            none). Default ``3.0``, TAR's.
    """

    focal_beta: float = 1.0
    w_max: float = DEFAULT_W_MAX

    def __post_init__(self) -> None:
        check_number("focal_beta", self.focal_beta, "a finite number >= 0", lambda v: v >= 0)
        if not (isinstance(self.w_max, (int, float)) and not isinstance(self.w_max, bool) and self.w_max >= 1):
            raise ValueError(
                f"w_max must be >= 1 for the focal weighting, whose cap is exact (weights of mean 1 cannot all "
                f"lie below 1), got {self.w_max!r}."
            )


@dataclass(frozen=True)
class DROTimeParams:
    """``dro_time``'s parameters.

    Attributes:
        dro_eta: ``eta``, the step size of the group weights, a finite number ``> 0``. Default ``0.01``, the
            step size of Sagawa et al. (ICLR 2020) for their group DRO experiments.
        dro_bins: ``G``, the number of bins of normalised episode time (the groups), an integer ``>= 1``.
            Default ``10``.
    """

    dro_eta: float = 0.01
    dro_bins: int = 10

    def __post_init__(self) -> None:
        check_number("dro_eta", self.dro_eta, "a finite number > 0", lambda v: v > 0)
        check_count("dro_bins", self.dro_bins, 1)


# ---------------------------------------------------------------------------------------------
# Shared steps. Internal: they assume checked inputs.
# ---------------------------------------------------------------------------------------------


def _prepare(losses: Tensor, valid: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Detached losses (float32 for half inputs, 0 on padding), the float mask and ``[..., 1]`` valid counts."""
    x = losses.detach()
    x = x.float() if x.dtype in HALF_DTYPES else x
    x = torch.where(valid, x, torch.zeros((), dtype=x.dtype, device=x.device))  # padding may hold NaN
    m = valid.to(x.dtype)
    return x, m, m.sum(-1, keepdim=True)


def _check_nonnegative(x: Tensor, valid: Tensor, name: str, by: str = "a segment's mean loss") -> None:
    """Refuse a negative loss at a valid step (an in-graph assertion under ``torch.compile``)."""
    bad = valid & (x < 0)
    message = f"the {name} weighting divides by {by} and needs per-step losses >= 0."
    if torch.compiler.is_compiling():
        torch._assert_async(~bad.any(), message)
        return
    if bad.any():
        first = tuple(int(i) for i in bad.nonzero()[0])
        raise ValueError(f"{message} {int(bad.sum())} valid steps are negative (first at {first}, {x[first].item()}).")


def truncate_count(n_valid: Tensor, fraction: float) -> Tensor:
    """Steps ``truncate`` drops from a segment of ``n_valid`` valid steps: ``floor(q * n)``, at most ``n - 1``.

    A segment drops nothing unless ``q * n >= 1`` (with ``q = 0.1``: segments of fewer than 10
    valid steps keep them all). The product is taken in float64 with :data:`COUNT_TOLERANCE`.
    Returns a float64 tensor shaped like ``n_valid``.
    """
    n = n_valid.to(torch.float64)
    return torch.minimum(torch.floor(n * fraction + COUNT_TOLERANCE), (n - 1).clamp_min(0))


def keyframe_count(n_valid: Tensor, fraction: float) -> Tensor:
    """Steps ``keyframe`` up-weights in a segment of ``n_valid`` valid steps: ``f * n`` rounded to the
    nearest integer, halves up (``floor(f * n + 1/2)``, as ``perturb_mask`` rounds), at least 1 and
    at most ``n`` (``0`` for ``n = 0``). Float64, with :data:`COUNT_TOLERANCE`."""
    n = n_valid.to(torch.float64)
    return torch.minimum(torch.floor(n * fraction + 0.5 + COUNT_TOLERANCE).clamp_min(1), n)


def _top_share(x: Tensor, valid: Tensor, n_valid: Tensor, count: Tensor) -> Tensor:
    """Per step, its share in the ``count`` highest-loss valid steps of its segment, in ``[0, 1]``.

    A step with ``a`` valid steps of strictly larger loss and ``e`` of equal loss (itself
    included) gets ``clamp((count - a) / e, 0, 1)``: the steps above the boundary get 1, those
    below 0, and a group of equal losses straddling it shares what is left equally. The shares
    of a segment sum to ``count``; padding gets 0. One sort per segment.
    """
    keys = torch.where(valid, x, torch.full((), math.inf, dtype=x.dtype, device=x.device))
    ordered = keys.sort(dim=-1).values.contiguous()
    below = torch.searchsorted(ordered, keys.contiguous(), side="left")  # valid steps of smaller loss
    upto = torch.searchsorted(ordered, keys.contiguous(), side="right")  # ... of smaller or equal loss
    above = n_valid - upto.to(x.dtype)
    ties = (upto - below).to(x.dtype).clamp_min(1)
    share = ((count.to(x.dtype) - above) / ties).clamp(0, 1)
    return torch.where(valid, share, torch.zeros((), dtype=x.dtype, device=x.device))


# ---------------------------------------------------------------------------------------------
# The four rules, on prepared inputs
# ---------------------------------------------------------------------------------------------


def _tilted(x: Tensor, valid: Tensor, m: Tensor, n_valid: Tensor, tilt: float) -> Tensor:
    mean = x.sum(-1, keepdim=True) / n_valid.clamp_min(1)
    # x / mean lies in [0, n]; a segment of zero losses has mean 0 and gets scores 0 (uniform).
    scores = x / mean.clamp_min(torch.finfo(x.dtype).tiny)
    return unit_mean_softmax(scores, valid, m, n_valid, tilt)


def _truncate(x: Tensor, valid: Tensor, m: Tensor, n_valid: Tensor, fraction: float) -> Tensor:
    count = truncate_count(n_valid, fraction).to(x.dtype)
    share = _top_share(x, valid, n_valid, count)
    return (m - share) * (n_valid / (n_valid - count).clamp_min(1))


def _keyframe(x: Tensor, valid: Tensor, m: Tensor, n_valid: Tensor, fraction: float, factor: float) -> Tensor:
    count = keyframe_count(n_valid, fraction).to(x.dtype)
    share = _top_share(x, valid, n_valid, count)
    extra = factor - 1
    return (m + extra * share) * (n_valid / (n_valid + extra * count).clamp_min(1))


def _focal(x: Tensor, valid: Tensor, m: Tensor, n_valid: Tensor, beta: float) -> Tensor:
    # (l / mean) ** beta renormalised to unit mean is M * softmax(beta * log l): the mean cancels.
    # A segment whose valid losses are all 0 has equal losses: it is weighted uniformly.
    zero_segment = (x * m).amax(-1, keepdim=True) <= 0
    x = torch.where(zero_segment, torch.ones((), dtype=x.dtype, device=x.device), x)
    logits = torch.xlogy(beta, x)  # beta * log l; -inf for l = 0 when beta > 0, 0 when beta = 0
    return unit_mean_softmax(logits, valid, m, n_valid, 1.0)


def _dro_time_update(x: Tensor, m: Tensor, time_bin: Tensor, log_q: Tensor, eta: float, reduce) -> Tensor:
    """One exponentiated-gradient step of the log group weights ``log_q`` ``[G]`` from a batch.

    The per-bin sums of the valid losses and the per-bin counts of valid steps are taken in
    ``log_q``'s dtype, passed through ``reduce`` (a sum over ranks) when given, then each bin with
    a valid step moves by ``eta * mean loss of the bin / mean loss of the batch``; a bin without
    one does not move. Renormalised with ``logsumexp``.
    """
    bins, dtype = log_q.shape[-1], log_q.dtype
    index = time_bin.reshape(-1)
    stats = torch.zeros(2, bins, dtype=dtype, device=log_q.device)
    stats[0].scatter_add_(0, index, (x * m).reshape(-1).to(dtype))
    stats[1].scatter_add_(0, index, m.reshape(-1).to(dtype))
    if reduce is not None:
        stats = reduce(stats)
    sums, counts = stats.unbind(0)
    batch_mean = sums.sum() / counts.sum().clamp_min(1)
    # Losses all 0: every ratio 0 (nothing moves).
    ratio = (sums / counts.clamp_min(1)) / batch_mean.clamp_min(torch.finfo(dtype).tiny)
    moved = log_q + torch.where(counts > 0, eta * ratio, torch.zeros((), dtype=dtype, device=log_q.device))
    return moved - torch.logsumexp(moved, dim=-1)


def _dro_time(
    losses: Tensor, valid: Tensor, time_bin: Tensor, log_q: Tensor, eta: float, mix: float | Tensor, reduce
) -> tuple[Tensor, Tensor]:
    """The update of the group weights, then the weights, on checked inputs."""
    x, m, n_valid = _prepare(losses, valid)
    _check_nonnegative(x, valid, "dro_time", by="the batch's mean loss")
    new_log_q = _dro_time_update(x, m, time_bin, log_q, eta, reduce)
    # w = M * softmax of log q[bin] over a segment's valid steps: G * q_g(t) normalised to unit mean.
    # In the state's dtype, so that a tiny q does not round to 0 first.
    w = unit_mean_softmax(new_log_q[time_bin], valid, m.to(new_log_q.dtype), n_valid.to(new_log_q.dtype), 1.0)
    return _finish(w, m.to(w.dtype), mix, losses.dtype), new_log_q


def _finish(w: Tensor, m: Tensor, mix: float | Tensor, dtype: torch.dtype) -> Tensor:
    return (mix_uniform(w, m, mix) * m).to(dtype)


# ---------------------------------------------------------------------------------------------
# Public weightings
# ---------------------------------------------------------------------------------------------


def tilted_weights(
    losses: Tensor, valid: Tensor, *, tilt: float = TiltedParams.tilt, mix: float | Tensor = 1.0
) -> Tensor:
    """Tilted empirical risk over the steps of a segment, made scale-free.

    Follows Li, Beirami, Sanjabi and Smith, "Tilted Empirical Risk Minimization" (ICLR 2021):
    the gradient of the tilted risk ``(1/t) log mean exp(t l)`` weights each loss by
    ``softmax(t l)``. Here the losses are divided by the segment's mean valid loss first, so one
    ``t`` means the same on heads whose losses differ by orders of magnitude::

        w = M * softmax(t * l / mean(l))   over a segment's M valid steps

    Softmax ignores shifts, so this is TAR (Eqs. 5-7) with the segment's mean in place of its
    standard deviation and without the cap: it tests those two choices.

    Args:
        losses: ``[..., L]`` per-step losses, ``>= 0`` at valid steps.
        valid: ``[..., L]`` bool mask.

    Keyword Args:
        tilt: ``t``, a finite number ``> 0``. Default ``1.0``.
        mix: the schedule's alpha in ``[0, 1]``; ``0`` gives uniform weights.

    Returns:
        Weights as described in :mod:`~tar_rl.objectives.baselines`; no cap.
    """
    params = TiltedParams(tilt=tilt)
    return _tilted_registered(losses, valid, params, mix, None)


def truncate_weights(
    losses: Tensor, valid: Tensor, *, fraction: float = TruncateParams.truncate_fraction, mix: float | Tensor = 1.0
) -> Tensor:
    """Loss truncation over the steps of a segment: the highest-loss steps weigh 0.

    Follows Kang and Hashimoto, "Improved Natural Language Generation via Loss Truncation"
    (ACL 2020), which drops the examples of highest loss as likely noise: here, in a segment of
    ``n`` valid steps, the ``k = floor(q * n)`` highest-loss steps (:func:`truncate_count`; at most
    ``n - 1``) get weight 0 and the others ``n / (n - k)``. Steps of equal loss at the boundary
    share the dropped mass equally (a group of ``e`` tied steps of which ``r`` fall among the top
    ``k`` each get ``(1 - r / e) * n / (n - k)``). The robust opposite of TAR: it bets that
    high-loss steps are noise.

    Keyword Args:
        fraction: ``q``, in ``[0, 1)``. Default ``0.1``: a 16-step segment drops its top step;
            segments of fewer than 10 valid steps drop nothing.
        mix: the schedule's alpha in ``[0, 1]``.
    """
    params = TruncateParams(truncate_fraction=fraction)
    return _truncate_registered(losses, valid, params, mix, None)


def keyframe_weights(
    losses: Tensor,
    valid: Tensor,
    *,
    fraction: float = KeyframeParams.keyframe_fraction,
    factor: float = KeyframeParams.keyframe_factor,
    mix: float | Tensor = 1.0,
) -> Tensor:
    """Keyframe-focused weighting: the highest-loss steps weigh ``K`` times the others.

    After Wen et al., "Keyframe-Focused Visual Imitation Learning" (ICML 2021), which up-weights
    the few keyframes where the expert's action changes in a way its past does not predict; here
    the keyframes of a segment of ``n`` valid steps are its ``k`` highest-loss steps,
    ``k = floor(f * n + 1/2)``, at least 1 (:func:`keyframe_count`).
    They get ``K * n / (n + (K - 1) k)``, the others ``n / (n + (K - 1) k)``; tied steps at the
    boundary share the selection equally. A hard-threshold relative of TAR.

    Keyword Args:
        fraction: ``f``, in ``(0, 1)``. Default ``0.3``.
        factor: ``K``, a finite number ``>= 1`` (``1``: uniform). Default ``5.0``.
        mix: the schedule's alpha in ``[0, 1]``.
    """
    params = KeyframeParams(keyframe_fraction=fraction, keyframe_factor=factor)
    return _keyframe_registered(losses, valid, params, mix, None)


def focal_weights(
    losses: Tensor,
    valid: Tensor,
    *,
    beta: float = FocalParams.focal_beta,
    w_max: float = DEFAULT_W_MAX,
    mix: float | Tensor = 1.0,
) -> Tensor:
    """A regression analogue of focal weighting: ``w ~ (l / mean l) ** beta``, unit mean, capped.

    After Lin, Goyal, Girshick, He and Dollar, "Focal Loss for Dense Object Detection" (ICCV 2017),
    whose factor ``(1 - p) ** gamma`` grows with the error of an example; for a regression loss
    the error is the loss itself, relative to the segment's mean valid loss. The weights
    ``(l / mean l) ** beta`` are renormalised to unit mean over the valid steps, blended with
    uniform by ``mix``, then capped exactly at ``w_max``: the unit-mean ``min(c * w, w_max)``
    (TAR's ``cap="exact"``). A polynomial relative of TAR's exponential emphasis. Steps of loss
    0 weigh 0 for ``beta > 0`` (when the other steps cannot carry the mass under the cap, they
    share the rest equally); a segment of zero losses is weighted uniformly.

    Args:
        losses: ``[..., L]`` per-step losses, ``>= 0`` at valid steps.
        valid: ``[..., L]`` bool mask.

    Keyword Args:
        beta: a finite number ``>= 0`` (``0``: uniform). Default ``1.0``.
        w_max: the cap, ``>= 1`` (``math.inf``: none). Default ``3.0``.
        mix: the schedule's alpha in ``[0, 1]``.
    """
    params = FocalParams(focal_beta=beta, w_max=w_max)
    return _focal_registered(losses, valid, params, mix, None)


def time_bins(step: Tensor, episode_length: Tensor, bins: int, valid: Tensor | None = None) -> Tensor:
    """The bin of normalised episode time of each step: ``floor(bins * step / episode_length)``.

    Computed in integers, so that a step on a bin's boundary falls in the bin it opens (step 3 of
    an episode of 10 steps lies in bin 3 of 10). The steps ``0 .. T-1`` of an episode of ``T``
    steps fall in the bins ``0 .. bins-1``.

    Args:
        step: integer ``[..., L]``, each step's index in its episode (the dataset's ``step``).
        episode_length: integer ``[..., L]``, the length of that episode.
        bins: ``G``, an integer ``>= 1``.
        valid: optional bool ``[..., L]``; only these steps are checked (padding may hold
            anything: it is put in a bin in range).

    Returns:
        int64 ``[..., L]`` in ``0 .. bins-1``.

    Raises:
        TypeError, ValueError: a non-integer tensor, mismatched shapes, or a step (a valid one)
            outside ``0 .. episode_length - 1``.
    """
    for name, value in (("step", step), ("episode_length", episode_length)):
        integer = isinstance(value, Tensor) and not (value.is_floating_point() or value.is_complex())
        if not integer or value.dtype == torch.bool:
            raise TypeError(f"{name} must be an integer tensor, got {getattr(value, 'dtype', type(value).__name__)}.")
    if step.shape != episode_length.shape or (valid is not None and valid.shape != step.shape):
        shapes = [tuple(t.shape) for t in (step, episode_length, *([] if valid is None else [valid]))]
        raise ValueError(f"step, episode_length (and valid) must have the same shape, got {shapes}.")
    step, length = step.long(), episode_length.long()
    bad = (step < 0) | (step >= length)
    if valid is not None:
        bad = bad & valid
    if bad.any():
        first = tuple(int(i) for i in bad.nonzero()[0])
        raise ValueError(
            f"{int(bad.sum())} steps lie outside their episode (0 <= step < episode_length fails; first at "
            f"{first}: step {int(step[first])}, episode_length {int(length[first])})."
        )
    return torch.div(step * bins, length.clamp_min(1), rounding_mode="floor").clamp(0, bins - 1)


def dro_time_weights(
    losses: Tensor,
    valid: Tensor,
    time_bin: Tensor,
    log_q: Tensor,
    *,
    eta: float = DROTimeParams.dro_eta,
    mix: float | Tensor = 1.0,
    reduce=None,
) -> tuple[Tensor, Tensor]:
    """Group DRO over bins of normalised episode time: one online step, then the weights.

    Follows Sagawa, Koh, Hashimoto and Liang, "Distributionally Robust Neural Networks for Group
    Shifts" (ICLR 2020), whose online algorithm keeps a distribution ``q`` over groups, moves it
    towards the groups of high loss by an exponentiated-gradient step each batch and weights each
    example by its group's ``q``. Here the groups are ``G`` bins of normalised episode time
    (:func:`time_bins`), so the objective up-weights the phases of the demonstrations that the
    policy fits worst. Each call, on the batch's valid steps:

    1. ``q_g <- q_g * exp(eta * Lbar_g / Lbar)`` for every bin ``g`` with a valid step, ``Lbar_g``
       the bin's mean loss and ``Lbar`` the batch's; a bin without one is not multiplied; then
       ``q`` is renormalised to sum 1. Kept as ``log q`` (renormalised with ``logsumexp``), so it
       never underflows.
    2. A step ``t`` of a segment gets ``G * q_g(t)`` normalised to unit mean over the segment's
       valid steps, i.e. ``M * softmax(log q[bin(t)])`` over its ``M`` valid steps, blended with
       uniform by ``mix``.

    The one deviation from Sagawa et al.: the exponent divides the bin's mean loss by the batch's
    (their step uses the loss itself), which makes the update scale-free, as ``tilted`` is, so that
    one ``eta`` means the same on heads whose losses differ by orders of magnitude.

    Args:
        losses: ``[..., L]`` per-step losses, ``>= 0`` at valid steps.
        valid: ``[..., L]`` bool mask.
        time_bin: integer ``[..., L]``, each step's bin in ``0 .. G-1`` (:func:`time_bins`).
        log_q: ``[G]`` floating, the log group weights before this batch (``logsumexp`` 0); not
            modified. Start from ``-log G`` everywhere (uniform).

    Keyword Args:
        eta: the step size, a finite number ``> 0``. Default ``0.01`` (Sagawa et al.'s).
        mix: the schedule's alpha in ``[0, 1]``; ``0`` gives uniform weights (``q`` moves anyway).
        reduce: ``None``, or a function summing a ``[2, G]`` tensor over the ranks of a distributed
            job (the per-bin loss sums and valid counts), so that every rank takes the same step.

    Returns:
        ``(weights, new_log_q)``: the weights as described in :mod:`~tar_rl.objectives.baselines`
        (uniform in a segment whose valid steps share one bin), and the updated ``[G]`` log group
        weights in ``log_q``'s dtype.
    """
    if not (isinstance(log_q, Tensor) and log_q.is_floating_point() and log_q.ndim == 1 and log_q.numel() >= 1):
        raise ValueError(f"log_q must be a [G] floating tensor, got {getattr(log_q, 'shape', type(log_q).__name__)}.")
    params = DROTimeParams(dro_eta=eta, dro_bins=log_q.shape[0])
    check_step_losses(losses, valid)
    if not isinstance(time_bin, Tensor) or time_bin.is_floating_point() or time_bin.shape != losses.shape:
        raise ValueError(f"time_bin must be an integer tensor shaped like losses {tuple(losses.shape)}.")
    time_bin = time_bin.long()
    if (valid & ((time_bin < 0) | (time_bin >= params.dro_bins))).any():
        raise ValueError(f"time_bin must lie in 0 .. {params.dro_bins - 1} at the valid steps.")
    time_bin = time_bin.clamp(0, params.dro_bins - 1)
    return _dro_time(losses, valid, time_bin, log_q, params.dro_eta, mix, reduce)


# ---------------------------------------------------------------------------------------------
# Registration: (losses, valid, params, mix, generator, **inputs) -> weights (see Weighting)
# ---------------------------------------------------------------------------------------------


def _tilted_registered(losses, valid, params, mix, generator):
    check_step_losses(losses, valid)
    x, m, n_valid = _prepare(losses, valid)
    _check_nonnegative(x, valid, "tilted")
    return _finish(_tilted(x, valid, m, n_valid, params.tilt), m, mix, losses.dtype)


def _truncate_registered(losses, valid, params, mix, generator):
    check_step_losses(losses, valid)
    x, m, n_valid = _prepare(losses, valid)
    return _finish(_truncate(x, valid, m, n_valid, params.truncate_fraction), m, mix, losses.dtype)


def _keyframe_registered(losses, valid, params, mix, generator):
    check_step_losses(losses, valid)
    x, m, n_valid = _prepare(losses, valid)
    w = _keyframe(x, valid, m, n_valid, params.keyframe_fraction, params.keyframe_factor)
    return _finish(w, m, mix, losses.dtype)


def _focal_registered(losses, valid, params, mix, generator):
    check_step_losses(losses, valid)
    x, m, n_valid = _prepare(losses, valid)
    _check_nonnegative(x, valid, "focal")
    w = mix_uniform(_focal(x, valid, m, n_valid, params.focal_beta), m, mix)
    return cap_exact(w * m, m, n_valid, params.w_max).to(losses.dtype)


def _dro_time_registered(losses, valid, params, mix, generator, *, step, episode_length, state, reduce=None):
    check_step_losses(losses, valid)
    time_bin = time_bins(step, episode_length, params.dro_bins, valid)
    return _dro_time(losses, valid, time_bin, state, params.dro_eta, mix, reduce)


def _dro_time_initial_state(params: DROTimeParams) -> Tensor:
    """Uniform group weights, as ``log q`` (float64: ``[G]`` numbers, kept exactly over a long run)."""
    return torch.full((params.dro_bins,), -math.log(params.dro_bins), dtype=torch.float64)


for _w in (
    Weighting(
        "tilted",
        _tilted_registered,
        TiltedParams,
        summary="tilted empirical risk over a segment's steps, M * softmax(t * l / mean l) (Li et al. 2021)",
    ),
    Weighting(
        "truncate",
        _truncate_registered,
        TruncateParams,
        summary="loss truncation: a segment's top fraction q of steps by loss weigh 0 (Kang and Hashimoto 2020)",
    ),
    Weighting(
        "keyframe",
        _keyframe_registered,
        KeyframeParams,
        summary="a segment's top fraction f of steps by loss weigh K times the others (after Wen et al. 2021)",
    ),
    Weighting(
        "focal",
        _focal_registered,
        FocalParams,
        summary="(l / mean l) ** beta, unit mean, exact cap at w_max (focal weighting for regression)",
    ),
    Weighting(
        "dro_time",
        _dro_time_registered,
        DROTimeParams,
        reads_time=True,
        initial_state=_dro_time_initial_state,
        summary="group DRO over ten bins of normalised episode time (Sagawa et al., ICLR 2020)",
    ),
):
    WEIGHTINGS.register(_w.name, _w)
