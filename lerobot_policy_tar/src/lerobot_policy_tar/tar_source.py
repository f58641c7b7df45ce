"""TAR's math, from tar-rl's own source: ``tar_rl.objectives.tar``, its schedule, its checks and the ranking
signals' state (``tar_rl.objectives.signals``) import torch alone.

The plugin keeps no copy of the weights: tar-rl is installed into the LeRobot environment without its
dependencies (``pip install --no-deps -e .`` at the repository root), and these modules load neither torchrl nor a
simulator.
"""

from __future__ import annotations

try:
    from tar_rl.objectives.checks import check_finite
    from tar_rl.objectives.schedule import MixSchedule
    from tar_rl.objectives.signals import TimeNormalizer
    from tar_rl.objectives.tar import DEFAULT_EPS, DEFAULT_GAMMA, DEFAULT_W_MAX, check_tar_params, tar_weights
except ModuleNotFoundError as error:  # pragma: no cover - the message is the point
    raise ModuleNotFoundError(
        "lerobot_policy_tar takes TAR's math from tar-rl: install it without its dependencies into this "
        "environment with `pip install --no-deps -e .` in a tar-rl checkout (docs/lerobot.md)."
    ) from error

__all__ = [
    "DEFAULT_EPS",
    "DEFAULT_GAMMA",
    "DEFAULT_W_MAX",
    "MixSchedule",
    "TimeNormalizer",
    "check_finite",
    "check_tar_params",
    "tar_weights",
]
