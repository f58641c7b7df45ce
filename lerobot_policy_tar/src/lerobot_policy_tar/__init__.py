"""TAR (Time-Adaptive Reweighting) for LeRobot's ACT, Diffusion, SmolVLA, pi0 and pi0.5 policies.

Importing the package registers the policy types ``act_tar``, ``diffusion_tar``, ``smolvla_tar``, ``pi0_tar`` and
``pi05_tar`` (``lerobot-train`` imports it because its distribution name starts with ``lerobot_policy_``). The
policies and processors load on first use, as LeRobot's own do.
"""

from .configuration_tar import (
    BASES,
    ACTTARConfig,
    DiffusionTARConfig,
    PI0TARConfig,
    PI05TARConfig,
    SmolVLATARConfig,
    TARSettings,
    tar_config_class,
)

__all__ = [
    "BASES",
    "ACTTARConfig",
    "DiffusionTARConfig",
    "PI0TARConfig",
    "PI05TARConfig",
    "SmolVLATARConfig",
    "TARSettings",
    "tar_config_class",
]
