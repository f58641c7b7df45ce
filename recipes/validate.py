"""The training job's settings checked before any work: the resolved config dict, :func:`validate` and its
:class:`Job` (the typed config the builders and the loop read)."""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from tar_rl.collectors.suites import SUITES, Suite, suite_for
from tar_rl.data import DemoDataset
from tar_rl.objectives import COMPILE_MODES, WEIGHTINGS, check_gripper_dims
from tar_rl.policies import POLICIES, DataInfo, Policy

from . import diagnose, post_training
from .builders import given_dataset, make_objective, make_policy, torch_device
from .config import DEFAULT_TASKS, ObjectiveConfig, OptimConfig, TrainConfig, objective_params, typed_config
from .errors import ConfigError

__all__ = ["INT_SETTINGS", "MAX_LR", "MAX_STEPS", "Job", "check_slice_len", "int_rule", "resolve_config", "validate"]

#: The most optimiser steps a job may ask for (the paper trains 100K; a billion steps of the smallest head take
#: weeks on a GPU): a larger count is a typo, refused before work rather than found out days later.
MAX_STEPS = 1_000_000_000
#: The largest peak learning rate: AdamW moves each weight by about ``lr`` per step, so a larger one makes
#: the weights of these heads (of order 1) meaningless at the first step.
MAX_LR = 1.0

#: The integer settings with fixed bounds: ``(low, high)``, ``high`` None for none (``eval.horizon``'s bound is
#: its suite's; ``data.workers`` and ``eval.workers`` may also be null).
INT_SETTINGS: dict[str, tuple[int, int | None]] = {
    "seed": (0, None),
    "threads": (0, None),
    "data.seed": (0, None),
    "data.n_demos": (1, None),
    "data.slice_len": (1, None),
    "data.batch_segments": (1, None),
    "data.chunk_horizon": (1, None),
    "data.history": (1, None),
    "data.image_size": (0, None),
    "data.workers": (0, None),
    "eval.seed": (0, None),
    "eval.rollouts": (0, None),
    "eval.every": (0, None),
    "eval.workers": (0, None),
    "optim.steps": (1, MAX_STEPS),
    "optim.warmup": (0, None),
    "optim.skip_nonfinite": (0, None),
    "logging.every": (1, None),
    "logging.checkpoint_every": (1, None),
    "logging.record_episodes": (1, None),
    "diagnostics.heldout_demos": (0, None),
    "diagnostics.heldout_seed": (0, None),
    "diagnostics.train_episodes": (1, None),
    "diagnostics.bins": (2, None),
}
_NULLABLE = ("data.workers", "eval.workers")


def int_rule(low: int, high: int | None) -> str:
    """What an integer setting of these bounds must be, in words (``an integer >= 0``)."""
    return f"an integer between {low} and {high}" if high is not None else f"an integer >= {low}"


def resolve_config(cfg: Any) -> dict:
    """A plain dict of the job's settings from a Hydra ``DictConfig``, a :class:`TrainConfig` or a dict."""
    from omegaconf import DictConfig, OmegaConf

    if isinstance(cfg, DictConfig):
        config = OmegaConf.to_container(cfg, resolve=True)
    elif dataclasses.is_dataclass(cfg):
        config = dataclasses.asdict(cfg)
    elif isinstance(cfg, dict):
        config = copy.deepcopy(cfg)
    else:
        raise ConfigError(f"expected a TrainConfig, a DictConfig or a dict, got {type(cfg).__name__}")
    config.pop("defaults", None)
    config.pop("hydra", None)
    return config


@dataclass(frozen=True)
class Job:
    """A checked training job.

    Attributes:
        config: its typed settings; ``init["source"]`` holds the source run's name when ``init.from`` is set.
        train_tasks: the training tasks (``data.tasks`` resolved, or a ``data.path`` dataset's own).
        eval_tasks: the evaluated tasks (``eval.tasks`` resolved, or the training tasks); empty when
            ``eval.rollouts=0``.
        suite: the suite evaluating the job, or the source of a ``data.path`` dataset no simulator here has.
    """

    config: TrainConfig
    train_tasks: tuple[str, ...]
    eval_tasks: tuple[str, ...]
    suite: str


