"""The time axis TAR weights, and the reduction over it: one code path for every base policy.

A base policy's training loss is a per-element loss ``[N, H, A]`` over its action chunk (``H`` entries of ``A``
action dims) with the chunk's validity ``[N, H]`` (``True`` = a real entry, ``False`` = padding past the episode's
end), plus, for ACT, a per-item regulariser ``[N]`` (the VAE's KL term). From it:

* ``segment`` mode (the paper): a dataset item holds ``L`` consecutive observation steps, each with its own chunk;
  :func:`fold_segments` turns a batch of ``B`` items into ``N = B * L`` items of the base policy's own shapes, and a
  step's loss is the mean of its element losses over its valid chunk entries and the action dims. TAR weights the
  ``L`` steps of each item (a step is real while its current action is inside the episode).
* ``chunk`` mode: ``N = B`` and TAR weights the ``H`` entries of each chunk (each the mean over the action dims),
  a reinterpretation of the paper's time axis that costs nothing extra.

TAR's weights rank the steps by their losses or, for a sampled loss, by a ranking signal of the same draw
(``policy.tar.signal``, :func:`ranking_signal`); either way they weight the losses. The item's loss is the
TAR-weighted mean over its valid steps plus the mean of the regulariser over them: the regulariser is not an
imitation loss and is not reweighted. Items come back as ``[B]``, so LeRobot's own sample
weights (``reduction="none"``) multiply them as they multiply any policy's per-sample loss. Beside it the reduction
gives the same items' uniform loss (every valid step weighted 1) and the weights' effective sample size, so a run's
log compares with the base policy's.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from .tar_source import check_finite, tar_weights

__all__ = [
    "ElementLosses",
    "TARReduction",
    "effective_sample_size",
    "fold_segments",
    "ranking_signal",
    "reduce_over_time",
]


@dataclass(frozen=True)
class ElementLosses:
    """A base policy's unreduced training loss.

    Attributes:
        loss: ``[N, H, A]`` per-element loss (action chunk entries x action dims).
        valid: ``[N, H]`` bool, ``True`` on real chunk entries, ``False`` on padding.
        extra: ``[N]`` per-item regulariser added unweighted (ACT's weighted KL term), or ``None``.
        terms: ``[N]`` per-item unweighted terms the base policy logs besides its loss, by the base policy's name
            for them (ACT: ``kld_loss``, its KL divergence before ``kl_weight``); the policy logs their mean over
            the real steps.
        action_error: ``[N, H, A]`` for a sampled loss (diffusion, flow matching): the squared error of the action
            chunk the prediction implies at the same draw, per element, detached; ``None`` otherwise.
        quantile: ``[N]`` for a sampled loss: each item's drawn time (noise level) as its quantile in ``[0, 1]``
            under the distribution it is drawn from; ``None`` otherwise.
    """

    loss: Tensor
    valid: Tensor
    extra: Tensor | None = None
    terms: dict[str, Tensor] = field(default_factory=dict)
    action_error: Tensor | None = None
    quantile: Tensor | None = None


@dataclass(frozen=True)
class TARReduction:
    """What :func:`reduce_over_time` returns.

    Attributes:
        per_item: ``[B]`` loss per dataset item (a segment or a chunk).
        uniform: ``[B]`` the same items' loss with uniform weights (every valid step 1): the base policy's
            reduction over time.
        losses: ``[B, T]`` the per-step losses TAR weighted (detached).
        valid: ``[B, T]`` bool, ``True`` on real steps.
        weights: ``[B, T]`` TAR's weights (``0`` on padding, mean ``1`` over the valid steps of an item).
    """

    per_item: Tensor
    uniform: Tensor
    losses: Tensor
    valid: Tensor
    weights: Tensor


def _windows(x: Tensor, slice_len: int, size: int, keep_axis: bool) -> Tensor:
    """``[B, slice_len + size - 1, ...]`` -> ``[B * slice_len, size, ...]`` (step ``t`` reads ``x[:, t : t + size]``);
    without ``keep_axis`` (``size == 1``) the window axis is dropped: ``[B * slice_len, ...]``."""
    stacked = torch.stack([x[:, t : t + size] for t in range(slice_len)], dim=1)
    folded = stacked.reshape(x.shape[0] * slice_len, size, *x.shape[2:])
    return folded if keep_axis else folded.squeeze(1)


def fold_segments(
    batch: dict[str, Any],
    *,
    slice_len: int,
    observation_keys: list[str],
    observation_window: int | None,
    action_window: int,
    action_offset: int,
) -> tuple[dict[str, Any], Tensor]:
    """Fold a batch of segments into the base policy's batch of single steps.

    Args:
        batch: a preprocessed batch of ``B`` items; the keys in ``observation_keys`` (and their ``*_is_pad``) hold
            ``[B, slice_len + observation_window - 1, ...]``, ``action``/``action_is_pad``
            ``[B, slice_len + action_window - 1, ...]``; every other tensor with ``B`` rows and every list of ``B``
            entries (the task strings) is per item and repeated for each step.

    Keyword Args:
        slice_len: ``L``, the steps of a segment.
        observation_keys: the observation features with a time axis.
        observation_window: the observation steps the base policy reads per step (its ``n_obs_steps``), or ``None``
            for a base policy that reads one step without a time axis (ACT, pi0, pi0.5).
        action_window: ``H``, the base policy's chunk length.
        action_offset: the index of step ``t``'s current action in its chunk window (``-min(action deltas)``).

    Returns:
        The folded batch (``B * L`` items, step-major within an item) and ``valid`` ``[B, L]``: ``True`` where the
        step's current action is inside the episode.
    """
    action = batch["action"]
    size, length = action.shape[0], action.shape[1]
    if length != slice_len + action_window - 1:
        raise ValueError(
            f"a segment batch needs {slice_len + action_window - 1} actions per item (slice_len {slice_len}, chunk "
            f"{action_window}), got {length}: the dataset's delta timestamps are not this policy's."
        )
    obs_size = observation_window or 1
    folded: dict[str, Any] = {}
    for key, value in batch.items():
        base_key = key.removesuffix("_is_pad")
        if base_key in observation_keys:
            folded[key] = _windows(value, slice_len, obs_size, keep_axis=observation_window is not None)
        elif base_key == "action":
            folded[key] = _windows(value, slice_len, action_window, keep_axis=True)
        elif isinstance(value, Tensor) and value.ndim > 0 and value.shape[0] == size:
            folded[key] = value.repeat_interleave(slice_len, dim=0)
        elif isinstance(value, list) and len(value) == size:
            folded[key] = [entry for entry in value for _ in range(slice_len)]
        else:
            folded[key] = value
    is_pad = batch.get("action_is_pad")
    if is_pad is None:
        valid = torch.ones(size, slice_len, dtype=torch.bool, device=action.device)
    else:
        valid = ~is_pad[:, action_offset : action_offset + slice_len]
    return folded, valid


def _steps(values: Tensor, valid_entry: Tensor, segments: Tensor | None) -> Tensor:
    """``[N, H, A]`` element values -> ``[B, T]`` per-step values: the mean over the action dims, then (``segment``
    mode) over the step's valid chunk entries; 0 on padded entries."""
    entry = values.mean(-1)  # [N, H]: mean over the action dims
    entry = torch.where(valid_entry, entry, torch.zeros((), dtype=entry.dtype, device=entry.device))
    if segments is None:
        return entry
    step = entry.sum(-1) / valid_entry.sum(-1).clamp_min(1)  # [N]: mean over the step's valid chunk entries
    return step.reshape(segments.shape)


def ranking_signal(
    element: ElementLosses,
    losses: Tensor,
    valid: Tensor,
    *,
    signal: str,
    segments: Tensor | None,
    normalizer: Callable[..., Tensor] | None = None,
    update: bool = False,
) -> Tensor:
    """What TAR ranks the ``[B, T]`` steps by (``policy.tar.signal``), detached: the per-step ``losses``
    (``loss``); the per-step mean of ``element.action_error`` (``action_error``); or the losses over
    ``normalizer``'s running mean at each step's draw (``time_normalized``: tar-rl's ``TimeNormalizer`` called on
    the losses, ``element.quantile`` per step, ``valid`` and ``update``, which keeps its update).

    A signal that is NaN or inf at a valid step is refused as a non-finite loss is: a ``ValueError`` naming the
    signal and the first such step.
    """
    losses = losses.detach()
    if signal == "loss":
        return losses
    check_finite(losses, valid, "step")
    if signal == "action_error":
        if element.action_error is None:
            raise ValueError("the policy's element losses carry no action_error for policy.tar.signal='action_error'")
        scores = _steps(element.action_error.detach(), element.valid, segments)
    elif signal == "time_normalized":
        if element.quantile is None or normalizer is None:
            raise ValueError("policy.tar.signal='time_normalized' needs the draws' quantiles and a normalizer")
        quantile = element.quantile.detach()  # [N]: a segment's L items are its steps; a chunk's entries share one
        position = quantile[:, None].expand(losses.shape) if segments is None else quantile.reshape(losses.shape)
        scores = normalizer(losses, position, valid, update)
    else:
        raise ValueError(f"unknown ranking signal {signal!r}")
    check_finite(scores, valid, "step", f"ranking signal {signal!r}")
    return scores


def reduce_over_time(
    element: ElementLosses,
    *,
    segments: Tensor | None,
    gamma: float,
    w_max: float,
    eps: float,
    cap: str,
    mix: float | Tensor,
    signal: str = "loss",
    normalizer: Callable[..., Tensor] | None = None,
    update: bool = False,
) -> TARReduction:
    """TAR over the time axis: ``[B]`` losses from a base policy's element losses.

    Args:
        element: the base policy's element losses over ``N`` items.

    Keyword Args:
        segments: ``valid`` ``[B, L]`` from :func:`fold_segments` (``segment`` mode; ``N = B * L``) or ``None``
            (``chunk`` mode: the time axis is the chunk, ``N = B``).
        gamma, w_max, eps, cap, mix: TAR's settings and the schedule's mixing weight (``tar_weights``).
        signal, normalizer, update: what the weights rank the steps by (:func:`ranking_signal`); they weight the
            losses whatever it is.
    """
    valid_entry = element.valid
    losses = _steps(element.loss, valid_entry, segments)
    if segments is None:
        valid = valid_entry
    else:
        valid = segments & (valid_entry.sum(-1) > 0).reshape(segments.shape)
    scores = ranking_signal(
        element, losses, valid, signal=signal, segments=segments, normalizer=normalizer, update=update
    )
    weights = tar_weights(scores, valid, gamma=gamma, w_max=w_max, eps=eps, cap=cap, mix=mix)
    n_valid = valid.sum(-1).clamp_min(1)
    per_item = (weights * losses).sum(-1) / n_valid
    uniform = (valid * losses).sum(-1) / n_valid
    if element.extra is not None:
        extra = element.extra if segments is None else element.extra.reshape(segments.shape)
        extra = extra if segments is None else (extra * valid).sum(-1) / n_valid
        per_item = per_item + extra
        uniform = uniform + extra
    return TARReduction(per_item=per_item, uniform=uniform, losses=losses.detach(), valid=valid, weights=weights)


def effective_sample_size(weights: Tensor, valid: Tensor) -> Tensor:
    """The mean over items with a valid step of ``(sum w)^2 / (M sum w^2)`` over their ``M`` valid steps: 1 for
    uniform weights, ``1 / M`` when one step takes all the weight (tar-rl's ``weight_ess``)."""
    m = valid.to(weights.dtype)
    n_valid = m.sum(-1)
    square_sum = (weights.square() * m).sum(-1)
    ess = (weights * m).sum(-1).square() / (n_valid * square_sum).clamp_min(torch.finfo(weights.dtype).tiny)
    nonempty = n_valid > 0
    return (ess * nonempty).sum() / nonempty.sum().clamp_min(1)
