"""Offline behaviour cloning on MetaWorld demonstrations: typed config -> ``make_*`` builders -> one loop.

``tar-rl train [overrides]`` runs :func:`train` through Hydra (see ``recipes/config.py`` for the
config). The loop::

    segments [B, L] from the offline replay buffer (SliceSampler)
      -> policy head's per-step losses [B, L, ...]
      -> objective (TARLoss: uniform, tar or a control) -> loss_tar
      -> AdamW step (warm-up + cosine decay, gradient clipping, optional EMA, AMP on CUDA)
    every eval.every steps and at the end: the evaluator collectors (success, Fast20, NEPS)

Run directory (``run_dir``, by default ``runs/<objective>-<policy>-s<seed>-<hash>``)::

    config.yaml          the resolved config (a later start with other settings is refused)
    checkpoint.pt        the whole training state (written atomically), see ``Trainer.checkpoint``
    metrics.csv          tidy table: step, phase (train | eval), name, value
    eval_rollouts.csv    one row per evaluation rollout (the evaluator's columns + step)
    weights.csv          per-step loss and TAR weight along whole demonstrations (if recorded)
    summary.json         final metrics per difficulty group; "finished": true marks a finished run
    .lock                flock-ed by the job running in the folder (``tar_rl.runlock``): one job at a time

Resume: running the same command again continues from ``checkpoint.pt`` with the same data
order (the sampler's generator state), the same schedule and control RNG (the objective's state),
the same optimiser, LR schedule and EMA state, the logs as they were at that step and each rank's
logging window (the running sums since the last metrics row); it reaches the same final weights and
writes the same log files, byte for byte, as an uninterrupted run. A finished run is reported and
skipped, so a sweep that was stopped half way is restarted with the same command.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import math
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModuleBase

from tar_rl import distributed, runs
from tar_rl.collectors.suites import SUITES, Suite, suite_for
from tar_rl.data import DatasetError, DemoDataset, load_dataset
from tar_rl.errors import DiskFullError, RunInterrupted, TarRLError, debug_mode, interrupted, one_line
from tar_rl.io import atomic_write, write_csv_atomic, write_json_atomic
from tar_rl.metrics import summarize
from tar_rl.objectives import COMPILE_MODES, WEIGHTINGS, MixSchedule, TARLoss, window_weights
from tar_rl.policies import POLICIES, DataInfo, Policy, build_policy
from tar_rl.runlock import run_lock
from tar_rl.runs import (
    CHECKPOINT,
    RunLogs,
    config_differences,
    git_commit,
    json_metric,
    last_metric,
    load_checkpoint,
    machine,
    print_table,
    rollout_records,
    save_checkpoint,
    summary_rows,
)

from . import diagnose, post_training
from .config import CONFIG_NAME, default_config, register_configs

__all__ = [
    "ConfigError",
    "TrainingError",
    "evaluate_checkpoint",
    "hydra_main",
    "make_dataset",
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


class ConfigError(TarRLError, ValueError):
    """A bad setting (or a run folder that holds another run), reported before any work starts."""


class TrainingError(TarRLError, RuntimeError):
    """The training run cannot go on (a non-finite loss, a full disk); the last good checkpoint is kept."""


# -- Config ------------------------------------------------------------------------------------


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


def validate(config: dict) -> dict:
    """Check every setting before any work; returns the resolved task lists ``{"train": ..., "eval": ...}``.

    Raises:
        ConfigError: naming the setting and the valid choices or range.
    """
    obj, data, ev, opt, log = (config[k] for k in ("objective", "data", "eval", "optim", "logging"))
    _check_choice("objective.name", obj["name"], list(WEIGHTINGS))
    _check_choice("policy.name", config["policy"]["name"], list(POLICIES))
    _check_choice("objective.cap", obj["cap"], ["paper", "exact"])
    _check_choice("objective.shape", obj["shape"], ["linear", "cosine"])
    _check_choice("objective.compile", obj["compile"], list(COMPILE_MODES))
    for key in ("start", "ramp"):
        if not 0 <= obj[key] <= 1:
            raise ConfigError(f"objective.{key} is a fraction of optim.steps and must lie in [0, 1], got {obj[key]}")
    _check_objective_numbers(obj)
    _check_choice("data.suite", data["suite"], SUITES.names())
    given = _given_dataset(data["path"]) if data["path"] else None
    try:
        suite = suite_for(data["suite"], given)
    except ValueError as err:
        raise ConfigError(str(err)) from None
    suite_name = suite.name if suite is not None else given.source
    if given is not None and suite is None and ev["rollouts"]:
        raise ConfigError(
            f"data.path={data['path']} holds {given.source} demonstrations of {given.tasks}, which have no "
            f"simulator here (evaluation runs {sorted(SUITES)}): set eval.rollouts=0 to train without evaluation"
        )
    train_tasks = tuple(given.tasks) if given is not None else _resolve_tasks(suite, "data.tasks", data["tasks"])
    eval_tasks = ()
    if ev["rollouts"]:
        eval_tasks = _resolve_tasks(suite, "eval.tasks", ev["tasks"]) if ev["tasks"] else train_tasks
    if suite is not None:
        try:
            suite.check_config(config, given, train_tasks, eval_tasks)
        except ValueError as err:
            raise ConfigError(str(err)) from None
    if data["image_size"] and suite is not None and not suite.images:
        raise ConfigError(f"data.image_size={data['image_size']}: the {suite_name} suite has no image observations")
    for name, value, low in (
        ("seed", config["seed"], 0),
        ("data.seed", data["seed"], 0),
        ("eval.seed", ev["seed"], 0),
        ("data.n_demos", data["n_demos"], 1),
        ("data.slice_len", data["slice_len"], 1),
        ("data.batch_segments", data["batch_segments"], 1),
        ("data.chunk_horizon", data["chunk_horizon"], 1),
        ("data.history", data["history"], 1),
        ("data.image_size", data["image_size"], 0),
        ("eval.rollouts", ev["rollouts"], 0),
        ("eval.every", ev["every"], 0),
        ("optim.steps", opt["steps"], 1),
        ("optim.warmup", opt["warmup"], 0),
        ("optim.skip_nonfinite", opt["skip_nonfinite"], 0),
        ("logging.every", log["every"], 1),
        ("logging.checkpoint_every", log["checkpoint_every"], 1),
        ("logging.record_episodes", log["record_episodes"], 1),
    ):
        _check_int(name, value, low)
    _check_int("eval.horizon", ev["horizon"], 1, suite.max_horizon if suite is not None else None)
    _check_int("threads", config["threads"], 0)
    for name in ("data.workers", "eval.workers"):
        value = config[name.split(".")[0]][name.split(".")[1]]
        if value is not None:
            _check_int(name, value, 0)
    for step in log["record_weights_at"]:
        if not (step == -1 or (isinstance(step, int) and 1 <= step <= opt["steps"])):
            raise ConfigError(
                f"logging.record_weights_at: {step!r} is not a step in 1..{opt['steps']} (or -1, the last)"
            )
    if not (opt["lr"] > 0 and math.isfinite(opt["lr"])):
        raise ConfigError(f"optim.lr must be a positive number, got {opt['lr']}")
    _check_choice("optim.decay", opt["decay"], ["cosine", "constant"])
    if not 0 <= opt["min_lr_ratio"] <= 1:
        raise ConfigError(f"optim.min_lr_ratio must lie in [0, 1], got {opt['min_lr_ratio']}")
    if opt["grad_clip"] < 0:
        raise ConfigError(f"optim.grad_clip must be >= 0 (0: off), got {opt['grad_clip']}")
    if not 0 <= opt["ema"] < 1:
        raise ConfigError(f"optim.ema is a decay in [0, 1) (0: off), got {opt['ema']}")
    if len(opt["betas"]) != 2 or not all(0 <= b < 1 for b in opt["betas"]):
        raise ConfigError(f"optim.betas must be two numbers in [0, 1), got {opt['betas']}")
    _device(config["device"])
    diag = config["diagnostics"]
    for name in ("heldout_demos", "heldout_seed"):
        _check_int(f"diagnostics.{name}", diag[name], 0)
    _check_int("diagnostics.train_episodes", diag["train_episodes"], 1)
    _check_int("diagnostics.bins", diag["bins"], 2)
    try:
        diagnose.check_heldout_seeds(config)
    except ValueError as err:
        raise ConfigError(str(err)) from None
    # Demonstration and evaluation variations must never overlap (checked on the largest number
    # of attempts collection may make, before collecting; on a given dataset, on the seeds it used).
    if ev["rollouts"]:
        try:
            if given is not None:
                suite.check_dataset(given, ev["seed"], ev["rollouts"])
            else:
                suite.check_seeds(config)
        except ValueError as err:
            where = f"data.path={data['path']}" if given is not None else f"data.seed={data['seed']}"
            raise ConfigError(f"{where} and eval.seed={ev['seed']}: {err}") from None
    # The objective and the head are built once on placeholder data (or the given dataset's
    # description) so that their own checks run now.
    try:
        placeholder = DataInfo(
            chunk_horizon=data["chunk_horizon"], history=data["history"], image_size=data["image_size"]
        )
        if given is not None:
            placeholder = DataInfo.from_metadata(given.metadata)
        policy = make_policy(config, placeholder)
        make_objective(config, policy)
    except (ValueError, TypeError) as err:
        raise ConfigError(str(err)) from None
    _check_init(config, policy, placeholder)
    return {"train": train_tasks, "eval": eval_tasks, "suite": suite_name}


def _check_init(config: dict, policy: Policy, info: DataInfo) -> None:
    """Check ``init.from`` (if set) against the policy built from ``config`` and record the source's name as
    ``init.source`` (part of the run's identity)."""
    init = config.setdefault("init", {"from": None})
    unknown = sorted(set(init) - {"from", "source"})
    if unknown:
        raise ConfigError(f"init has no setting(s) {unknown}; valid: init.from")
    if not init.get("from"):
        init.pop("source", None)
        return
    try:
        source = post_training.load_source(init["from"])
        post_training.check_fits(source, config["policy"]["name"], policy, info)
    except post_training.InitError as err:
        raise ConfigError(str(err)) from None
    init["source"] = source.name


def _check_objective_numbers(obj: dict) -> None:
    """TAR's hyper-parameters (``tar_rl.objectives.TARParams`` checks the same), named as settings."""
    if not (math.isfinite(obj["gamma"]) and obj["gamma"] > 0):
        raise ConfigError(
            f"objective.gamma is a softmax temperature and must be a finite number > 0, got {obj['gamma']}"
        )
    if not obj["w_max"] > 0:
        raise ConfigError(f"objective.w_max is a weight cap and must be > 0 (inf: no cap), got {obj['w_max']}")
    if obj["cap"] == "exact" and obj["w_max"] < 1:
        raise ConfigError(
            f"objective.cap=exact needs objective.w_max >= 1 (weights of mean 1 cannot all lie below 1), "
            f"got {obj['w_max']}"
        )
    if not (math.isfinite(obj["eps"]) and obj["eps"] > 0):
        raise ConfigError(f"objective.eps must be a finite number > 0, got {obj['eps']}")
    if not 0 <= obj["perturb_fraction"] <= 1:
        raise ConfigError(f"objective.perturb_fraction must lie in [0, 1], got {obj['perturb_fraction']}")
    if not (math.isfinite(obj["perturb_scale"]) and obj["perturb_scale"] >= 0):
        raise ConfigError(f"objective.perturb_scale must be a finite number >= 0, got {obj['perturb_scale']}")


def _device(name: str, local_rank: int = 0) -> torch.device:
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


# -- Builders ----------------------------------------------------------------------------------


def _given_dataset(path: str) -> DemoDataset:
    """The dataset folder of ``data.path``, opened (and checked: files, sizes, format)."""
    try:
        return load_dataset(path)
    except DatasetError as err:
        raise ConfigError(f"data.path={path}: {err}") from None


def make_dataset(config: dict, tasks: Sequence[str], progress: bool = True) -> DemoDataset:
    """The demonstration dataset: ``data.path`` if given, else collected in ``data.suite`` once, then loaded
    from ``data.root``."""
    data = config["data"]
    if data["path"]:
        return _given_dataset(data["path"])
    return SUITES[data["suite"]].build_dataset(config, tasks, data["n_demos"], data["seed"], progress)


def make_policy(config: dict, info: DataInfo) -> Policy:
    """The head named ``policy.name`` (registry ``tar_rl.policies.POLICIES``)."""
    return build_policy(config["policy"], info)


def make_objective(config: dict, policy: Policy) -> TARLoss:
    """``TARLoss`` around the head's per-step loss, its schedule in fractions of ``optim.steps``."""
    obj, steps = config["objective"], config["optim"]["steps"]
    schedule = MixSchedule(start=round(obj["start"] * steps), ramp=round(obj["ramp"] * steps), shape=obj["shape"])
    loss = TARLoss(
        policy.loss,
        obj["name"],
        gamma=obj["gamma"],
        w_max=obj["w_max"],
        eps=obj["eps"],
        cap=obj["cap"],
        schedule=schedule,
        perturb_fraction=obj["perturb_fraction"],
        perturb_scale=obj["perturb_scale"],
        seed=config["seed"],
        loss_key=policy.loss_key,
        compile_weights=obj["compile"],
        nonfinite="propagate",  # a NaN/inf step loss reaches the trainer's optim.skip_nonfinite handling
    )
    if policy.event_valid is not None:
        loss.set_keys(event_valid=policy.event_valid)
    return loss


def make_optimizer(config: dict, params) -> tuple[torch.optim.Optimizer, torch.optim.lr_scheduler.LambdaLR]:
    """AdamW and its schedule: linear warm-up over ``optim.warmup`` steps, then cosine or constant."""
    opt = config["optim"]
    optimizer = torch.optim.AdamW(params, lr=opt["lr"], betas=tuple(opt["betas"]), weight_decay=opt["weight_decay"])
    steps, warmup, floor = opt["steps"], opt["warmup"], opt["min_lr_ratio"]

    def factor(step: int) -> float:
        if step < warmup:
            return (step + 1) / warmup
        if opt["decay"] == "constant":
            return 1.0
        progress = min(1.0, (step - warmup) / max(1, steps - warmup))
        return floor + (1 - floor) * 0.5 * (1 + math.cos(math.pi * progress))

    return optimizer, torch.optim.lr_scheduler.LambdaLR(optimizer, factor)


def make_evaluator(
    config: dict,
    tasks: Sequence[str],
    progress: bool = True,
    shard: tuple[int, int] = (0, 1),
    suite: str | None = None,
) -> Callable[[TensorDictModuleBase], pd.DataFrame]:
    """A function running the evaluator collectors of ``suite`` (default ``data.suite``) on a policy.

    ``validate(config)["suite"]`` names the suite of a ``data.path`` dataset. ``shard=(rank, world)``
    runs that share of the rollouts on this process's share of the cores. A MetaWorld policy reading
    ``pixels`` gets camera images of ``data.image_size``.
    """
    run_suite = SUITES[suite or config["data"]["suite"]]
    return lambda actor: run_suite.evaluate(config, actor, list(tasks), progress, shard)


# -- Run state ---------------------------------------------------------------------------------


def _eval_actor(actor: TensorDictModuleBase, ema) -> TensorDictModuleBase:
    """A CPU copy of the policy for the evaluator's worker processes (the EMA weights if given)."""
    return copy.deepcopy(ema.module if ema is not None else actor).to("cpu").eval()


def record_weights(
    objective: TARLoss, episodes: list[tuple[str, int, TensorDict]], slice_len: int, step: int
) -> list[tuple]:
    """Per-step loss and TAR weight along whole demonstrations (rows of ``weights.csv``, the paper's Fig. 5).

    The loss is the head's per-step loss at the current weights; the weight is
    :func:`tar_rl.objectives.window_weights` of those losses with the objective's gamma, w_max,
    eps and cap at full strength, whatever the run's own weighting and schedule.
    """
    rows = []
    was_training = objective.training
    objective.eval()
    p = objective.tar_params
    try:
        with torch.no_grad():
            for task, episode, td in episodes:
                losses = objective.step_losses(td.unsqueeze(0)).squeeze(0).float().cpu()
                weight = window_weights(losses, slice_len, gamma=p.gamma, w_max=p.w_max, eps=p.eps, cap=p.cap)
                gripper = td["action"][..., -1].float().cpu()
                rows += [
                    (step, task, episode, t, float(losses[t]), float(weight[t]), float(gripper[t]))
                    for t in range(losses.shape[0])
                ]
    finally:
        objective.train(was_training)
    return rows


def _demo_episodes(
    dataset: DemoDataset, tasks: Sequence[str], per_task: int, keys, device
) -> list[tuple[str, int, TensorDict]]:
    data = dataset.data
    episode = data["episode"].numpy()
    task_id = data["task_id"].numpy()
    out = []
    for task in tasks:
        ids = np.unique(episode[task_id == dataset.metadata["task_ids"][task]])[:per_task]
        for e in ids:
            idx = np.flatnonzero(episode == e)
            td = data[int(idx[0]) : int(idx[-1]) + 1]
            td = td.select(*keys) if keys is not None else td
            out.append((task, int(e), td.clone().to(device)))
    return out


# -- Checkpoints -------------------------------------------------------------------------------


def policy_from_checkpoint(state: dict, path: str | Path = "checkpoint") -> TensorDictModuleBase:
    """Rebuild the saved policy (EMA weights if the run kept them) for inference, on CPU."""
    config = state["config"]
    policy = make_policy(config, DataInfo.from_dict(state["data_info"]))
    weights = state["ema_policy"] if state.get("ema_policy") is not None else state["policy"]
    try:
        policy.actor.load_state_dict(weights)
    except RuntimeError as err:
        raise ValueError(
            f"{path}: the saved weights do not fit the policy {config['policy']['name']!r} built from its config: {err}"
        ) from None
    return policy.actor.eval()


def _with_defaults(saved: dict) -> dict:
    """A saved config completed with the defaults of settings it does not hold."""

    def merge(base: dict, over: dict) -> dict:
        out = dict(base)
        for key, value in over.items():
            out[key] = merge(base[key], value) if isinstance(value, dict) and isinstance(base.get(key), dict) else value
        return out

    return merge(default_config(saved["objective"]["name"], saved["policy"]["name"]), copy.deepcopy(saved))


def run_name(config: dict) -> str:
    """The run's directory name: ``<objective>-<policy>-s<seed>-<hash>`` (:func:`tar_rl.runs.run_name` measured
    against the default job of its objective and head)."""
    return runs.run_name(config, default_config(config["objective"]["name"], config["policy"]["name"]))


def identity(config: dict) -> dict:
    """The settings that make the run differ from the default job (:func:`tar_rl.runs.identity`)."""
    return runs.identity(config, default_config(config["objective"]["name"], config["policy"]["name"]))


def identity_differences(old: dict, new: dict) -> list[str]:
    """``key.path: old -> new`` for every setting of a run's identity that differs between two configs (settings
    a config lacks read as their defaults); empty when both name the same run."""
    return config_differences(runs.identity(_with_defaults(old), {}), runs.identity(_with_defaults(new), {}))


def evaluate_checkpoint(
    path: str | Path,
    tasks: Sequence[str] | None = None,
    rollouts: int | None = None,
    seed: int | None = None,
    horizon: int | None = None,
    workers: int | None = None,
    out: str | Path | None = None,
    progress: bool = True,
) -> pd.DataFrame:
    """Evaluate a saved policy; settings default to the run's ``eval`` config. Prints the table.

    Writes the rollouts to ``out`` (default ``eval-<seed>.csv`` beside the checkpoint) and returns them.

    Raises:
        FileNotFoundError: no checkpoint there. ValueError / ConfigError: not a checkpoint, a
        policy that does not fit it, or bad settings (named).
    """
    path = Path(path)
    state = load_checkpoint(path)
    config = _with_defaults(state["config"])
    # Evaluating a saved policy needs neither its post-training source nor held-out data.
    config["init"] = {"from": None}
    config["diagnostics"]["heldout_demos"] = 0
    ev = config["eval"]
    for key, value in (("rollouts", rollouts), ("seed", seed), ("horizon", horizon), ("workers", workers)):
        if value is not None:
            ev[key] = value
    if tasks:
        ev["tasks"] = list(tasks)
    checked = validate(config)
    actor = policy_from_checkpoint(state, path)
    rollouts_df = make_evaluator(config, checked["eval"], progress=progress, suite=checked["suite"])(actor)
    target = Path(out) if out else (path if path.is_dir() else path.parent) / f"eval-{ev['seed']}.csv"
    write_csv_atomic(rollouts_df.assign(step=state["step"]), target)
    print(f"{path} (step {state['step']}), {ev['rollouts']} rollouts per task, seed {ev['seed']}; rollouts in {target}")
    print_table(summarize(rollouts_df))
    return rollouts_df


# -- The job -----------------------------------------------------------------------------------


def _prepare_run_dir(run_dir: Path) -> None:
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
        atomic_write(run_dir / ".write-test", lambda f: f.write("ok"))
        (run_dir / ".write-test").unlink()
    except OSError as err:
        raise ConfigError(f"cannot write to the run directory {run_dir}: {err}") from None


def _last_checkpoint(run_dir: Path) -> str:
    """Where a stopped run resumes from, in words: the last checkpoint's step and file, or that there is none."""
    path = run_dir / CHECKPOINT
    try:
        step = load_checkpoint(path)["step"]
    except FileNotFoundError:
        return f"no checkpoint was written yet in {run_dir}"
    except ValueError:
        return f"{path} cannot be read"
    return f"the last good checkpoint (step {step}) is kept in {path}"


def _interruption(run_dir: Path, trainer: Trainer | None) -> str:
    """Where a run stopped by Ctrl-C stopped, and how to resume it."""
    if trainer is None:
        where = "before training started (while loading or collecting the dataset)"
    elif trainer.step < trainer.steps:
        where = f"at step {trainer.step} of {trainer.steps}"
    else:
        where = f"in the final evaluation (after step {trainer.steps})"
    return f"interrupted {where}; {_last_checkpoint(run_dir)}: run the same command to resume"


def _check_resumable(run_dir: Path, config: dict) -> dict | None:
    """The checkpoint to resume from (None for a new run); refuses a folder whose run has other settings.

    Before its first checkpoint a started run is known by its ``config.yaml``, which is compared the same way.
    """
    path = run_dir / CHECKPOINT
    if not path.exists():
        _check_same_run(run_dir, _started_config(run_dir), config)
        return None
    try:
        state = load_checkpoint(path)
    except ValueError as err:
        raise ConfigError(
            f"{str(err).splitlines()[0]}; remove {path} to start the run again from step 0, or choose another run_dir"
        ) from err
    _check_same_run(run_dir, state["config"], config)
    return state


def _started_config(run_dir: Path) -> dict | None:
    """The config a started run wrote into ``run_dir/config.yaml`` (None if there is none)."""
    path = run_dir / "config.yaml"
    if not path.exists():
        return None
    from omegaconf import OmegaConf

    try:
        saved = OmegaConf.to_container(OmegaConf.load(path), resolve=True)
        if not isinstance(saved, dict):
            raise ValueError(f"it holds a {type(saved).__name__}, not a config")
    except Exception as err:  # OmegaConf raises many kinds for a damaged YAML file
        first = str(err).splitlines()[0] if str(err) else type(err).__name__
        raise ConfigError(f"{path} cannot be read ({first}); remove it or choose another run_dir") from err
    return saved


def _check_same_run(run_dir: Path, saved: dict | None, config: dict) -> None:
    if saved is None:
        return
    diff = identity_differences(saved, config)
    if diff:
        raise ConfigError(
            f"{run_dir} holds a run with other settings ({'; '.join(diff)}); choose another run_dir or remove it"
        )


class Trainer:
    """One training job: built from a resolved config, then :meth:`run` (resume, loop, final evaluation).

    Under ``torchrun`` every rank builds a ``Trainer``; the policy's objective is wrapped in
    ``DistributedDataParallel``; each rank draws the same global batch of ``data.batch_segments``
    segments (the sampler's generator is seeded identically) and trains on its contiguous share
    of them, so the job follows the data order of a single-process run of the same global batch.
    Rank 0 alone writes files and prints; evaluation is sharded over the ranks and gathered.
    """

    def __init__(self, config: dict, tasks: dict, run_dir: Path, resume: dict | None, dist: distributed.Dist):
        self.config, self.tasks, self.run_dir, self.dist = config, tasks, run_dir, dist
        data_cfg, self.opt_cfg, self.log_cfg = config["data"], config["optim"], config["logging"]
        self.progress = self.log_cfg["progress"] and dist.main
        self.device = _device(config["device"], dist.local_rank)
        if config["threads"]:
            torch.set_num_threads(config["threads"])
        torch.manual_seed(config["seed"])
        if not dist.main:
            dist.barrier()  # rank 0 collects (or finds) the dataset first; the others then load it
        self.dataset = make_dataset(config, tasks["train"], progress=self.progress)
        self.heldout = diagnose.heldout_dataset(config, tasks["train"], progress=self.progress)
        if dist.main:
            dist.barrier()
        if config["eval"]["rollouts"]:
            SUITES[tasks["suite"]].check_dataset(self.dataset, config["eval"]["seed"], config["eval"]["rollouts"])
        self.info = DataInfo.from_metadata(self.dataset.metadata)
        self.policy = make_policy(config, self.info)
        self.source = None
        if config["init"].get("from"):
            self.source = post_training.load_source(config["init"]["from"])
            post_training.check_fits(self.source, config["policy"]["name"], self.policy, self.info)
            if resume is None:  # a resumed run reads its own weights from its checkpoint
                post_training.apply_init(self.policy, self.source)
        self.objective = make_objective(config, self.policy).to(self.device)
        self.model = self.objective
        if dist.active:
            ids = [self.device.index] if self.device.type == "cuda" else None
            self.model = distributed.data_parallel(self.objective, device_ids=ids)
        self.params = [p for p in self.objective.parameters() if p.requires_grad]
        self.optimizer, self.scheduler = make_optimizer(config, self.params)
        self.ema = None
        if self.opt_cfg["ema"] > 0:
            from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn

            decay = get_ema_multi_avg_fn(self.opt_cfg["ema"])
            self.ema = AveragedModel(self.policy.actor, multi_avg_fn=decay, use_buffers=True)
        self.generator = torch.Generator().manual_seed(config["seed"])
        self.sampler = self.dataset.segments(
            data_cfg["batch_segments"], data_cfg["slice_len"], keys=self.policy.keys, generator=self.generator
        )
        share = data_cfg["batch_segments"] // dist.world
        self.rows = slice(dist.rank * share, (dist.rank + 1) * share)
        self.evaluator = None  # eval.rollouts=0: training only
        if config["eval"]["rollouts"]:
            shard = (dist.rank, dist.world)
            self.evaluator = make_evaluator(
                config, tasks["eval"], progress=self.progress, shard=shard, suite=tasks["suite"]
            )
        self.steps = self.opt_cfg["steps"]
        self.record_at = (
            {self.steps if s == -1 else s for s in self.log_cfg["record_weights_at"]} if dist.main else set()
        )
        self.episodes = []
        if self.record_at:
            self.episodes = _demo_episodes(
                self.dataset, tasks["train"], self.log_cfg["record_episodes"], self.policy.keys, self.device
            )
        self.logs = RunLogs(run_dir)
        self.commit = git_commit()
        self.step, self.skipped, self.train_seconds = 0, 0, 0.0
        # The logging window: this rank's running sums of the step scalars and the number of steps
        # summed since the last metrics row (in the checkpoint, so that a resumed run logs the same means).
        self.window_sums: dict[str, float] = {}
        self.window_count = 0
        if resume is not None:
            self._restore(resume)

    # -- state ------------------------------------------------------------------------------

    def _restore(self, state: dict) -> None:
        if DataInfo.from_dict(state["data_info"]) != self.info:
            raise ConfigError(f"{self.run_dir}: the dataset differs from the one the checkpoint was trained on")
        self.objective.load_state_dict(state["objective"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.scheduler.load_state_dict(state["scheduler"])
        if self.ema is not None:
            self.ema.load_state_dict(state["ema"])
        self.generator.set_state(state["sampler_rng"])
        torch.set_rng_state(state["torch_rng"])
        self.logs = RunLogs(self.run_dir, **state["logs"])
        self.step, self.skipped, self.train_seconds = state["step"], state["skipped"], state["train_seconds"]
        self._restore_window(state.get("log_windows") or [])
        self._print(f"{self.run_dir}: resuming at step {self.step} of {self.steps}")

    def _restore_window(self, windows: list[dict]) -> None:
        """Each rank's logging window as saved; saved by another number of ranks, rank 0 takes their sum.

        (Then the means of the next metrics row agree up to float rounding. Checkpoints that hold
        no window start with an empty one.)
        """
        if len(windows) == self.dist.world:
            mine = [windows[self.dist.rank]]
        else:
            mine = windows if self.dist.main else []
        for window in mine:
            for name, value in window["sums"].items():
                self.window_sums[name] = self.window_sums.get(name, 0.0) + value
            self.window_count += window["count"]

    def checkpoint(self, finished: bool = False) -> None:
        """Write the whole training state (rank 0; every rank holds the same state but its logging window)."""
        windows = self.dist.all_gather_object({"sums": dict(self.window_sums), "count": self.window_count})
        if not self.dist.main:
            return
        ema = self.ema
        save_checkpoint(
            {
                "step": self.step,
                "finished": finished,
                "config": self.config,
                "data_info": self.info.to_dict(),
                "policy": self.policy.actor.state_dict(),
                "ema_policy": ema.module.state_dict() if ema is not None else None,
                "objective": self.objective.state_dict(),
                "optimizer": self.optimizer.state_dict(),
                "scheduler": self.scheduler.state_dict(),
                "ema": ema.state_dict() if ema is not None else None,
                "sampler_rng": self.generator.get_state(),
                "torch_rng": torch.get_rng_state(),
                "logs": self.logs.state(),
                "log_windows": windows,
                "skipped": self.skipped,
                "train_seconds": self.train_seconds,
                "world_size": self.dist.world,
                "task_ids": sorted(int(i) for i in self.dataset.metadata["task_ids"].values()),
                "git_commit": self.commit,
            },
            self.run_dir,
        )
        self.logs.write()

    def _print(self, *args) -> None:
        if self.dist.main:
            print(*args)

    # -- one step ---------------------------------------------------------------------------

    def train_step(self) -> dict[str, float] | None:
        """One optimiser step on this rank's share of the next global batch; its scalars, or None if skipped."""
        batch = self.sampler.sample()[self.rows].to(self.device, non_blocking=True)
        use_amp = self.opt_cfg["amp"] and self.device.type == "cuda"
        with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=use_amp):
            out = self.model(batch)
        loss = out["loss_tar"]
        self.optimizer.zero_grad(set_to_none=True)
        # Every rank runs backward every step (DDP's gradient all-reduce happens there), so a
        # non-finite loss on one rank is seen by all of them, through the gradients and the flag.
        loss.backward()
        clip = self.opt_cfg["grad_clip"] if self.opt_cfg["grad_clip"] > 0 else math.inf
        grad_norm = torch.nn.utils.clip_grad_norm_(self.params, clip)
        finite = self.dist.all_true(bool(torch.isfinite(loss)) and bool(torch.isfinite(grad_norm)))
        self.step += 1
        if not finite:
            self.skipped += 1
            self.optimizer.zero_grad(set_to_none=True)
            self.scheduler.step()
            if self.skipped > self.opt_cfg["skip_nonfinite"]:
                allowed = self.opt_cfg["skip_nonfinite"]
                raise TrainingError(
                    f"non-finite loss or gradient at step {self.step} of {self.steps} (loss={float(loss.detach())}; "
                    f"{self.skipped} such step(s), optim.skip_nonfinite={allowed}); {_last_checkpoint(self.run_dir)}: "
                    "start a new run with a lower optim.lr, or allow skipped steps with optim.skip_nonfinite=N"
                )
            return None
        self.optimizer.step()
        self.scheduler.step()
        if self.ema is not None:
            self.ema.update_parameters(self.policy.actor)
        logged = [*_LOGGED, *(k for k in out.keys() if isinstance(k, str) and k.startswith("aux_"))]
        scalars = {n: float(out[n].detach()) for n in logged}
        scalars["grad_norm"] = float(grad_norm)
        return scalars

    # -- evaluation and weights ------------------------------------------------------------

    def evaluate(self, step: int) -> pd.DataFrame | None:
        """Run the evaluator (sharded over ranks); rank 0 logs and returns the summary table.

        ``None`` on the other ranks, and everywhere when evaluation is off (``eval.rollouts=0``).
        """
        if self.evaluator is None:
            return None
        ema = self.ema if self.config["eval"]["use_ema"] else None
        rollouts = self.evaluator(_eval_actor(self.policy.actor, ema))
        if self.dist.active:
            parts = self.dist.all_gather_object(rollouts)
            rollouts = pd.concat(parts, ignore_index=True).sort_values(["task_id", "variation_index"])
            rollouts = rollouts.reset_index(drop=True)
        if not self.dist.main:
            return None
        table = summarize(rollouts)
        self.logs.rollouts += rollout_records(step, rollouts)
        self.logs.metrics += summary_rows(step, table)
        return table

    # -- the loop ---------------------------------------------------------------------------

    def run(self) -> pd.DataFrame | None:
        """Train from the current step to ``optim.steps``, evaluate, write the summary; rank 0 gets the table."""
        from tqdm import tqdm

        if self.dist.main:
            self.logs.write()
        every, eval_every = self.log_cfg["every"], self.config["eval"]["every"]
        tick = time.perf_counter()
        self.objective.train()
        bar = tqdm(total=self.steps, initial=self.step, desc="train", unit="step", disable=not self.progress)
        try:
            while self.step < self.steps:
                scalars = self.train_step()
                if scalars is not None:
                    sums = self.window_sums
                    self.window_sums = {k: sums.get(k, 0.0) + v for k, v in scalars.items()}
                    self.window_count += 1
                bar.update(1)
                done = self.step
                if done % every == 0 or done == self.steps:
                    now = time.perf_counter()
                    self.train_seconds += now - tick
                    tick = now
                    sums, n_ok = self.window_sums, self.window_count
                    self._log_train(done, sums, n_ok)
                    if n_ok:
                        bar.set_postfix(loss=f"{sums['loss_tar'] / n_ok:.4g}", alpha=f"{sums['tar_mix'] / n_ok:.2f}")
                    self.window_sums, self.window_count = {}, 0
                if eval_every and done % eval_every == 0 and done != self.steps:
                    self.evaluate(done)
                    tick = time.perf_counter()
                if done in self.record_at:
                    self.logs.weights += record_weights(
                        self.objective, self.episodes, self.config["data"]["slice_len"], done
                    )
                    self.objective.train()
                if done % self.log_cfg["checkpoint_every"] == 0 and done != self.steps:
                    self.train_seconds += time.perf_counter() - tick
                    tick = time.perf_counter()
                    self.checkpoint()
        finally:
            bar.close()
        self.train_seconds += time.perf_counter() - tick
        start = time.perf_counter()
        table = self.evaluate(self.steps)
        self.eval_seconds = time.perf_counter() - start
        self.fit = self.diagnose() if self.dist.main else None
        self.checkpoint(finished=True)
        return table

    def diagnose(self) -> dict:
        """The run's fit diagnostics (:func:`diagnose.fit_summary`) at the current weights."""
        slice_len = self.config["data"]["slice_len"]
        keys, device = self.policy.keys, self.device
        fit = diagnose.fit_summary(
            self.config,
            self.objective,
            self.dataset,
            self.heldout,
            self.tasks["train"],
            self.logs.metrics,
            episodes_of=lambda data, tasks, n: _demo_episodes(data, tasks, n, keys, device),
            record=lambda objective, episodes: record_weights(objective, episodes, slice_len, self.steps),
        )
        self.objective.train()
        return fit

    def _log_train(self, step: int, sums: dict[str, float], n_ok: int) -> None:
        # Extra scalar losses of the head (e.g. ACT's KL as aux_loss_kl): the same on every rank.
        names = [*_LOGGED, *sorted(n for n in sums if n.startswith("aux_")), "grad_norm"]
        totals = self.dist.all_sum([sums.get(n, 0.0) for n in names] + [float(n_ok)])
        count = totals[-1]
        if count:
            self.logs.metrics += [
                (step, "train", "loss" if n == "loss_tar" else n, v / count) for n, v in zip(names, totals[:-1])
            ]
        self.logs.metrics += [
            (step, "train", "lr", float(self.scheduler.get_last_lr()[0])),
            (step, "train", "skipped", float(self.skipped)),
        ]

    def write_summary(self, table: pd.DataFrame | None) -> None:
        config = self.config
        summary = {
            "run_name": self.run_dir.name,
            "objective": config["objective"]["name"],
            "policy": config["policy"]["name"],
            "seed": config["seed"],
            "steps": self.steps,
            "finished": True,
            "final": [
                {**rec, "neps": json_metric(rec["neps"])} for rec in table[table["level"] != "task"].to_dict("records")
            ]
            if table is not None
            else [],  # eval.rollouts=0: not evaluated
            "final_train_loss": last_metric(self.logs.metrics, "loss"),
            "fit": self.fit,
            "init": self.source.provenance() if self.source is not None else None,
            "nonfinite_steps_skipped": self.skipped,
            "train_seconds": self.train_seconds,
            "final_eval_seconds": self.eval_seconds,
            "world_size": self.dist.world,
            "config": config,
            "git_commit": self.commit,
            "machine": machine(),
            "versions": {"torch": torch.__version__, **self.dataset.metadata["versions"]},
        }
        write_json_atomic(summary, self.run_dir / "summary.json")


_LOGGED = ("loss_tar", "uniform_loss", "tar_mix", "weight_max", "weight_ess")


def _agree_across_ranks(config: dict, dist: distributed.Dist) -> None:
    """Refuse a job whose ranks were started with different settings (or an indivisible batch)."""
    if not dist.active:
        return
    settings = dist.all_gather_object(config)
    for rank, other in enumerate(settings):
        diff = identity_differences(settings[0], other)
        if diff:
            raise ConfigError(
                f"the ranks were started with different settings (rank 0 vs rank {rank}: {'; '.join(diff)})"
            )
    if config["data"]["batch_segments"] % dist.world:
        raise ConfigError(
            f"data.batch_segments={config['data']['batch_segments']} is not divisible by the {dist.world} processes"
        )


def train(cfg: Any) -> Path:
    """Run (or resume, or skip if finished) the training job; returns its run directory.

    Under ``torchrun`` (``WORLD_SIZE`` > 1) every rank calls this; see :class:`Trainer`.

    Args:
        cfg: a Hydra ``DictConfig``, a :class:`TrainConfig` or an equivalent dict.

    The run directory is locked (``tar_rl.runlock``) by rank 0 from before anything is written into
    it until the job ends, so a second job on it is refused while this one runs.

    Raises:
        ConfigError: a bad setting, an unwritable run directory, a run directory holding a
            different run, or an unreadable checkpoint; raised before any data is collected or any
            step is taken.
        RunFolderBusy: another process is running in the run directory.
        TrainingError: non-finite losses beyond ``optim.skip_nonfinite``, or no space left on
            the device (the last good checkpoint is named).
        RunInterrupted: Ctrl-C during training (the step and the last checkpoint are named).
    """
    config = resolve_config(cfg)
    tasks = validate(config)
    dist = distributed.init(_device(config["device"]).type)
    held = contextlib.ExitStack()
    try:
        _agree_across_ranks(config, dist)
        run_dir = Path(config["run_dir"] or Path(config["runs_root"]) / run_name(config))
        if dist.main:
            _prepare_run_dir(run_dir)
            held.enter_context(run_lock(run_dir))
        dist.barrier()
        resume = _check_resumable(run_dir, config)
        if resume is not None and resume.get("finished") and (run_dir / "summary.json").exists():
            if dist.main:
                print(f"{run_dir}: finished already ({resume['step']} steps); not run again")
            return run_dir
        if dist.main:
            from omegaconf import OmegaConf

            atomic_write(run_dir / "config.yaml", lambda f: f.write(OmegaConf.to_yaml(OmegaConf.create(config))))
        trainer = None
        try:
            trainer = Trainer(config, tasks, run_dir, resume, dist)
            table = trainer.run()
        except BaseException as err:
            if not interrupted(err):
                raise
            raise RunInterrupted(_interruption(run_dir, trainer)) from err
        if dist.main:
            trainer.write_summary(table)
            rollouts = config["eval"]["rollouts"]
            if table is None:
                print(f"\n{run_dir}: {trainer.steps} steps; not evaluated (eval.rollouts=0)")
            else:
                print(f"\n{run_dir}: {trainer.steps} steps, final evaluation ({rollouts} rollouts per task):")
                print_table(table)
            if trainer.skipped:
                print(
                    f"{run_dir}: {trainer.skipped} of {trainer.steps} steps were skipped for a non-finite loss or "
                    f"gradient (optim.skip_nonfinite={config['optim']['skip_nonfinite']})"
                )
        del trainer  # its DDP model goes while the group lives; the barrier then lets gloo's threads finish
        dist.barrier()
        return run_dir
    except DiskFullError as err:
        raise TrainingError(
            f"{err.what}; {_last_checkpoint(run_dir)}: free some space, then run the same command to resume"
        ) from err
    finally:
        held.close()
        distributed.shutdown(dist)


# -- Hydra entry point -------------------------------------------------------------------------


def hydra_main(argv: list[str] | None = None) -> int:
    """``tar-rl train [overrides] [--cfg job] [-m]``: Hydra parses the command line, :func:`train` runs."""
    import logging

    import hydra

    logging.getLogger("torchrl").setLevel(logging.WARNING)
    register_configs()

    @hydra.main(version_base="1.3", config_path=None, config_name=CONFIG_NAME)
    def _main(cfg) -> None:
        # A user's error ends in one line (what, where, what to do); the traceback only in debug mode.
        try:
            train(cfg)
        except TarRLError as err:
            if debug_mode():
                raise
            raise SystemExit(one_line("tar-rl train", err)) from None
        except BaseException as err:
            if debug_mode() or not interrupted(err):
                raise
            if not isinstance(err, RunInterrupted):
                err = RunInterrupted("interrupted; run the same command to start (or resume) the run")
            print(one_line("tar-rl train", err), file=sys.stderr)
            raise SystemExit(130) from None

    saved = sys.argv
    sys.argv = ["tar-rl train", *(sys.argv[2:] if argv is None else argv)]
    try:
        _main()
    finally:
        sys.argv = saved
    return 0
