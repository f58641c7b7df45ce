"""The training job's settings checked before any work: the resolved config dict, :func:`validate` and its
:class:`Job` (the typed config the builders and the loop read)."""

from __future__ import annotations

import copy
import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from tar_rl.collectors.suites import SUITES, Suite, suite_for
from tar_rl.data import DemoDataset
from tar_rl.objectives import COMPILE_MODES, WEIGHTINGS, WeightingParams
from tar_rl.policies import DataInfo, Policy

from . import diagnose, post_training
from .builders import given_dataset, make_objective, make_policy, torch_device
from .config import DEFAULT_TASKS, ObjectiveConfig, OptimConfig, TrainConfig, typed_config
from .errors import ConfigError

__all__ = ["Job", "check_slice_len", "resolve_config", "validate"]


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
        bounds = f"between {low} and {high}" if high is not None else f">= {low}"
        raise ConfigError(f"{name} must be an integer {bounds}, got {value!r}")


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
    suite, given, tasks = _check_suite_and_tasks(cfg)
    _check_numbers(cfg, suite)
    if given is not None:
        check_slice_len(cfg.data.slice_len, given)
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
            )
        policy = make_policy(cfg.policy, placeholder)
        make_objective(cfg.objective, cfg.optim.steps, cfg.seed, policy)
    except (ValueError, TypeError) as err:
        raise ConfigError(str(err)) from None
    _check_init(cfg, policy, placeholder)
    return Job(cfg, **tasks)


def _check_objective(obj: ObjectiveConfig) -> None:
    _check_choice("objective.name", obj.name, list(WEIGHTINGS))
    _check_choice("objective.cap", obj.cap, ["paper", "exact"])
    _check_choice("objective.shape", obj.shape, ["linear", "cosine"])
    _check_choice("objective.compile", obj.compile, list(COMPILE_MODES))
    for key, value in (("start", obj.start), ("ramp", obj.ramp)):
        if not 0 <= value <= 1:
            raise ConfigError(f"objective.{key} is a fraction of optim.steps and must lie in [0, 1], got {value}")
    _check_objective_numbers(obj)


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


def _check_numbers(cfg: TrainConfig, suite: Suite | None) -> None:
    data, ev, opt, log = cfg.data, cfg.eval, cfg.optim, cfg.logging
    for name, value, low in (
        ("seed", cfg.seed, 0),
        ("data.seed", data.seed, 0),
        ("eval.seed", ev.seed, 0),
        ("data.n_demos", data.n_demos, 1),
        ("data.slice_len", data.slice_len, 1),
        ("data.batch_segments", data.batch_segments, 1),
        ("data.chunk_horizon", data.chunk_horizon, 1),
        ("data.history", data.history, 1),
        ("data.image_size", data.image_size, 0),
        ("eval.rollouts", ev.rollouts, 0),
        ("eval.every", ev.every, 0),
        ("optim.steps", opt.steps, 1),
        ("optim.warmup", opt.warmup, 0),
        ("optim.skip_nonfinite", opt.skip_nonfinite, 0),
        ("logging.every", log.every, 1),
        ("logging.checkpoint_every", log.checkpoint_every, 1),
        ("logging.record_episodes", log.record_episodes, 1),
    ):
        _check_int(name, value, low)
    _check_int("eval.horizon", ev.horizon, 1, suite.max_horizon if suite is not None else None)
    _check_int("threads", cfg.threads, 0)
    for name, value in (("data.workers", data.workers), ("eval.workers", ev.workers)):
        if value is not None:
            _check_int(name, value, 0)
    for step in log.record_weights_at:
        if not (step == -1 or (isinstance(step, int) and 1 <= step <= opt.steps)):
            raise ConfigError(f"logging.record_weights_at: {step!r} is not a step in 1..{opt.steps} (or -1, the last)")
    _check_optim(opt)


def _check_optim(opt: OptimConfig) -> None:
    if not (opt.lr > 0 and math.isfinite(opt.lr)):
        raise ConfigError(f"optim.lr must be a positive number, got {opt.lr}")
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
    diag = cfg.diagnostics
    for name, value in (("heldout_demos", diag.heldout_demos), ("heldout_seed", diag.heldout_seed)):
        _check_int(f"diagnostics.{name}", value, 0)
    _check_int("diagnostics.train_episodes", diag.train_episodes, 1)
    _check_int("diagnostics.bins", diag.bins, 2)
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


def _check_objective_numbers(obj: ObjectiveConfig) -> None:
    """The weightings' hyper-parameters (``tar_rl.objectives.WeightingParams`` checks the same), named as settings."""
    if not (math.isfinite(obj.gamma) and obj.gamma > 0):
        raise ConfigError(f"objective.gamma is a softmax temperature and must be a finite number > 0, got {obj.gamma}")
    if not obj.w_max > 0:
        raise ConfigError(f"objective.w_max is a weight cap and must be > 0 (inf: no cap), got {obj.w_max}")
    if obj.cap == "exact" and obj.w_max < 1:
        raise ConfigError(
            f"objective.cap=exact needs objective.w_max >= 1 (weights of mean 1 cannot all lie below 1), "
            f"got {obj.w_max}"
        )
    if obj.name == "focal" and obj.w_max < 1:
        raise ConfigError(
            f"objective=focal caps exactly and needs objective.w_max >= 1 (weights of mean 1 cannot all lie "
            f"below 1), got {obj.w_max}"
        )
    if not (math.isfinite(obj.eps) and obj.eps > 0):
        raise ConfigError(f"objective.eps must be a finite number > 0, got {obj.eps}")
    baselines = (
        "tilt",
        "truncate_fraction",
        "keyframe_fraction",
        "keyframe_factor",
        "focal_beta",
        "dro_eta",
        "dro_bins",
    )
    try:  # the baselines' rules live in WeightingParams; its message names the parameter
        WeightingParams(**{key: getattr(obj, key) for key in baselines}, gripper_dims=tuple(obj.gripper_dims))
    except ValueError as err:
        raise ConfigError(f"objective.{err}") from None
    if not 0 <= obj.perturb_fraction <= 1:
        raise ConfigError(f"objective.perturb_fraction must lie in [0, 1], got {obj.perturb_fraction}")
    if not (math.isfinite(obj.perturb_scale) and obj.perturb_scale >= 0):
        raise ConfigError(f"objective.perturb_scale must be a finite number >= 0, got {obj.perturb_scale}")