def _check_int(name: str, value, low: int, high: int | None = None) -> None:
    ok = isinstance(value, int) and not isinstance(value, bool) and value >= low and (high is None or value <= high)
    if not ok:
        raise ConfigError(f"{name} must be {int_rule(low, high)}, got {value!r}")


def _check_choice(name: str, value, choices: Sequence[str]) -> None:
    if value not in choices:
        raise ConfigError(f"{name}={value!r} is not valid; choose one of {list(choices)}")


def _resolve_tasks(suite: Suite, name: str, spec: list[str]) -> tuple[str, ...]:
    if not spec:
        raise ConfigError(f"{name} is empty: name at least one task or group")
    try:
        return tuple(suite.resolve(list(spec)))
    except ValueError as err:
        raise ConfigError(f"{name}: {err}") from None


def validate(config: dict) -> Job:
    """Check every setting of a job before any work; the typed config (:func:`typed_config`) and its tasks.

    Args:
        config: the job's settings as a plain dict (:func:`resolve_config`'s, or a run's saved config); it is
            not changed.

    Raises:
        ConfigError: naming the setting and the valid choices or range.
    """
    cfg = typed_config(config)
    _check_objective(cfg.objective)
    _check_signal(cfg.objective, cfg.policy.name)
    suite, given, tasks = _check_suite_and_tasks(cfg)
    _check_numbers(cfg, suite)
    if given is not None:
        check_slice_len(cfg.data.slice_len, given)
    else:
        _check_slice_len_before_collection(cfg.data.slice_len, suite)
    torch_device(cfg.device)
    _check_diagnostics(cfg)
    _check_seeds(cfg, suite, given)
    # The objective and the head are built once on placeholder data (or the given dataset's
    # description) so that their own checks run now.
    try:
        if given is not None:
            placeholder = DataInfo.from_metadata(given.metadata)
        else:
            placeholder = DataInfo.for_tasks(
                suite.task_names,
                suite.instructions,
                chunk_horizon=cfg.data.chunk_horizon,
                history=cfg.data.history,
                image_size=cfg.data.image_size,
                **({"action_dim": suite.action_dim} if suite.action_dim else {}),
            )
        policy = make_policy(cfg.policy, placeholder)
        make_objective(cfg.objective, cfg.optim.steps, cfg.seed, policy)
    except (ValueError, TypeError) as err:
        raise ConfigError(str(err)) from None
    if cfg.objective.name == "tar_arm":  # the weighting that reads gripper_dims, indices into the action dims
        try:
            check_gripper_dims(tuple(cfg.objective.gripper_dims), placeholder.action_dim)
        except ValueError as err:
            raise ConfigError(f"objective.{err}") from None
    _check_init(cfg, policy, placeholder)
    return Job(cfg, **tasks)


def _check_objective(obj: ObjectiveConfig) -> None:
    _check_choice("objective.name", obj.name, list(WEIGHTINGS))
    _check_choice("objective.shape", obj.shape, ["linear", "cosine"])
    _check_choice("objective.compile", obj.compile, list(COMPILE_MODES))
    if not 0 <= obj.start < 1:
        never = " (the weighting would start after the last step: TAR would never reach full strength)"
        raise ConfigError(
            f"objective.start is a fraction of optim.steps and must lie in [0, 1), got {obj.start}"
            + (never if obj.start >= 1 else "")
        )
    if not 0 <= obj.ramp <= 1:
        raise ConfigError(f"objective.ramp is a fraction of optim.steps and must lie in [0, 1], got {obj.ramp}")
    if obj.start + obj.ramp > 1 + 1e-9:
        raise ConfigError(
            f"objective.start + objective.ramp must be <= 1 (the ramp ends by the last step), got {obj.start} + "
            f"{obj.ramp} = {obj.start + obj.ramp:g}: TAR would never reach full strength; lower one of them"
        )
    try:  # the weighting's parameters check themselves; their message names the parameter
        objective_params(obj)
    except ValueError as err:
        raise ConfigError(f"objective.{err}") from None


