"""The recipe's errors: a bad setting (before any work) and a training run that cannot go on."""

from __future__ import annotations

from tar_rl.errors import TarRLError

__all__ = ["ConfigError", "TrainingError"]


class ConfigError(TarRLError, ValueError):
    """A bad setting (or a run folder that holds another run), reported before any work starts."""


class TrainingError(TarRLError, RuntimeError):
    """The training run cannot go on (a non-finite loss, a full disk); the last good checkpoint is kept."""
