"""What ``TARLoss`` reads: the batch's validity mask and time entries, and its inner loss's output (the per-step
loss entry, reduced over event dims to ``[B, L]``, and the ranking signal an inner loss may give beside it).

An inner loss (any TorchRL ``LossModule`` built with ``reduction="none"``) returns its per-step loss as
one ``loss_*`` entry shaped like the input's batch ``[B, L]``, then any event dims (action dims, a
chunk's horizon). :class:`~tar_rl.objectives.TARLoss` and
:class:`~tar_rl.objectives.supervision.PerturbedTarget` read it through these functions, so both
reduce the event dims the same way: a plain mean, or the mean over the valid elements of an
``event_valid`` mask (``True`` on real elements).

An inner loss may also return a detached ``[B, L]`` entry, the ranking signal (:data:`SIGNAL`, ``TARLoss``'s
``signal`` key): the weights then rank the steps by it instead of by the loss, which they still weight (e.g. a
flow head's implied action error, whose order within a segment its sampled training time does not decide).
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torch import Tensor

from .checks import check_finite
from .elementwise import element_mean, masked_mean

__all__ = [
    "SIGNAL",
    "checked_loss",
    "dim_losses",
    "element_losses",
    "loss_entry",
    "nonfinite_term",
    "other_entries",
    "read_signal",
    "read_time",
    "read_valid",
    "scored",
    "scores",
    "segment_mean",
    "step_losses",
]


#: The entry of an inner loss's output holding its ranking signal (``TARLoss``'s default ``signal`` key).
SIGNAL = "signal"


def read_valid(tensordict: TensorDictBase, key: NestedKey) -> Tensor:
    """The bool ``[B, L]`` validity mask at ``key`` (``True`` on real steps; all ``True`` when absent), checked;
    a batch of fewer than two dims (not segments) is refused."""
    batch = tensordict.batch_size
    if len(batch) < 2:
        raise ValueError(
            f"TARLoss expects a TensorDict of segments with batch shape [B, L], got {list(batch)}: reshape "
            "the sampler's flat output, e.g. `batch.reshape(-1, slice_len)`."
        )
    valid = tensordict.get(key, None)
    if valid is None:
        return torch.ones(batch, dtype=torch.bool, device=tensordict.device)
    if valid.dtype != torch.bool:
        raise TypeError(f"the validity mask {key!r} must be torch.bool (True on real steps), got {valid.dtype}.")
    while valid.ndim > len(batch) and valid.shape[-1] == 1:
        valid = valid.squeeze(-1)
    if valid.shape != batch:
        raise ValueError(
            f"the validity mask {key!r} has shape {list(valid.shape)}, expected the batch shape {list(batch)}."
        )
    return valid


def read_time(tensordict: TensorDictBase, keys: tuple[NestedKey, ...], weighting: str) -> dict[str, Tensor]:
    """``step`` and ``episode_length`` (integer ``[B, L]``) at ``keys`` for a weighting that reads time; ``{}``
    when ``keys`` is empty."""
    batch = tensordict.batch_size
    inputs = {}
    for name, key in zip(("step", "episode_length"), keys):
        value = tensordict.get(key, None)
        if value is None:
            raise KeyError(
                f"the {weighting} weighting reads each step's position in its episode, but the batch "
                f"has no {key!r} entry (the {name} of every step): sample it with the segments "
                f"(SegmentSampler writes 'episode_length'; the dataset stores 'step'), or say where it is "
                f"with TARLoss.set_keys({name}=...)."
            )
        while value.ndim > len(batch) and value.shape[-1] == 1:
            value = value.squeeze(-1)
        if value.shape != batch or value.is_floating_point() or value.dtype == torch.bool:
            raise ValueError(
                f"the {name} entry {key!r} must be an integer tensor of the batch shape {list(batch)}, "
                f"got {value.dtype} {list(value.shape)}."
            )
        inputs[name] = value
    return inputs


def loss_entry(out: TensorDictBase, loss_key: NestedKey | None) -> NestedKey:
    """The key of the per-step loss in ``out``: ``loss_key`` if given, else its only ``loss_*`` entry."""
    if loss_key is not None:
        if loss_key not in out.keys(True):
            raise KeyError(f"the inner loss returned no {loss_key!r}; it returned {list(out.keys())}.")
        return loss_key
    names = [k for k in out.keys() if isinstance(k, str) and k.startswith("loss")]
    if len(names) != 1:
        raise ValueError(
            f"the inner loss returned {len(names)} loss entries {names}: say which one holds the "
            "per-step loss with TARLoss(..., loss_key=...)."
        )
    return names[0]


def checked_loss(out: TensorDictBase, key: NestedKey, tensordict: TensorDictBase) -> Tensor:
    """The inner loss at ``key``, refused unless its leading dims are the batch shape."""
    loss = out.get(key)
    batch = tensordict.batch_size
    if loss.shape[: len(batch)] != batch:
        raise ValueError(
            f"the inner loss's {key!r} has shape {list(loss.shape)}, but TARLoss needs per-step "
            f"losses shaped like the batch {list(batch)} (then any event dims): build the inner "
            "loss with reduction='none' and do not pass it a pad_mask (which flattens the output)."
        )
    return loss


def _event_mask(loss: Tensor, tensordict: TensorDictBase, event_key: NestedKey) -> Tensor:
    """The ``event_valid`` mask at ``event_key`` broadcast to the loss's shape."""
    event_valid = tensordict.get(event_key)
    if event_valid.dtype != torch.bool or event_valid.shape != loss.shape[: event_valid.ndim]:
        raise ValueError(
            f"the event mask {event_key!r} must be torch.bool with a leading part of the loss's "
            f"shape {list(loss.shape)}, got {event_valid.dtype} {list(event_valid.shape)}."
        )
    event_valid = event_valid.reshape(event_valid.shape + (1,) * (loss.ndim - event_valid.ndim))
    return event_valid.expand_as(loss)


