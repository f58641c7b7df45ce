"""Objectives: TAR (:mod:`~tar_rl.objectives.tar`, paper Eqs. 3-8), its controls and the registry of
weightings (:mod:`~tar_rl.objectives.weighting`), the baselines from the literature, the element variants,
TAR's schedule, ``TARLoss``.

Each registered weighting owns a frozen dataclass of its parameters (``WEIGHTINGS[name].params``: ``TARParams``,
``FocalParams``, ...), checked when built and given to ``TARLoss(inner, name, params=...)``.

Installed as ``tar_rl.objectives`` (this folder is mapped there by ``pyproject.toml``). The weightings import
torch only and are imported here, so that every weighting is registered in ``WEIGHTINGS``; ``TARLoss`` and the
supervision transforms need torchrl and tensordict and are imported on first use, so that
``from tar_rl.objectives import tar_weights`` loads neither.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

from .baselines import (
    COUNT_TOLERANCE,
    DROTimeParams,
    FocalParams,
    KeyframeParams,
    TiltedParams,
    TruncateParams,
    dro_time_weights,
    focal_weights,
    keyframe_count,
    keyframe_weights,
    tilted_weights,
    time_bins,
    truncate_count,
    truncate_weights,
)
from .checks import check_step_losses
from .elementwise import (
    TARArmParams,
    check_element_losses,
    check_gripper_dims,
    element_mean,
    tar_arm_weights,
    tar_dimnorm_weights,
)
from .schedule import (
    SCHEDULE_SHAPES,
    MixSchedule,
    mix_at,
)
from .tar import (
    CAP_MODES,
    DEFAULT_EPS,
    DEFAULT_GAMMA,
    DEFAULT_W_MAX,
    TARParams,
    tar_weights,
)
from .weighting import (
    WEIGHTINGS,
    NoParams,
    PerturbParams,
    Weighting,
    get_weighting,
    invert_weights,
    perturb_mask,
    random_weights,
    shuffle_weights,
    uniform_weights,
    window_weights,
)

if TYPE_CHECKING:  # pragma: no cover
    from .supervision import PerturbedTarget, perturb_target
    from .tar_loss import COMPILE_MODES, NONFINITE_MODES, TARLoss, WeightingState, compiles_weights, segment_mean

# name -> the module that defines it, for the names that need torchrl or tensordict
_LAZY = {
    "PerturbedTarget": "supervision",
    "perturb_target": "supervision",
    "COMPILE_MODES": "tar_loss",
    "NONFINITE_MODES": "tar_loss",
    "TARLoss": "tar_loss",
    "WeightingState": "tar_loss",
    "compiles_weights": "tar_loss",
    "segment_mean": "tar_loss",
}

__all__ = [
    "CAP_MODES",
    "COMPILE_MODES",
    "COUNT_TOLERANCE",
    "DEFAULT_EPS",
    "DEFAULT_GAMMA",
    "DEFAULT_W_MAX",
    "NONFINITE_MODES",
    "SCHEDULE_SHAPES",
    "WEIGHTINGS",
    "DROTimeParams",
    "FocalParams",
    "KeyframeParams",
    "MixSchedule",
    "NoParams",
    "PerturbParams",
    "PerturbedTarget",
    "TARArmParams",
    "TARLoss",
    "TARParams",
    "TiltedParams",
    "TruncateParams",
    "Weighting",
    "WeightingState",
    "check_element_losses",
    "check_gripper_dims",
    "check_step_losses",
    "compiles_weights",
    "dro_time_weights",
    "element_mean",
    "focal_weights",
    "get_weighting",
    "invert_weights",
    "keyframe_count",
    "keyframe_weights",
    "mix_at",
    "perturb_mask",
    "perturb_target",
    "random_weights",
    "segment_mean",
    "shuffle_weights",
    "tar_arm_weights",
    "tar_dimnorm_weights",
    "tar_weights",
    "tilted_weights",
    "time_bins",
    "truncate_count",
    "truncate_weights",
    "uniform_weights",
    "window_weights",
]


def __getattr__(name: str):
    if name in _LAZY:
        value = getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
