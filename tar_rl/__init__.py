"""tar-rl: Time-Adaptive Reweighting (TAR) for behaviour-cloning policy training on TorchRL.

The objective lives in :mod:`tar_rl.objectives` (the repository's ``objectives/`` folder);
the names most users need are re-exported here. They are imported on first use, so that
processes which need only part of the package (demonstration-collection workers, which need
MetaWorld and numpy) do not pay for importing torchrl.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

__version__ = "0.1.0"

_EXPORTS = {
    name: "tar_rl.objectives"
    for name in ("WEIGHTINGS", "MixSchedule", "TARLoss", "TARParams", "get_weighting", "segment_mean", "tar_weights")
}

__all__ = [
    "WEIGHTINGS",
    "MixSchedule",
    "TARLoss",
    "TARParams",
    "__version__",
    "get_weighting",
    "segment_mean",
    "tar_weights",
]

if TYPE_CHECKING:  # pragma: no cover
    from tar_rl.objectives import (
        WEIGHTINGS,
        MixSchedule,
        TARLoss,
        TARParams,
        get_weighting,
        segment_mean,
        tar_weights,
    )


def __getattr__(name: str):
    if name in _EXPORTS:
        value = getattr(importlib.import_module(_EXPORTS[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'tar_rl' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))
