"""TAR's per-step weights, paper Eqs. 3-8, readable top to bottom; imports torch only.

Shapes and the mask, for every function here and every weighting of the package:

* ``losses``: floating tensor ``[..., L]``, the per-step losses of segments of length ``L``
  (any leading batch dimensions).
* ``valid``: ``torch.bool`` tensor of the same shape, ``True`` on real steps and ``False`` on
  padding. This is the only mask polarity used in tar-rl; it is TorchRL's
  ``("collector", "mask")`` as written by ``SliceSampler(pad_output=True)``.
* the weights: same shape and dtype as ``losses``, ``0`` on padding, mean ``1`` over the
  valid steps of every segment that has one, all ``0`` in a segment that has none.

Nothing is differentiated through the weights (the losses are detached first, the paper's
stop-gradient of Eq. 3). Half-precision losses are weighted in float32 and the weights cast back,
so AMP runs see the same weights as full-precision runs up to the final rounding.

The building blocks (Eqs. 4-8, the mixing) are shared with the controls
(:mod:`~tar_rl.objectives.weighting`), the baselines and the element variants; they assume checked
inputs and detached losses, and the package does not export them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

from .checks import check_step_losses

__all__ = ["CAP_MODES", "DEFAULT_EPS", "DEFAULT_GAMMA", "DEFAULT_W_MAX", "TARParams", "tar_weights"]

#: Softmax temperature on the within-segment z-scores (Eq. 6). With ``gamma=1`` a step one
#: standard deviation above the segment mean gets ``e`` times the weight of an average step.
DEFAULT_GAMMA = 1.0
#: Cap on a single step's weight, in units of the segment's mean weight (Eq. 8).
DEFAULT_W_MAX = 3.0
#: Added to the segment's standard deviation before dividing (Eq. 5). Per-step imitation
#: losses of a trained policy are ~1e-3..1e-1 with spreads of the same order, so 1e-8 leaves
#: the z-scores untouched there and only matters when a segment's losses are all equal.
DEFAULT_EPS = 1e-8

CapMode = Literal["paper", "exact"]
CAP_MODES: tuple[str, ...] = ("paper", "exact")

#: Dtypes weighted in float32, the weights cast back.
HALF_DTYPES = (torch.float16, torch.bfloat16)


def check_tar_params(*, gamma: float, w_max: float, eps: float, cap: CapMode) -> None:
    """Raise a ``ValueError`` naming the first of TAR's hyper-parameters that is out of range."""
    if not (isinstance(gamma, (int, float)) and math.isfinite(gamma) and gamma > 0):
        raise ValueError(f"gamma must be a finite number > 0, got {gamma!r}.")
    if not isinstance(w_max, (int, float)):
        raise ValueError(f"w_max must be a number >= 1 (math.inf for no cap), got {w_max!r}.")
    if not w_max >= 1:  # one rule for both caps (NaN included): a cap below the mean weight cannot hold
        raise ValueError(
            f"w_max >= 1 is needed (weights of mean 1 cannot all lie below a smaller cap: cap='paper' renormalises "
            f"them above it, cap='exact' cannot reach it), got {w_max!r}; use a number >= 1 (math.inf for no cap)"
        )
    if not (isinstance(eps, (int, float)) and math.isfinite(eps) and eps > 0):
        raise ValueError(f"eps must be a finite number > 0, got {eps!r}.")
    if cap not in CAP_MODES:
        raise ValueError(f"cap must be one of {list(CAP_MODES)}, got {cap!r}.")


@dataclass(frozen=True)
class TARParams:
    """TAR's hyper-parameters (Eqs. 5-8), checked when built; also those of TAR's controls (``shuffle``,
    ``random``, ``invert``) and of ``tar_dimnorm``.

    Attributes:
        gamma: softmax temperature on the z-scores (Eq. 6), a finite number ``> 0``. Default ``1.0``.
        w_max: cap on a step's weight (Eq. 8), ``>= 1`` with either cap (weights of mean 1 cannot all lie
            below a smaller cap); ``math.inf`` disables the cap. Default ``3.0``.
        eps: stabiliser added to the standard deviation (Eq. 5), a finite number ``> 0``. Default ``1e-8``.
        cap: ``"paper"`` clips once and renormalises (Eq. 8 as printed: after it a weight may end above
            ``w_max``); ``"exact"`` finds the unit-mean weights ``min(c * w, w_max)`` for which the cap
            holds exactly. Default ``"paper"``.
    """

    gamma: float = DEFAULT_GAMMA
    w_max: float = DEFAULT_W_MAX
    eps: float = DEFAULT_EPS
    cap: CapMode = "paper"

    def __post_init__(self) -> None:
        check_tar_params(gamma=self.gamma, w_max=self.w_max, eps=self.eps, cap=self.cap)

    def tar_kwargs(self) -> dict:
        """TAR's four hyper-parameters as keyword arguments of :func:`tar_weights`."""
        return {"gamma": self.gamma, "w_max": self.w_max, "eps": self.eps, "cap": self.cap}


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


def mix_uniform(w: Tensor, m: Tensor, mix: float | Tensor) -> Tensor:
    """The schedule's blend ``(1 - mix) * uniform + mix * w`` (Sec. III-B), for every weighting.

    ``m`` is the float mask of valid steps (the uniform weights); ``mix == 1`` returns ``w``.
    A weighting with a cap applies it after the blend, as TAR does.
    """
    if isinstance(mix, (int, float)) and mix == 1:
        return w
    return (1 - mix) * m + mix * w


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


def weights_from_scores(
    scores_input: Tensor, valid: Tensor, *, gamma: float, w_max: float, eps: float, cap: CapMode, mix: float | Tensor
) -> Tensor:
    """Eqs. 4-8 plus the schedule's mixing, on already detached and checked inputs and hyper-parameters (for
    weightings that score steps by something other than their loss; not exported)."""
    dtype = scores_input.dtype
    x = scores_input.float() if dtype in HALF_DTYPES else scores_input
    m = valid.to(x.dtype)
    x = torch.where(valid, x, torch.zeros((), dtype=x.dtype, device=x.device))  # padding may hold NaN
    n_valid = m.sum(-1, keepdim=True)
    count = n_valid.clamp_min(1)
    scores = _zscores(x, m, count, eps)  # Eqs. 4-5
    w = unit_mean_softmax(scores, valid, m, n_valid, gamma)  # Eqs. 6-7
    w = mix_uniform(w, m, mix)  # the schedule's alpha, applied before the cap (Sec. III-B)
    cap_fn = cap_exact if cap == "exact" else _cap_paper
    w = cap_fn(w, m, n_valid, w_max)  # Eq. 8
    return w.to(dtype)


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
        w_max: cap on a weight, ``>= 1`` (``math.inf``: none). Default ``3.0``.
        eps: added to the std, ``> 0``. Default ``1e-8``.
        mix: alpha in ``[0, 1]`` (float or 0-d tensor): ``0`` gives uniform weights, ``1`` full TAR.
        cap: ``"paper"`` (clip once, renormalise; weights may end above ``w_max``)
            or ``"exact"`` (the cap holds exactly).

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
    check_tar_params(gamma=gamma, w_max=w_max, eps=eps, cap=cap)
    check_step_losses(losses, valid)
    return weights_from_scores(losses.detach(), valid, gamma=gamma, w_max=w_max, eps=eps, cap=cap, mix=mix)