def step_losses(out: TensorDictBase, key: NestedKey, tensordict: TensorDictBase, event_key: NestedKey | None) -> Tensor:
    """The inner per-step loss at ``key`` as ``[B, L]``: trailing event dims averaged away (over the valid
    elements of ``event_key``'s mask when it is given)."""
    loss = checked_loss(out, key, tensordict)
    if loss.ndim == tensordict.batch_dims:
        return loss
    if event_key is None:
        return loss.mean(tuple(range(tensordict.batch_dims, loss.ndim)))
    return element_mean(loss, _event_mask(loss, tensordict, event_key), tensordict.batch_dims)


def dim_losses(
    out: TensorDictBase, key: NestedKey, tensordict: TensorDictBase, event_key: NestedKey | None
) -> Tensor | None:
    """The inner loss at ``key`` per step and action dim ``[*batch, A]``: the mean over the other event dims (over
    the valid entries of ``event_key``'s mask, 0 where a step has none); ``None`` without event dims."""
    loss = checked_loss(out, key, tensordict)
    if loss.ndim == tensordict.batch_dims:
        return None
    axes = tuple(range(tensordict.batch_dims, loss.ndim - 1))  # the event dims but the action dims
    if event_key is None:
        return loss.mean(axes) if axes else loss
    return masked_mean(loss, _event_mask(loss, tensordict, event_key), axes)  # padding may be NaN


def element_losses(
    out: TensorDictBase, key: NestedKey, tensordict: TensorDictBase, event_key: NestedKey | None, weighting: str
) -> tuple[Tensor, Tensor]:
    """The inner per-element loss ``[B, L, *event, A]`` and its event mask (all ``True`` without ``event_key``),
    for the element weighting called ``weighting``."""
    loss = checked_loss(out, key, tensordict)
    if tensordict.batch_dims != 2:
        raise ValueError(
            f"objective {weighting!r} weights per-element losses of a [B, L] batch, got batch shape "
            f"{list(tensordict.batch_size)}: reshape it to [B, L]."
        )
    if loss.ndim == tensordict.batch_dims:
        raise ValueError(
            f"objective {weighting!r} weights per-element losses, but the inner loss's {key!r} has one "
            f"loss per step (shape {list(loss.shape)}): it needs event dims with the action dims last."
        )
    if event_key is None:
        return loss, torch.ones(loss.shape, dtype=torch.bool, device=loss.device)
    return loss, _event_mask(loss, tensordict, event_key)


def read_signal(out: TensorDictBase, key: NestedKey, tensordict: TensorDictBase) -> Tensor | None:
    """The inner output's ranking signal at ``key``, detached, as ``[B, L]`` (a trailing dim of 1 dropped); ``None``
    when the output has none. Refused unless it is floating and of the batch shape."""
    signal = out.get(key, None)
    if signal is None:
        return None
    batch = tensordict.batch_size
    while signal.ndim > len(batch) and signal.shape[-1] == 1:
        signal = signal.squeeze(-1)
    if signal.shape != batch or not signal.is_floating_point():
        raise ValueError(
            f"the inner loss's ranking signal {key!r} must be a floating tensor of the batch shape {list(batch)} "
            f"(one value per step), got {signal.dtype} {list(signal.shape)}."
        )
    return signal.detach()


