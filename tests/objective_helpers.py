"""``tar_loss``: ``TARLoss`` built from keyword arguments, the weighting's parameters among them (for tests)."""

from __future__ import annotations

import dataclasses

from tar_rl import WEIGHTINGS, TARLoss


def tar_loss(inner, weighting: str = "tar", **kwargs) -> TARLoss:
    """``TARLoss(inner, weighting, params=..., **rest)``: the keyword arguments that name fields of the weighting's
    parameters (``WEIGHTINGS[weighting].params``) build its ``params``; the others go to ``TARLoss``."""
    if weighting in WEIGHTINGS:
        params = WEIGHTINGS[weighting].params
        given = {f.name: kwargs.pop(f.name) for f in dataclasses.fields(params) if f.name in kwargs}
        if given:
            kwargs["params"] = params(**given)
    return TARLoss(inner, weighting, **kwargs)
