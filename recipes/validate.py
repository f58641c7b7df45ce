"""The training job's settings checked before any work: :func:`validate` and its :class:`Job` (the typed config the
builders and the loop read, and its evaluation).

Each section checks its own fields where it is defined (``TrainConfig.check``: the integer bounds beside the fields,
the section's other rules in its ``check``); :func:`validate` adds the rules that span sections or need the suite,
the dataset or the built head and objective."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from tar_rl.collectors.suites import SUITES, EvalSpec, Suite, suite_for
from tar_rl.data import DemoDataset
from tar_rl.objectives import WEIGHTINGS, check_gripper_dims
from tar_rl.policies import POLICIES, DataInfo, Policy

from . import diagnose, post_training
from .builders import given_dataset, make_objective, make_policy, torch_device
from .config import DEFAULT_TASKS, ObjectiveConfig, TrainConfig, as_config_error, check_choice, check_int, typed_config
from .errors import ConfigError

__all__ = ["Job", "check_slice_len", "validate"]


@dataclass(frozen=True)
class Job:
    """A checked training job.

    Attributes:
        config: its typed settings; ``init["source"]`` holds the source run's name when ``init.from`` is set.
        train_tasks: the training tasks (``data.tasks`` resolved, or a ``data.path`` dataset's own).
        eval_tasks: the evaluated tasks (``eval.tasks`` resolved, or the training tasks); empty when
            ``eval.rollouts=0``.
        suite: the suite evaluating the job, or the source of a ``data.path`` dataset no simulator here has.
        evaluation: what the suite's evaluator runs (the ``eval`` section's rollouts, seed, horizon and workers, the
            dataset's image size and given folder); None when ``eval.rollouts=0``.
    """

    config: TrainConfig
    train_tasks: tuple[str, ...]
    eval_tasks: tuple[str, ...]
    suite: str
    evaluation: EvalSpec | None = None


def _resolve_tasks(suite: Suite, name: str, spec: list[str]) -> tuple[str, ...]:
    if not spec:
        raise ConfigError(f"{name} is empty: name at least one task or group")
    with as_config_error(f"{name}: "):
        return tuple(suite.resolve(list(spec)))


def validate(config: Any) -> Job:
    """Check every setting of a job before any work: each section's own (``TrainConfig.check``), then the rules that
    span sections; the typed config (:func:`typed_config`), its tasks and its evaluation.

    Args:
        config: the job's settings: Hydra's resolved ``DictConfig``, a :class:`TrainConfig`, or a plain dict
            (``tar_rl.recipes.config.resolve_config``'s, or a run's saved config); it is not changed.

    Raises:
        ConfigError: naming the setting and the valid choices or range.
    """
    cfg = typed_config(config)
    cfg.check()
    _check_signal(cfg.objective, cfg.policy.name)
    suite, given, tasks = _check_suite_and_tasks(cfg)
    check_int("eval.horizon", cfg.eval.horizon, 1, suite.max_horizon if suite is not None else None)
    for step in cfg.logging.record_weights_at:
        if not (step == -1 or (isinstance(step, int) and 1 <= step <= cfg.optim.steps)):
            raise ConfigError(
                f"logging.record_weights_at: {step!r} is not a step in 1..{cfg.optim.steps} (or -1, the last)"
            )
    if given is not None:
        check_slice_len(cfg.data.slice_len, given)
    else:
        _check_slice_len_before_collection(cfg.data.slice_len, suite)
    torch_device(cfg.device)
    with as_config_error():  # the held-out seeds against the others (the group's numbers are its own check)
        diagnose.check_heldout_seeds(cfg)
    ev, data = cfg.eval, cfg.data  # the evaluator's settings, built once: the suites read these, not the sections
    evaluation = None
    if ev.rollouts:
        evaluation = EvalSpec(ev.rollouts, ev.seed, ev.horizon, ev.workers, data.image_size, data.path)
        # Demonstration and evaluation variations never overlap: checked on the largest number of attempts
        # collection may make, before collecting; on a given dataset, on the seeds it used.
        where = f"data.path={data.path}" if given is not None else f"data.seed={data.seed}"
        with as_config_error(f"{where} and eval.seed={ev.seed}: "):
            if given is not None:
                suite.check_dataset(given, evaluation)
            else:
                suite.check_seeds(data.seed, data.n_demos, evaluation)
    # The objective and the head are built once on placeholder data (or the given dataset's
    # description) so that their own checks run now.
    with as_config_error(errors=(ValueError, TypeError)):
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
    if cfg.objective.name == "tar_arm":  # the weighting that reads gripper_dims, indices into the action dims
        with as_config_error("objective."):
            check_gripper_dims(tuple(cfg.objective.gripper_dims), placeholder.action_dim)
    _check_init(cfg, policy, placeholder)
    return Job(cfg, **tasks, evaluation=evaluation)


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
    check_choice("data.suite", data.suite, SUITES.names())
    given = given_dataset(data.path) if data.path else None
    with as_config_error():
        suite = suite_for(data.suite, given)
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
        with as_config_error():
            suite.check_config(data, given, train_tasks, eval_tasks)
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
    with as_config_error(errors=(post_training.InitError,)):
        source = post_training.load_source(init["from"])
        post_training.check_fits(source, cfg.policy.name, policy, info)
    init["source"] = source.name
