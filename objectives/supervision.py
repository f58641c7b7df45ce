"""Supervision transforms: what the ``perturb_high`` / ``perturb_low`` controls do to a head's target.

The perturbation controls corrupt supervision rather than reweight it: on the steps
:func:`~tar_rl.objectives.weighting.perturb_mask` selects, Gaussian noise is added to the expert
target the head learns from, and the steps are then averaged uniformly. The target is the entry a
head's loss declares as its supervision target (``target_key`` on the loss, e.g. the expert chunk
``action_chunk`` of a chunked head; for torchrl's BC losses, their ``action`` key):
:class:`PerturbedTarget` reads it from the loss it wraps and applies :func:`perturb_target` to that
entry only, so no head renames its keys for the controls. The training job builds the wrapper around
the head's loss (``tar_rl.recipes.make_objective``) and gives it to ``TARLoss`` as its inner loss.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torch import Tensor
from torchrl.objectives import LossModule

from .inner import SIGNAL, loss_entry, read_signal, read_valid, scored, scores, step_losses
from .weighting import PerturbParams, perturb_mask

__all__ = ["PerturbedTarget", "perturb_target", "target_key"]


def perturb_target(
    tensordict: TensorDictBase,
    key: NestedKey,
    chosen: Tensor,
    scale: float,
    generator: torch.Generator | None = None,
) -> TensorDictBase:
    """A shallow copy of ``tensordict`` whose supervision target ``key`` has Gaussian noise on the chosen steps.

    Args:
        tensordict: a ``[B, L]`` TensorDict of segments; it is not modified.
        key: the supervision target, ``[B, L, ...]`` (an action ``[B, L, A]``, a chunk ``[B, L, H, A]``).
        chosen: ``[B, L]`` bool, the steps to corrupt (every element of their target).
        scale: the noise's standard deviation, in target units.
        generator: draws the noise, one standard normal of the target's full shape, in float32.
    """
    target = tensordict.get(key)
    noise = torch.randn(target.shape, generator=generator, dtype=torch.float32).to(target)
    chosen = chosen.reshape(chosen.shape + (1,) * (target.ndim - chosen.ndim))
    perturbed = tensordict.copy()
    perturbed.set(key, target + scale * noise * chosen)
    return perturbed


def target_key(loss: LossModule) -> NestedKey:
    """The supervision target of ``loss``: its declared ``target_key``, else its ``action`` key (torchrl's BC
    losses), else ``"action"``."""
    declared = getattr(loss, "target_key", None) or getattr(getattr(loss, "tensor_keys", None), "action", None)
    return "action" if declared is None else declared


class PerturbedTarget(LossModule):
    """An inner loss whose expert target is corrupted on the steps TAR would up- (or down-) weight: the
    ``perturb_high`` / ``perturb_low`` controls. The training job builds it around the head's loss and gives it
    to :class:`~tar_rl.objectives.TARLoss` with the control's weighting (the uniform mean); ``TARLoss`` calls it
    with the schedule's alpha and sets its keys (the mask, the target, the event mask) to its own.

    Each call runs the inner loss twice: once without gradients on the clean batch, whose per-step losses
    (event dims reduced as ``TARLoss`` reduces them; its ranking signal where it gives one, as TAR's weights
    rank by it) choose, per segment, the
    ``floor(fraction * mix * M + 1/2)`` highest-loss (``which="high"``) or lowest-loss (``"low"``) valid steps
    (:func:`~tar_rl.objectives.weighting.perturb_mask`); then on a copy of the batch whose target has Gaussian
    noise of std ``perturb_scale`` on those steps (:func:`perturb_target`). Its output is the second pass's,
    with the detached diagnostic ``perturbed_fraction`` (chosen steps over valid steps).

    Args:
        inner (LossModule): the per-step loss (``reduction="none"``).
        which (str): ``"high"`` or ``"low"``.
        params (PerturbParams): ``perturb_fraction`` and ``perturb_scale``.

    Keyword Args:
        loss_key (NestedKey): the inner output holding the per-step loss; default: its only ``loss_*`` entry.
        nonfinite (str): ``"raise"`` or ``"propagate"``, as for ``TARLoss`` (a non-finite clean loss ranks as 0).
        seed (int): seeds the generator of the tie-breaks and the noise; its state is part of ``state_dict()``,
            so that a resumed run draws the same numbers.

    ``forward(tensordict, mix=1.0)`` takes the schedule's alpha, which scales the fraction.
    """

    @dataclass
    class _AcceptedKeys:
        """Input keys, as :class:`~tar_rl.objectives.TARLoss`'s (which sets them here).

        Attributes:
            valid (NestedKey): bool ``[B, L]`` mask, ``True`` on real steps. Defaults to ``("collector", "mask")``.
            action (NestedKey): the supervision target to corrupt. Defaults to the inner loss's
                (:func:`target_key`).
            event_valid (NestedKey, optional): bool mask over the loss's event dims, ``True`` on real elements.
            signal (NestedKey): the inner output's ranking signal, ``[B, L]``, when it gives one. Defaults to
                ``"signal"``.
        """

        valid: NestedKey = ("collector", "mask")
        action: NestedKey = "action"
        event_valid: NestedKey | None = None
        signal: NestedKey = SIGNAL

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys

    def __init__(
        self,
        inner: LossModule,
        which: str,
        params: PerturbParams,
        *,
        loss_key: NestedKey | None = None,
        nonfinite: str = "raise",
        seed: int = 0,
    ) -> None:
        if which not in ("high", "low"):
            raise ValueError(f"which must be 'high' or 'low', got {which!r}.")
        if not isinstance(params, PerturbParams):
            raise TypeError(f"params must be PerturbParams, got {type(params).__name__}.")
        super().__init__()
        self.inner = inner
        self.which = which
        self.params = params
        self.loss_key = loss_key
        self.nonfinite = nonfinite
        self.generator = torch.Generator().manual_seed(seed)
        self.set_keys(action=target_key(inner))

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    def get_extra_state(self) -> dict:
        return {"generator": self.generator.get_state()}

    def set_extra_state(self, state: dict) -> None:
        self.generator.set_state(state["generator"])

    @property
    def target_key(self) -> NestedKey:
        """The supervision target it corrupts (its ``action`` key)."""
        return self.tensor_keys.action

    @property
    def reduction(self) -> str:
        """The inner loss's reduction (``"none"``: per-step losses)."""
        return getattr(self.inner, "reduction", "none")

    @property
    def in_keys(self) -> list[NestedKey]:
        return list(self.inner.in_keys)

    @property
    def out_keys(self) -> list[NestedKey]:
        return [*getattr(self.inner, "out_keys", ()), "perturbed_fraction"]

    def forward(self, tensordict: TensorDictBase, mix: float | Tensor = 1.0) -> TensorDictBase:
        valid = read_valid(tensordict, self.tensor_keys.valid)
        with torch.no_grad():
            clean_out = self.inner(tensordict)
            key = loss_entry(clean_out, self.loss_key)
            losses = step_losses(clean_out, key, tensordict, self.tensor_keys.event_valid)
            signal = read_signal(clean_out, self.tensor_keys.signal, tensordict)
            ranked = scores(losses, signal, valid, self.tensor_keys.signal, self.nonfinite)
            clean = scored(ranked, valid, self.nonfinite)
        fraction = self.params.perturb_fraction * mix
        chosen = perturb_mask(clean, valid, fraction=fraction, which=self.which, generator=self.generator)
        perturbed = perturb_target(
            tensordict, self.tensor_keys.action, chosen, self.params.perturb_scale, self.generator
        )
        out = self.inner(perturbed)
        out.set("perturbed_fraction", chosen.sum() / valid.sum().clamp_min(1))
        return out
