"""The ``make_*`` builders of the training job: dataset, policy head, objective, optimiser, evaluator, device."""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Sequence
from typing import Any

import pandas as pd
import torch
from tensordict.nn import TensorDictModuleBase

from tar_rl.collectors.suites import SUITES, EvalSpec
from tar_rl.data import DatasetError, DemoDataset, load_dataset
from tar_rl.objectives import WEIGHTINGS, MixSchedule, PerturbedTarget, TARLoss
from tar_rl.policies import DataInfo, Policy, build_policy

from .config import DataConfig, ObjectiveConfig, OptimConfig, objective_params
from .errors import ConfigError

__all__ = [
    "given_dataset",
    "make_dataset",
    "make_evaluation_pool",
    "make_evaluator",
    "make_objective",
    "make_optimizer",
    "make_policy",
    "torch_device",
]


def torch_device(name: str, local_rank: int = 0) -> torch.device:
    """The torch device for ``device`` (under torchrun, ``cuda`` means this rank's ``cuda:LOCAL_RANK``)."""
    if name in ("auto", "cuda") and torch.cuda.is_available() and local_rank:
        return torch.device("cuda", local_rank)
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError:
        raise ConfigError(f"device={name!r} is not a device; use auto, cpu, cuda or cuda:N") from None
    if device.type not in ("cpu", "cuda"):
        raise ConfigError(f"device={name!r}: only cpu and cuda are supported")
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"device={name!r} but CUDA is not available here; use device=cpu or device=auto")
    return device


def given_dataset(path: str) -> DemoDataset:
    """The dataset folder of ``data.path``, opened (and checked: files, sizes, format)."""
    try:
        return load_dataset(path)
    except DatasetError as err:
        raise ConfigError(f"data.path={path}: {err}") from None


def make_dataset(data: DataConfig, tasks: Sequence[str], progress: bool = True) -> DemoDataset:
    """The demonstration dataset of the ``data`` section: ``data.path`` if given, else collected in ``data.suite``
    once, then loaded from ``data.root``."""
    if data.path:
        return given_dataset(data.path)
    return SUITES[data.suite].build_dataset(data, tasks, data.n_demos, data.seed, progress)


def make_policy(policy: Any, info: DataInfo) -> Policy:
    """The head of the ``policy`` section (its head's config dataclass; registry ``tar_rl.policies.POLICIES``)."""
    return build_policy(policy, info)


def make_objective(obj: ObjectiveConfig, steps: int, seed: int, policy: Policy) -> TARLoss:
    """``TARLoss`` around the head's per-step loss with the weighting's parameters (:func:`objective_params`), its
    schedule in fractions of ``steps`` (``optim.steps``); ``seed`` (the job's) seeds the controls' draws. The head's
    loss returns the ranking signal ``objective.signal`` beside it (none for ``loss``); a perturbation control's
    inner loss is the head's wrapped in ``PerturbedTarget`` (its supervision corrupted)."""
    schedule = MixSchedule(start=round(obj.start * steps), ramp=round(obj.ramp * steps), shape=obj.shape)
    params = objective_params(obj)
    nonfinite = "propagate"  # a NaN/inf step loss reaches the trainer's optim.skip_nonfinite handling
    inner = policy.loss if obj.signal == "loss" else _with_signal(policy.loss, obj.signal)
    which = WEIGHTINGS[obj.name].perturb
    if which is not None:
        inner = PerturbedTarget(inner, which, params, loss_key=policy.loss_key, nonfinite=nonfinite, seed=seed)
    loss = TARLoss(
        inner,
        obj.name,
        params=params,
        schedule=schedule,
        seed=seed,
        loss_key=policy.loss_key,
        compile_weights=obj.compile,
        nonfinite=nonfinite,
    )
    if policy.event_valid is not None:
        loss.set_keys(event_valid=policy.event_valid)
    return loss


def _with_signal(loss, signal: str):
    """The head's ``loss`` returning the ranking signal ``signal`` beside its loss (``ChunkLoss.with_signal``)."""
    offered = getattr(loss, "signals", ("loss",))
    if signal not in offered:
        raise ValueError(f"objective.signal={signal!r} is not a ranking signal the head's loss offers: {list(offered)}")
    return loss.with_signal(signal)


def make_optimizer(opt: OptimConfig, params) -> tuple[torch.optim.Optimizer, torch.optim.lr_scheduler.LambdaLR]:
    """AdamW and its schedule: linear warm-up over ``optim.warmup`` steps, then cosine or constant."""
    optimizer = torch.optim.AdamW(params, lr=opt.lr, betas=tuple(opt.betas), weight_decay=opt.weight_decay)
    steps, warmup, floor = opt.steps, opt.warmup, opt.min_lr_ratio

    def factor(step: int) -> float:
        if step < warmup:
            return (step + 1) / warmup
        if opt.decay == "constant":
            return 1.0
        progress = min(1.0, (step - warmup) / max(1, steps - warmup))
        return floor + (1 - floor) * 0.5 * (1 + math.cos(math.pi * progress))

    return optimizer, torch.optim.lr_scheduler.LambdaLR(optimizer, factor)


def make_evaluator(
    spec: EvalSpec,
    suite: str,
    tasks: Sequence[str],
    pool,
    progress: bool = True,
    shard: tuple[int, int] = (0, 1),
) -> Callable[[TensorDictModuleBase], pd.DataFrame]:
    """A function running the evaluator collectors of ``suite`` on a policy, as ``spec`` says (a checked job's
    ``validate(config).evaluation`` and ``.suite``, which names the suite of a ``data.path`` dataset).

    The evaluations run on ``pool`` (:func:`make_evaluation_pool`'s), which the caller leaves when its evaluations
    are over. ``shard=(rank, world)`` runs that share of the rollouts on this process's share of the cores.
    """
    run_suite = SUITES[suite]
    return lambda actor: run_suite.evaluate(spec, actor, list(tasks), progress, shard, pool)


def make_evaluation_pool(suite: str) -> contextlib.AbstractContextManager:
    """What the evaluations of a job in ``suite`` share (e.g. MetaWorld's worker processes), as a context manager
    the job leaves at its end; nothing for a suite name outside the registry (a dataset no simulator here has)."""
    return SUITES[suite].evaluation_pool() if suite in SUITES.names() else contextlib.nullcontext()
