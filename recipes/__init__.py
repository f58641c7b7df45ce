"""Recipes: typed configs -> make_* builders -> one training loop (see recipes/README.md).

Modules: ``config`` (the typed config and its Hydra groups), ``validate`` (every setting checked before any
work), ``builders`` (the ``make_*`` builders), ``offline_bc`` (the ``Trainer`` and ``train``, ``tar-rl train``),
``rundir`` (run names and folder checks), ``record`` (weights along demonstrations), ``evaluate``
(``tar-rl eval``), ``post_training`` (``init.from``), ``diagnose`` (fit diagnostics), ``errors``.
"""

from .builders import (
    make_dataset,
    make_evaluation_pool,
    make_evaluator,
    make_objective,
    make_optimizer,
    make_policy,
)
from .config import resolve_config
from .errors import ConfigError, TrainingError
from .evaluate import evaluate_checkpoint, policy_from_checkpoint
from .offline_bc import Trainer, hydra_main, train
from .record import record_weights
from .rundir import identity, run_name
from .validate import validate

__all__ = [
    "ConfigError",
    "Trainer",
    "TrainingError",
    "evaluate_checkpoint",
    "hydra_main",
    "identity",
    "make_dataset",
    "make_evaluation_pool",
    "make_evaluator",
    "make_objective",
    "make_optimizer",
    "make_policy",
    "policy_from_checkpoint",
    "record_weights",
    "resolve_config",
    "run_name",
    "train",
    "validate",
]