def _check_signal(obj: ObjectiveConfig, head: str) -> None:
    """``objective.signal``: ``loss`` or a ranking signal the head offers (``PolicySpec.signals``), for a step
    weighting."""
    offered = ["loss", *POLICIES[head].signals]
    if obj.signal not in offered:
        others = " or ".join(
            f"with policy={name} {' or '.join(spec.signals)}" for name, spec in POLICIES.items() if spec.signals
        )
        raise ConfigError(
            f"objective.signal={obj.signal!r} is not a ranking signal of the {head} head, which offers {offered}; "
            f"use loss, or {others}"
        )
    if obj.signal != "loss" and WEIGHTINGS[obj.name].elementwise:
        raise ConfigError(
            f"objective.signal={obj.signal} ranks the steps, one value per step, but objective={obj.name} scores "
            "per-element losses; use objective.signal=loss with it"
        )


def _check_suite_and_tasks(cfg: TrainConfig) -> tuple[Suite | None, DemoDataset | None, dict]:
    """The suite evaluating the job (None: a given dataset no simulator here has), the given dataset
    (``data.path``, opened and checked) and the resolved tasks (:class:`Job`'s ``train_tasks``, ``eval_tasks``
    and ``suite``)."""
    data, ev = cfg.data, cfg.eval
    _check_choice("data.suite", data.suite, SUITES.names())
    given = given_dataset(data.path) if data.path else None
    try:
        suite = suite_for(data.suite, given)
    except ValueError as err:
        raise ConfigError(str(err)) from None
    suite_name = suite.name if suite is not None else given.source
    if given is not None and suite is None and ev.rollouts:
        raise ConfigError(
            f"data.path={data.path} holds {given.source} demonstrations of {given.tasks}, which have no "
            f"simulator here (evaluation runs {sorted(SUITES)}): set eval.rollouts=0 to train without evaluation"
        )
    if given is not None:
        _check_given_tasks(data, suite, given)
    train_tasks = tuple(given.tasks) if given is not None else _resolve_tasks(suite, "data.tasks", data.tasks)
    eval_tasks = ()
    if ev.rollouts:
        eval_tasks = _resolve_tasks(suite, "eval.tasks", ev.tasks) if ev.tasks else train_tasks
    if suite is not None:
        try:
            suite.check_config(data, given, train_tasks, eval_tasks)
        except ValueError as err:
            raise ConfigError(str(err)) from None
    if data.image_size and suite is not None and not suite.images:
        raise ConfigError(f"data.image_size={data.image_size}: the {suite_name} suite has no image observations")
    return suite, given, {"train_tasks": train_tasks, "eval_tasks": eval_tasks, "suite": suite_name}


def _check_given_tasks(data, suite: Suite | None, given: DemoDataset) -> None:
    """``data.tasks`` left at its default, or naming the tasks of the ``data.path`` dataset (which trains on its
    own tasks): resolved by the suite (its groups included), or by name for a dataset no suite here has."""
    if list(data.tasks) == list(DEFAULT_TASKS):
        return
    named = _resolve_tasks(suite, "data.tasks", data.tasks) if suite is not None else tuple(data.tasks)
    if set(named) != set(given.tasks):
        raise ConfigError(
            f"data.tasks={list(data.tasks)} disagrees with the tasks of data.path={data.path} ({given.tasks}): a "
            "data.path dataset trains on its own tasks; leave data.tasks out or set it to them"
        )


def check_slice_len(slice_len: int, dataset: DemoDataset) -> None:
    """``data.slice_len`` at most the longest episode of the dataset (a longer one pads every segment).

    Raises:
        ConfigError: naming the setting, the dataset and the allowed range.
    """
    longest = dataset.longest_episode
    if slice_len > longest:
        raise ConfigError(
            f"data.slice_len={slice_len} is longer than the longest episode of the dataset {dataset.path} "
            f"({longest} steps), so every segment would be padded; choose data.slice_len between 1 and {longest}"
        )


