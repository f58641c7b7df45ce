"""``tar_loss``: ``TARLoss`` built from keyword arguments, the weighting's parameters among them, around the inner
loss as the training job builds it (a perturbation control's wrapped in ``PerturbedTarget``; for tests)."""

from __future__ import annotations

import dataclasses

from tar_rl import WEIGHTINGS, TARLoss
from tar_rl.objectives import PerturbedTarget


def tar_loss(inner, weighting: str = "tar", **kwargs) -> TARLoss:
    """``TARLoss(inner, weighting, params=..., **rest)``: the keyword arguments that name fields of the weighting's
    parameters (``WEIGHTINGS[weighting].params``) build its ``params``; the others go to ``TARLoss``. A
    perturbation control's ``inner`` is wrapped in ``PerturbedTarget`` first, with the same parameters, loss key,
    ``nonfinite`` and seed (as ``tar_rl.recipes.make_objective`` does)."""
    if weighting in WEIGHTINGS:
        spec = WEIGHTINGS[weighting]
        given = {f.name: kwargs.pop(f.name) for f in dataclasses.fields(spec.params) if f.name in kwargs}
        if given:
            kwargs["params"] = spec.params(**given)
        if spec.perturb is not None:
            inner = PerturbedTarget(
                inner,
                spec.perturb,
                kwargs.get("params") or spec.params(),
                loss_key=kwargs.get("loss_key"),
                nonfinite=kwargs.get("nonfinite", "raise"),
                seed=kwargs.get("seed", 0),
            )
    return TARLoss(inner, weighting, **kwargs)