def scores(losses: Tensor, signal: Tensor | None, valid: Tensor, key: NestedKey, nonfinite: str) -> Tensor:
    """What the weights rank: the detached ``losses``, or the inner loss's ranking ``signal`` (at ``key``) when it
    gives one. A signal that is NaN or inf at a valid step is refused as a non-finite loss is (with
    ``nonfinite="raise"``, naming the step), or scored as 0 (``"propagate"``: :func:`nonfinite_term` makes the
    loss non-finite)."""
    if signal is None:
        return losses.detach()
    if nonfinite == "raise":
        check_finite(signal, valid, "step", f"ranking signal {key!r}")
    return signal


def nonfinite_term(signal: Tensor, valid: Tensor) -> Tensor:
    """A scalar to add to the loss: 0, or NaN when ``signal`` is NaN or inf at a valid step, so that a non-finite
    signal makes the loss non-finite as a non-finite per-step loss does (``nonfinite="propagate"``)."""
    bad = valid & ~torch.isfinite(signal)
    return torch.where(bad, signal, torch.zeros((), dtype=signal.dtype, device=signal.device)).sum() * 0.0


def scored(losses: Tensor, valid: Tensor, nonfinite: str) -> Tensor:
    """The detached losses a weighting scores: with ``nonfinite="propagate"``, a non-finite one is 0.

    Finite losses pass unchanged (the same values, so the same weights), without a host sync.
    """
    if nonfinite == "raise":
        return losses
    return losses.masked_fill(valid & ~torch.isfinite(losses), 0.0)


def segment_mean(losses: Tensor, weights: Tensor, valid: Tensor) -> Tensor:
    """Eq. 2 per segment, then the mean over segments that have at least one valid step.

    Args:
        losses: ``[..., L]`` per-step losses (padded steps may hold anything, NaN included).
        weights: ``[..., L]`` step weights (unit mean over valid steps for TAR, ones for Eq. 1).
        valid: ``[..., L]`` bool, ``True`` on real steps, ``False`` on padding.

    Returns:
        A scalar: ``mean_i (1 / M_i) sum_t m_t w_t l_t`` over segments ``i`` with ``M_i > 0``;
        ``0`` when no segment has a valid step.
    """
    zero = torch.zeros((), dtype=losses.dtype, device=losses.device)
    per_step = torch.where(valid, weights.to(losses.dtype) * losses, zero)
    n_valid = valid.sum(-1)
    per_segment = per_step.sum(-1) / n_valid.clamp_min(1).to(losses.dtype)
    return per_segment.sum() / (n_valid > 0).sum().clamp_min(1).to(losses.dtype)


def other_entries(
    out: TensorDictBase, key: NestedKey, tensordict: TensorDictBase, valid: Tensor, signal: NestedKey = SIGNAL
) -> tuple[list[Tensor], dict[str, Tensor]]:
    """The inner output's entries besides the per-step loss at ``key`` and the ranking signal at ``signal``: the
    scalar ``loss_*`` ones to add unweighted (reported as ``aux_<name>``), and the diagnostics: its detached
    ``loss_*`` entries of the batch shape as their mean over the valid steps (``inner_<name>``), its other entries
    detached. A differentiable ``loss_*`` entry of more than zero dims is refused (it would have to be weighted)."""
    extra, diagnostics = [], {}
    for name in out.keys():
        if not isinstance(name, str) or name in (key, signal):
            continue
        value = out.get(name)
        if not name.startswith("loss"):
            diagnostics[name] = value.detach()
        elif value.ndim == 0:
            extra.append(value)
            diagnostics[f"aux_{name}"] = value.detach()
        elif value.requires_grad:
            raise ValueError(
                f"the inner loss's extra entry {name!r} has shape {list(value.shape)} and a gradient: extra "
                "losses are added unweighted and must be scalars (detached per-step entries are diagnostics)."
            )
        else:  # a detached per-step entry (e.g. ACTLoss's loss_kl): its mean over the valid steps
            per_step = step_losses(out, name, tensordict, None)
            diagnostics[f"inner_{name}"] = segment_mean(per_step, valid.to(per_step.dtype), valid)
    return extra, diagnostics
