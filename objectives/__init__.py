"""Objectives: TAR's weightings, its schedule and the ``TARLoss`` LossModule.

Installed as ``tar_rl.objectives`` (this folder is mapped there by ``pyproject.toml``).
"""

from .schedule import SCHEDULE_SHAPES, MixSchedule, mix_at
from .supervision import perturb_target
from .tar_loss import COMPILE_MODES, NONFINITE_MODES, TARLoss, compiles_weights, segment_mean
from .weighting import (
    CAP_MODES,
    DEFAULT_EPS,
    DEFAULT_GAMMA,
    DEFAULT_W_MAX,
    WEIGHTINGS,
    TARParams,
    Weighting,
    check_step_losses,
    get_weighting,
    invert_weights,
    perturb_mask,
    random_weights,
    shuffle_weights,
    tar_weights,
    uniform_weights,
    window_weights,
)

__all__ = [
    "CAP_MODES",
    "COMPILE_MODES",
    "DEFAULT_EPS",
    "DEFAULT_GAMMA",
    "DEFAULT_W_MAX",
    "NONFINITE_MODES",
    "SCHEDULE_SHAPES",
    "WEIGHTINGS",
    "MixSchedule",
    "TARLoss",
    "TARParams",
    "Weighting",
    "check_step_losses",
    "compiles_weights",
    "get_weighting",
    "invert_weights",
    "mix_at",
    "perturb_mask",
    "perturb_target",
    "random_weights",
    "segment_mean",
    "shuffle_weights",
    "tar_weights",
    "uniform_weights",
    "window_weights",
]
