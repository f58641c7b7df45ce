"""Supervision transforms: what the ``perturb_high`` / ``perturb_low`` controls do to a head's target.

The perturbation controls corrupt supervision rather than reweight it: on the steps
:func:`~tar_rl.objectives.weighting.perturb_mask` selects, Gaussian noise is added to the expert
target the head learns from, and the steps are then averaged uniformly. The target is the entry a
head's loss declares as its supervision target (``target_key`` on the loss, e.g. the expert chunk
``action_chunk`` of a chunked head; for torchrl's BC losses, their ``action`` key): ``TARLoss``
reads it from its inner loss and applies :func:`perturb_target` to that entry only, so no head
renames its keys for the controls.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torch import Tensor

__all__ = ["perturb_target"]


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