def _check_slice_len_before_collection(slice_len: int, suite: Suite) -> None:
    """``data.slice_len`` at most the longest demonstration the suite can collect, checked before collecting (the
    collected dataset's own longest episode is checked once it is collected: :func:`check_slice_len`).

    Raises:
        ConfigError: naming the setting, the suite and the allowed range.
    """
    longest = suite.longest_demo
    if longest and slice_len > longest:
        raise ConfigError(
            f"data.slice_len={slice_len} is longer than any demonstration the {suite.name} suite collects (at most "
            f"{longest} steps), so every segment would be padded; choose data.slice_len between 1 and {longest}"
        )


def _check_numbers(cfg: TrainConfig, suite: Suite | None) -> None:
    ev, opt, log = cfg.eval, cfg.optim, cfg.logging
    for name, (low, high) in INT_SETTINGS.items():
        node = cfg
        for part in name.split("."):
            node = getattr(node, part)
        if not (node is None and name in _NULLABLE):
            _check_int(name, node, low, high)
    _check_int("eval.horizon", ev.horizon, 1, suite.max_horizon if suite is not None else None)
    for step in log.record_weights_at:
        if not (step == -1 or (isinstance(step, int) and 1 <= step <= opt.steps)):
            raise ConfigError(f"logging.record_weights_at: {step!r} is not a step in 1..{opt.steps} (or -1, the last)")
    _check_optim(opt)


def _check_optim(opt: OptimConfig) -> None:
    if not 0 < opt.lr <= MAX_LR:
        raise ConfigError(f"optim.lr must be a number in (0, {MAX_LR:g}], got {opt.lr}")
    _check_choice("optim.decay", opt.decay, ["cosine", "constant"])
    if not 0 <= opt.min_lr_ratio <= 1:
        raise ConfigError(f"optim.min_lr_ratio must lie in [0, 1], got {opt.min_lr_ratio}")
    if opt.grad_clip < 0:
        raise ConfigError(f"optim.grad_clip must be >= 0 (0: off), got {opt.grad_clip}")
    if not 0 <= opt.ema < 1:
        raise ConfigError(f"optim.ema is a decay in [0, 1) (0: off), got {opt.ema}")
    if len(opt.betas) != 2 or not all(0 <= b < 1 for b in opt.betas):
        raise ConfigError(f"optim.betas must be two numbers in [0, 1), got {opt.betas}")


def _check_diagnostics(cfg: TrainConfig) -> None:
    """The held-out seeds against the training and evaluation ones (the group's numbers are in :data:`INT_SETTINGS`)."""
    try:
        diagnose.check_heldout_seeds(cfg)
    except ValueError as err:
        raise ConfigError(str(err)) from None


def _check_seeds(cfg: TrainConfig, suite: Suite | None, given: DemoDataset | None) -> None:
    """Demonstration and evaluation variations never overlap: checked on the largest number of attempts
    collection may make, before collecting; on a given dataset, on the seeds it used."""
    data, ev = cfg.data, cfg.eval
    if not ev.rollouts:
        return
    try:
        if given is not None:
            suite.check_dataset(given, ev.seed, ev.rollouts)
        else:
            suite.check_seeds(data, ev)
    except ValueError as err:
        where = f"data.path={data.path}" if given is not None else f"data.seed={data.seed}"
        raise ConfigError(f"{where} and eval.seed={ev.seed}: {err}") from None


def _check_init(cfg: TrainConfig, policy: Policy, info: DataInfo) -> None:
    """Check ``init.from`` (if set) against the policy built from ``cfg`` and record the source's name as
    ``init.source`` (part of the run's identity)."""
    init = cfg.init
    unknown = sorted(set(init) - {"from", "source"})
    if unknown:
        raise ConfigError(f"init has no setting(s) {unknown}; valid: init.from")
    if not init.get("from"):
        init.pop("source", None)
        return
    try:
        source = post_training.load_source(init["from"])
        post_training.check_fits(source, cfg.policy.name, policy, info)
    except post_training.InitError as err:
        raise ConfigError(str(err)) from None
    init["source"] = source.name
