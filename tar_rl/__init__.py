"""tar-rl: Time-Adaptive Reweighting (TAR) for behaviour-cloning policy training on TorchRL.

The objective lives in :mod:`tar_rl.objectives` (the repository's ``objectives/`` folder);
the names most users need are re-exported here.
"""

from tar_rl.objectives import (
    WEIGHTINGS,
    MixSchedule,
    TARLoss,
    get_weighting,
    segment_mean,
    tar_weights,
)

__version__ = "0.1.0"

__all__ = ["WEIGHTINGS", "MixSchedule", "TARLoss", "__version__", "get_weighting", "segment_mean", "tar_weights"]
