"""Per-step weightings of segment losses: TAR (paper Eqs. 3-8) and its control variants.

The baselines from the literature (tilted, truncate, keyframe, focal, dro_time) live in
:mod:`~tar_rl.objectives.baselines` and share this module's conventions, parameters and registry.

Every function here is pure: it reads ``losses`` and ``valid`` and returns a new tensor of
weights. Nothing is differentiated through the weights (the losses are detached first, the
paper's stop-gradient of Eq. 3).

Shapes and the mask, for every function in this module:

* ``losses``: floating tensor ``[..., L]``, the per-step losses of segments of length ``L``
  (any leading batch dimensions).
* ``valid``: ``torch.bool`` tensor of the same shape, ``True`` on real steps and ``False`` on
  padding. This is the only mask polarity used in tar-rl; it is TorchRL's
  ``("collector", "mask")`` as written by ``SliceSampler(pad_output=True)``.
* the weights: same shape and dtype as ``losses``, ``0`` on padding, mean ``1`` over the
  valid steps of every segment that has one, all ``0`` in a segment that has none.

Half-precision losses are weighted in float32 and the weights cast back, so AMP runs see the
same weights as full-precision runs up to the final rounding.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

from tar_rl.registry import Registry

__all__ = [
    "CAP_MODES",
    "DEFAULT_DRO_BINS",
    "DEFAULT_DRO_ETA",
    "DEFAULT_EPS",
    "DEFAULT_FOCAL_BETA",
    "DEFAULT_GAMMA",
    "DEFAULT_GRIPPER_DIMS",
    "DEFAULT_KEYFRAME_FACTOR",
    "DEFAULT_KEYFRAME_FRACTION",
    "DEFAULT_TILT",
    "DEFAULT_TRUNCATE_FRACTION",
    "DEFAULT_W_MAX",
    "WEIGHTINGS",
    "Weighting",
    "WeightingParams",
    "check_step_losses",
    "get_weighting",
    "invert_weights",
    "perturb_mask",
    "random_weights",
    "shuffle_weights",
    "tar_weights",
    "uniform_weights",
    "window_weights",
]

#: Softmax temperature on the within-segment z-scores (Eq. 6). With ``gamma=1`` a step one
#: standard deviation above the segment mean gets ``e`` times the weight of an average step.
DEFAULT_GAMMA = 1.0
#: Cap on a single step's weight, in units of the segment's mean weight (Eq. 8).
DEFAULT_W_MAX = 3.0
#: The smallest cap ``cap="paper"`` renormalises to finite weights: the smallest normal float32 (weights are
#: computed in float32 at least). Clipping every weight at a smaller ``w_max`` and rescaling to unit mean
#: multiplies by ``1 / w_max``, which overflows float32.
MIN_W_MAX = float(torch.finfo(torch.float32).tiny)
#: Added to the segment's standard deviation before dividing (Eq. 5). Per-step imitation
#: losses of a trained policy are ~1e-3..1e-1 with spreads of the same order, so 1e-8 leaves
#: the z-scores untouched there and only matters when a segment's losses are all equal.
DEFAULT_EPS = 1e-8
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

CapMode = Literal["paper", "exact"]
CAP_MODES: tuple[str, ...] = ("paper", "exact")

#: Dtypes weighted in float32, the weights cast back.
HALF_DTYPES = (torch.float16, torch.bfloat16)


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
        if not (isinstance(self.gamma, (int, float)) and math.isfinite(self.gamma) and self.gamma > 0):
            raise ValueError(f"gamma must be a finite number > 0, got {self.gamma!r}.")
        if not (isinstance(self.w_max, (int, float)) and self.w_max > 0):
            raise ValueError(f"w_max must be a number > 0 (math.inf for no cap), got {self.w_max!r}.")
        if not (isinstance(self.eps, (int, float)) and math.isfinite(self.eps) and self.eps > 0):
            raise ValueError(f"eps must be a finite number > 0, got {self.eps!r}.")
        if self.cap not in CAP_MODES:
            raise ValueError(f"cap must be one of {CAP_MODES}, got {self.cap!r}.")
        if self.cap == "exact" and self.w_max < 1:
            raise ValueError(
                f"cap='exact' needs w_max >= 1 (weights of mean 1 cannot all be below 1), got {self.w_max!r}."
            )
        if self.w_max < MIN_W_MAX:
            raise ValueError(
                f"w_max must be >= {MIN_W_MAX:.4g} (the smallest normal float32: renormalising weights clipped at a "
                f"smaller cap overflows to inf), got {self.w_max!r}."
            )
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


def check_finite(losses: Tensor, valid: Tensor, what: str) -> None:
    """Raise a ``ValueError`` if a loss where ``valid`` is ``True`` is NaN or inf (``what``: ``step`` or
    ``element``, for the message). Under ``torch.compile`` the check is an in-graph assertion with the same
    message, so compiled code needs no graph break."""
    bad = valid & ~torch.isfinite(losses.detach())
    message = f"non-finite per-{what} loss at a valid {what}: the weights would be NaN."
    if torch.compiler.is_compiling():
        torch._assert_async(~bad.any(), message)
        return
    if bad.any():
        first = tuple(int(i) for i in bad.nonzero()[0])
        raise ValueError(
            f"{message} {int(bad.sum())} of {int(valid.sum())} valid {what}s are NaN or inf "
            f"(first at index {first}, value {losses.detach()[first].item()})."
        )


# ---------------------------------------------------------------------------------------------
# Building blocks of Eqs. 4-8, shared with the baselines (``baselines.py``). They assume checked
# inputs and detached losses; the package does not export them.
# ---------------------------------------------------------------------------------------------


def _zscores(x: Tensor, m: Tensor, count: Tensor, eps: float) -> Tensor:
    """Eqs. 4-5: masked mean, population std and z-score; ``0`` on padding."""
    mu = x.sum(-1, keepdim=True) / count
    dev = (x - mu) * m
    sigma = (dev.square().sum(-1, keepdim=True) / count).sqrt()
    return dev / (sigma + eps)


def unit_mean_softmax(scores: Tensor, valid: Tensor, m: Tensor, n_valid: Tensor, gamma: float) -> Tensor:
    """Eqs. 6-7: masked softmax of ``gamma * scores`` times the number of valid steps."""
    # The lowest finite value (not -inf) keeps a segment without valid steps finite: its
    # softmax is uniform and the mask then zeroes it.
    logits = (gamma * scores).masked_fill(~valid, torch.finfo(scores.dtype).min)
    return n_valid * torch.softmax(logits, dim=-1) * m


def _cap_paper(w: Tensor, m: Tensor, n_valid: Tensor, w_max: float) -> Tensor:
    """Eq. 8: clip at ``w_max`` once, then rescale to unit mean over the valid steps."""
    if math.isinf(w_max):
        return w
    clipped = w.clamp_max(w_max)
    total = clipped.sum(-1, keepdim=True)
    return clipped * (n_valid / total.clamp_min(torch.finfo(w.dtype).tiny)) * m


def cap_exact(w: Tensor, m: Tensor, n_valid: Tensor, w_max: float) -> Tensor:
    """Unit-mean weights ``min(c * w, w_max)`` with the cap holding exactly (``w_max >= 1``).

    Water-filling: with the valid weights sorted in decreasing order ``v_0 >= v_1 >= ...``,
    clipping the first ``k`` at ``w_max`` leaves the scale ``c_k = (M - k w_max) / S_k``
    (``S_k`` the sum of the rest) for the others; the answer is the smallest ``k`` whose
    largest unclipped weight stays under the cap, ``c_k v_k <= w_max``. If the positive
    weights cannot carry the mass (softmax underflow at huge ``gamma``), they take ``w_max``
    and the zero-weight steps share the rest equally: the limit of adding a vanishing constant
    to every weight. One sort, no loop over iterations.
    """
    if math.isinf(w_max):
        return w
    size = w.shape[-1]
    v, _ = torch.sort(w, dim=-1, descending=True)  # padding holds 0 and sorts last
    suffix = v.flip(-1).cumsum(-1).flip(-1)  # suffix[k] = sum_{j >= k} v_j
    k = torch.arange(size, device=w.device, dtype=w.dtype)
    mass = n_valid - k * w_max  # what the unclipped steps must carry
    scale = mass / suffix.clamp_min(torch.finfo(w.dtype).tiny)
    fits = (suffix > 0) & (mass > 0) & (scale * v <= w_max * (1 + 1e-6)) & (k < n_valid)
    found = fits.any(-1, keepdim=True)
    first = fits.to(torch.int8).argmax(-1, keepdim=True)  # first k that fits
    c = scale.gather(-1, first)
    capped = torch.minimum(c * w, torch.full_like(w, w_max))
    # Fallback (no k fits): positives at the cap, zeros share the remaining mass equally.
    positive = (w > 0).to(w.dtype) * m
    n_pos = positive.sum(-1, keepdim=True)
    share = (n_valid - n_pos * w_max) / (n_valid - n_pos).clamp_min(1)
    fallback = positive * w_max + (m - positive) * share
    return torch.where(found, capped, fallback) * m


def mix_uniform(w: Tensor, m: Tensor, mix: float | Tensor) -> Tensor:
    """The schedule's blend ``(1 - mix) * uniform + mix * w`` (Sec. III-B), for every weighting.

    ``m`` is the float mask of valid steps (the uniform weights); ``mix == 1`` returns ``w``.
    A weighting with a cap applies it after the blend, as TAR does.
    """
    if isinstance(mix, (int, float)) and mix == 1:
        return w
    return (1 - mix) * m + mix * w


def weights_from_scores(scores_input: Tensor, valid: Tensor, params: WeightingParams, mix: float | Tensor) -> Tensor:
    """Eqs. 4-8 plus the schedule's mixing, on already detached and checked inputs (for weightings that score
    steps by something other than their loss; not exported)."""
    dtype = scores_input.dtype
    x = scores_input.float() if dtype in HALF_DTYPES else scores_input
    m = valid.to(x.dtype)
    x = torch.where(valid, x, torch.zeros((), dtype=x.dtype, device=x.device))  # padding may hold NaN
    n_valid = m.sum(-1, keepdim=True)
    count = n_valid.clamp_min(1)
    scores = _zscores(x, m, count, params.eps)
    w = unit_mean_softmax(scores, valid, m, n_valid, params.gamma)
    w = mix_uniform(w, m, mix)  # the schedule's alpha, applied before the cap (Sec. III-B)
    cap = cap_exact if params.cap == "exact" else _cap_paper
    w = cap(w, m, n_valid, params.w_max)
    return w.to(dtype)


def _rand_like(x: Tensor, generator: torch.Generator | None, normal: bool) -> Tensor:
    """Random numbers shaped like ``x``, drawn on the generator's device, moved to ``x``'s."""
    device = generator.device if generator is not None else x.device
    draw = torch.randn if normal else torch.rand
    return draw(x.shape, generator=generator, device=device, dtype=torch.float32).to(x.device)


# ---------------------------------------------------------------------------------------------
# Public weightings
# ---------------------------------------------------------------------------------------------


def tar_weights(
    losses: Tensor,
    valid: Tensor,
    *,
    gamma: float = DEFAULT_GAMMA,
    w_max: float = DEFAULT_W_MAX,
    eps: float = DEFAULT_EPS,
    mix: float | Tensor = 1.0,
    cap: CapMode = "paper",
) -> Tensor:
    """TAR's per-step weights (paper Eqs. 3-8), one segment per row of the last axis.

    Steps: stop-gradient (Eq. 3); masked mean and population std over the valid steps
    (Eq. 4); z-score ``(l - mu) / (sigma + eps)`` (Eq. 5); masked softmax of ``gamma * s``
    (Eq. 6); unit-mean scaling ``M * p`` (Eq. 7); mixing ``(1 - mix) + mix * w`` with the
    schedule's alpha (Sec. III-B); cap at ``w_max`` and renormalisation to unit mean (Eq. 8).

    Args:
        losses: ``[..., L]`` floating per-step losses. Detached here; no gradient flows
            through the weights.
        valid: ``[..., L]`` bool, ``True`` on real steps, ``False`` on padding.

    Keyword Args:
        gamma: softmax temperature, ``> 0``. Default ``1.0``.
        w_max: cap on a weight, ``> 0`` (``math.inf``: none). Default ``3.0``.
        eps: added to the std, ``> 0``. Default ``1e-8``.
        mix: alpha in ``[0, 1]`` (float or 0-d tensor): ``0`` gives uniform weights, ``1`` full TAR.
        cap: ``"paper"`` (clip once, renormalise; weights may end slightly above ``w_max``)
            or ``"exact"`` (the cap holds exactly; needs ``w_max >= 1``).

    Returns:
        Weights of the shape and dtype of ``losses``: ``>= 0``, ``0`` on padding, mean ``1``
        over the valid steps of each segment; all ``1`` when a segment's losses are equal,
        ``1`` on a lone valid step, all ``0`` in a segment with no valid step.

    Raises:
        TypeError, ValueError: on a non-bool mask, mismatched shapes, bad hyper-parameters,
            or a NaN/inf loss at a valid step.

    Examples:
        >>> import torch
        >>> losses = torch.tensor([[0.0, 0.0, 3.0, 9.0]])
        >>> valid = torch.tensor([[True, True, True, False]])
        >>> w = tar_weights(losses, valid, gamma=1.0, w_max=3.0)
        >>> w[0, 3].item(), round(w[0, :3].mean().item(), 6)
        (0.0, 1.0)
    """
    params = WeightingParams(gamma=gamma, w_max=w_max, eps=eps, cap=cap)
    check_step_losses(losses, valid)
    return weights_from_scores(losses.detach(), valid, params, mix)


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
    return weights_from_scores(-losses.detach(), valid, WeightingParams(**params), mix)


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
    return weights_from_scores(scores, valid, WeightingParams(**params), mix)


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


def _param_kwargs(params: WeightingParams) -> dict:
    return {"gamma": params.gamma, "w_max": params.w_max, "eps": params.eps, "cap": params.cap}


def _uniform(losses, valid, params, mix, generator):
    return uniform_weights(losses, valid)


def _tar(losses, valid, params, mix, generator):
    check_step_losses(losses, valid)
    return weights_from_scores(losses.detach(), valid, params, mix)


def _invert(losses, valid, params, mix, generator):
    return invert_weights(losses, valid, mix=mix, **_param_kwargs(params))


def _random(losses, valid, params, mix, generator):
    return random_weights(losses, valid, mix=mix, generator=generator, **_param_kwargs(params))


def _shuffle(losses, valid, params, mix, generator):
    return shuffle_weights(losses, valid, mix=mix, generator=generator, **_param_kwargs(params))


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
