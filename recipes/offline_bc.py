"""Offline behaviour cloning: the training job (typed config -> ``make_*`` builders -> one loop).

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
writes the same log files, byte for byte, as an uninterrupted run. It resumes on the data it trained on
only: the checkpoint records the dataset's content digest, and a dataset whose content differs is
refused, named. A finished run is reported and skipped, so a sweep that was stopped half way is
restarted with the same command.
"""

from __future__ import annotations

import contextlib
import copy
import math
import sys
import time
import warnings
from pathlib import Path
from typing import Any

import pandas as pd
import torch
from tensordict.nn import TensorDictModuleBase

from tar_rl import distributed
from tar_rl.collectors.suites import SUITES
from tar_rl.data import DemoDataset
from tar_rl.errors import (
    DiskFullError,
    RunInterrupted,
    TarRLError,
    debug_mode,
    interrupted,
    one_line,
    sigterm_raises,
    terminated,
)
from tar_rl.io import atomic_write, write_json_atomic
from tar_rl.metrics import summarize
from tar_rl.policies import DataInfo
from tar_rl.runlock import run_lock
from tar_rl.runs import (
    SUMMARY_FILE,
    RunLogs,
    git_commit,
    json_metric,
    last_metric,
    machine,
    print_table,
    rollout_records,
    save_checkpoint,
    summary_rows,
)

from . import diagnose, post_training
from .builders import (
    make_dataset,
    make_evaluation_pool,
    make_evaluator,
    make_objective,
    make_optimizer,
    make_policy,
    torch_device,
)
from .config import CONFIG_NAME, TrainConfig, config_dict, register_configs
from .errors import ConfigError, TrainingError
from .overrides import check_overrides
from .record import demo_episodes, record_weights
from .rundir import check_resumable, identity_differences, last_checkpoint, prepare_run_dir, run_name
from .validate import Job, check_slice_len, validate

__all__ = ["Trainer", "hydra_main", "train"]


def _eval_actor(actor: TensorDictModuleBase, ema) -> TensorDictModuleBase:
    """A CPU copy of the policy for the evaluator's worker processes (the EMA weights if given)."""
    return copy.deepcopy(ema.module if ema is not None else actor).to("cpu").eval()


# -- The job -----------------------------------------------------------------------------------


def _interruption(run_dir: Path, trainer: Trainer | None, err: BaseException) -> str:
    """Where a run stopped by Ctrl-C (or SIGTERM) stopped, and how to resume it."""
    if trainer is None:
        where = "before training started (while loading or collecting the dataset)"
    elif trainer.step < trainer.steps:
        where = f"at step {trainer.step} of {trainer.steps}"
    else:
        where = f"in the final evaluation (after step {trainer.steps})"
    what = "terminated (SIGTERM)" if terminated(err) else "interrupted"
    return f"{what} {where}; {last_checkpoint(run_dir)}: run the same command to resume"


class Trainer:
    """One training job: built from a checked :class:`Job` (its typed config and tasks), then :meth:`run` (resume,
    loop, final evaluation).

    Under ``torchrun`` every rank builds a ``Trainer``; the policy's objective is wrapped in
    ``DistributedDataParallel``; each rank draws the same global batch of ``data.batch_segments``
    segments (the sampler's generator is seeded identically) and trains on its contiguous share
    of them, so the job follows the data order of a single-process run of the same global batch.
    Rank 0 alone writes files and prints; evaluation is sharded over the ranks and gathered.
    """

    def __init__(self, job: Job, run_dir: Path, resume: dict | None, dist: distributed.Dist):
        cfg = job.config
        self.cfg, self.job, self.run_dir, self.dist = cfg, job, run_dir, dist
        self.progress = cfg.logging.progress and dist.main
        self.device = torch_device(cfg.device, dist.local_rank)
        if cfg.threads:
            torch.set_num_threads(cfg.threads)
        torch.manual_seed(cfg.seed)
        if not dist.main:
            dist.barrier()  # rank 0 collects (or finds) the dataset first; the others then load it
        self.dataset = make_dataset(cfg.data, job.train_tasks, progress=self.progress)
        self.heldout = diagnose.heldout_dataset(cfg, job.train_tasks, progress=self.progress)
        if dist.main:
            dist.barrier()
        if resume is not None:
            _check_same_data(run_dir, resume, self.dataset)
        check_slice_len(cfg.data.slice_len, self.dataset)
        if job.evaluation is not None:
            SUITES[job.suite].check_dataset(self.dataset, job.evaluation)
        self.info = DataInfo.from_metadata(self.dataset.metadata)
        self.policy = make_policy(cfg.policy, self.info)
        self.source = None
        if cfg.init.get("from"):
            self.source = post_training.load_source(cfg.init["from"])
            post_training.check_fits(self.source, cfg.policy.name, self.policy, self.info)
            if resume is None:  # a resumed run reads its own weights from its checkpoint
                post_training.apply_init(self.policy, self.source)
        self.objective = make_objective(cfg.objective, cfg.optim.steps, cfg.seed, self.policy).to(self.device)
        self.model = self.objective
        if dist.active:
            ids = [self.device.index] if self.device.type == "cuda" else None
            self.model = distributed.data_parallel(self.objective, device_ids=ids)
        self.params = [p for p in self.objective.parameters() if p.requires_grad]
        self.optimizer, self.scheduler = make_optimizer(cfg.optim, self.params)
        self.ema = None
        if cfg.optim.ema > 0:
            from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn

            decay = get_ema_multi_avg_fn(cfg.optim.ema)
            self.ema = AveragedModel(self.policy.actor, multi_avg_fn=decay, use_buffers=True)
        self.generator = torch.Generator().manual_seed(cfg.seed)
        # What the head's loss reads, and each step's position in its episode for a weighting that reads time.
        keys = None if self.policy.keys is None else (*self.policy.keys, *self.objective.time_keys)
        self.sampler = self.dataset.segments(
            cfg.data.batch_segments, cfg.data.slice_len, keys=keys, generator=self.generator
        )
        share = cfg.data.batch_segments // dist.world
        self.rows = slice(dist.rank * share, (dist.rank + 1) * share)
        self.pool = make_evaluation_pool(job.suite)  # e.g. the evaluations' worker processes, kept until run() ends
        self.evaluator = None  # no evaluation (eval.rollouts=0): training only
        if job.evaluation is not None:
            shard = (dist.rank, dist.world)
            self.evaluator = make_evaluator(
                job.evaluation, job.suite, job.eval_tasks, self.pool, progress=self.progress, shard=shard
            )
        self.steps = cfg.optim.steps
        self.record_at = {self.steps if s == -1 else s for s in cfg.logging.record_weights_at} if dist.main else set()
        self.episodes = []
        if self.record_at:
            self.episodes = demo_episodes(
                self.dataset, job.train_tasks, cfg.logging.record_episodes, self.policy.keys, self.device
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

    def checkpoint(self, summary: dict | None = None) -> None:
        """Write the whole training state (rank 0; every rank holds the same state but its logging window).

        ``summary``: the run's ``summary.json``, given once the final evaluation is done; the checkpoint is then
        the finished run's, and holds what a re-run writes if the job ends before ``summary.json`` is written.
        """
        windows = self.dist.all_gather_object({"sums": dict(self.window_sums), "count": self.window_count})
        if not self.dist.main:
            return
        ema = self.ema
        save_checkpoint(
            {
                "step": self.step,
                "finished": summary is not None,
                "summary": summary,
                "config": config_dict(self.cfg),
                "data_info": self.info.to_dict(),
                "data_digest": self.dataset.digest,
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
        use_amp = self.cfg.optim.amp and self.device.type == "cuda"
        with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=use_amp):
            out = self.model(batch)
        loss = out["loss_tar"]
        self.optimizer.zero_grad(set_to_none=True)
        # Every rank runs backward every step (DDP's gradient all-reduce happens there), so a
        # non-finite loss on one rank is seen by all of them, through the gradients and the flag.
        loss.backward()
        clip = self.cfg.optim.grad_clip if self.cfg.optim.grad_clip > 0 else math.inf
        grad_norm = torch.nn.utils.clip_grad_norm_(self.params, clip)
        finite = self.dist.all_true(bool(torch.isfinite(loss)) and bool(torch.isfinite(grad_norm)))
        self.step += 1
        if not finite:
            self.skipped += 1
            self.optimizer.zero_grad(set_to_none=True)
            with warnings.catch_warnings():  # the schedule keeps its step count; torch warns when step 1 is skipped
                warnings.filterwarnings("ignore", "Detected call of `lr_scheduler.step\\(\\)` before", UserWarning)
                self.scheduler.step()
            if self.skipped > self.cfg.optim.skip_nonfinite:
                allowed = self.cfg.optim.skip_nonfinite
                raise TrainingError(
                    f"non-finite loss or gradient at step {self.step} of {self.steps} (loss={float(loss.detach())}; "
                    f"{self.skipped} such step(s), optim.skip_nonfinite={allowed}); {last_checkpoint(self.run_dir)}: "
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
        ema = self.ema if self.cfg.eval.use_ema else None
        rollouts = self.evaluator(_eval_actor(self.policy.actor, ema))
        if self.dist.active:
            parts = self.dist.all_gather_object(rollouts)
            rollouts = pd.concat(parts, ignore_index=True).sort_values(["task_id", "variation_index"])
            rollouts = rollouts.reset_index(drop=True)
        if not self.dist.main:
            return None
        table = summarize(rollouts)
        # An evaluation replaces the rows of an earlier one at its step (a finished checkpoint that holds no
        # summary, as earlier versions wrote them, is evaluated again), so that every step is logged once.
        self.logs.rollouts = [r for r in self.logs.rollouts if r["step"] != step] + rollout_records(step, rollouts)
        kept = [r for r in self.logs.metrics if not (r[0] == step and r[1] == "eval")]
        self.logs.metrics = kept + summary_rows(step, table)
        return table

    # -- the loop ---------------------------------------------------------------------------

    def run(self) -> pd.DataFrame | None:
        """Train from the current step to ``optim.steps``, evaluate, write the summary; rank 0 gets the table.

        The evaluations' worker processes (``pool``) end with it, whatever ends it.
        """
        with self.pool:
            return self._train_and_evaluate()

    def _train_and_evaluate(self) -> pd.DataFrame | None:
        from tqdm import tqdm

        if self.dist.main:
            self.logs.write()
        every, eval_every = self.cfg.logging.every, self.cfg.eval.every
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
                    self.logs.weights += record_weights(self.objective, self.episodes, self.cfg.data.slice_len, done)
                    self.objective.train()
                # The last step is checkpointed too: the final evaluation and diagnostics never cost training.
                if done % self.cfg.logging.checkpoint_every == 0 or done == self.steps:
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
        self.summary = self.summarize(table) if self.dist.main else None
        # The final evaluation's rows and the summary go into the checkpoint together: a job that ends before
        # writing summary.json is completed from it by a re-run, never evaluated again.
        self.checkpoint(summary=self.summary)
        return table

    def diagnose(self) -> dict:
        """The run's fit diagnostics (:func:`diagnose.fit_summary`) at the current weights."""
        slice_len = self.cfg.data.slice_len
        keys, device = self.policy.keys, self.device
        fit = diagnose.fit_summary(
            self.cfg,
            self.objective,
            self.dataset,
            self.heldout,
            self.job.train_tasks,
            self.logs.metrics,
            episodes_of=lambda data, tasks, n: demo_episodes(data, tasks, n, keys, device),
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

    def summarize(self, table: pd.DataFrame | None) -> dict:
        """The run's ``summary.json``: the final evaluation ``table`` per group, diagnostics, timings, provenance."""
        cfg = self.cfg
        return {
            "run_name": self.run_dir.name,
            "objective": cfg.objective.name,
            "policy": cfg.policy.name,
            "seed": cfg.seed,
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
            "config": config_dict(cfg),
            "data": {"path": str(self.dataset.path), "digest": self.dataset.digest},
            "git_commit": self.commit,
            "machine": machine(),
            "versions": {"torch": torch.__version__, **self.dataset.metadata["versions"]},
        }


_LOGGED = ("loss_tar", "uniform_loss", "tar_mix", "weight_max", "weight_ess")


def _print_results(run_dir: Path, job: Job, table: pd.DataFrame | None, skipped: int) -> None:
    """The finished run's last lines: its final evaluation (or that there was none) and its skipped steps."""
    settings = job.config
    steps = settings.optim.steps
    if table is None:
        print(f"\n{run_dir}: {steps} steps; not evaluated (eval.rollouts=0)")
    else:
        print(f"\n{run_dir}: {steps} steps, final evaluation ({job.evaluation.rollouts} rollouts per task):")
        print_table(table)
    if skipped:
        print(
            f"{run_dir}: {skipped} of {steps} steps were skipped for a non-finite loss or gradient "
            f"(optim.skip_nonfinite={settings.optim.skip_nonfinite})"
        )


def _complete(run_dir: Path, state: dict, job: Job) -> None:
    """Complete a run that ended after its final checkpoint but before its ``summary.json``: the logs and the
    summary as that checkpoint holds them (its final evaluation included), without evaluating again."""
    logs = RunLogs(run_dir, **state["logs"])
    logs.write()
    write_json_atomic(state["summary"], run_dir / SUMMARY_FILE)
    print(f"{run_dir}: finished ({state['step']} steps) but its summary was not written; written from its checkpoint")
    final = [row for row in logs.rollouts if row["step"] == state["step"]]
    table = summarize(pd.DataFrame(final)) if final else None
    _print_results(run_dir, job, table, state["skipped"])


def _check_same_data(run_dir: Path, state: dict, dataset: DemoDataset) -> None:
    """A run resumes on the data it trained on: the dataset's content digest must be the one its checkpoint
    records (a checkpoint that records none is checked by its data description alone, in ``Trainer._restore``)."""
    recorded = state.get("data_digest")
    if recorded is not None and recorded != dataset.digest:
        raise ConfigError(
            f"{run_dir}: the dataset {dataset.path} differs from the data the run trained on (its content digest "
            f"is {dataset.digest}, the checkpoint records {recorded}); resume on that data, or start a new run in "
            "another run_dir"
        )


def _agree_across_ranks(cfg: TrainConfig, dist: distributed.Dist) -> None:
    """Refuse a job whose ranks were started with different settings (or an indivisible batch)."""
    if not dist.active:
        return
    settings = dist.all_gather_object(config_dict(cfg))
    for rank, other in enumerate(settings):
        diff = identity_differences(settings[0], other)
        if diff:
            raise ConfigError(
                f"the ranks were started with different settings (rank 0 vs rank {rank}: {'; '.join(diff)})"
            )
    if cfg.data.batch_segments % dist.world:
        raise ConfigError(
            f"data.batch_segments={cfg.data.batch_segments} is not divisible by the {dist.world} processes"
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
    job = validate(cfg)
    settings = job.config
    # The settings as the run folder holds them: its config.yaml, its name and the check made when resuming.
    config = config_dict(settings)
    dist = distributed.init(torch_device(settings.device).type)
    held = contextlib.ExitStack()
    try:
        _agree_across_ranks(settings, dist)
        run_dir = Path(settings.run_dir or Path(settings.runs_root) / run_name(config))
        if dist.main:
            prepare_run_dir(run_dir)
            held.enter_context(run_lock(run_dir))
        dist.barrier()
        resume = check_resumable(run_dir, config)
        if resume is not None and resume.get("finished") and (run_dir / SUMMARY_FILE).exists():
            if dist.main:
                print(f"{run_dir}: finished already ({resume['step']} steps); not run again")
            return run_dir
        if resume is not None and resume.get("summary") is not None:
            if dist.main:
                _complete(run_dir, resume, job)
            dist.barrier()
            return run_dir
        if dist.main:
            from omegaconf import OmegaConf

            atomic_write(run_dir / "config.yaml", lambda f: f.write(OmegaConf.to_yaml(OmegaConf.create(config))))
        trainer = None
        try:
            trainer = Trainer(job, run_dir, resume, dist)
            table = trainer.run()
        except BaseException as err:
            if not interrupted(err):
                raise
            raise RunInterrupted(_interruption(run_dir, trainer, err)) from err
        if dist.main:
            write_json_atomic(trainer.summary, run_dir / SUMMARY_FILE)
            _print_results(run_dir, job, table, trainer.skipped)
        del trainer  # its DDP model goes while the group lives; the barrier then lets gloo's threads finish
        dist.barrier()
        return run_dir
    except DiskFullError as err:
        raise TrainingError(
            f"{err.what}; {last_checkpoint(run_dir)}: free some space, then run the same command to resume"
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
            stopped = terminated(err)
            if not isinstance(err, RunInterrupted):
                what = "terminated (SIGTERM)" if stopped else "interrupted"
                err = RunInterrupted(f"{what}; run the same command to start (or resume) the run")
            print(one_line("tar-rl train", err), file=sys.stderr)
            raise SystemExit(143 if stopped else 130) from None

    args = sys.argv[2:] if argv is None else list(argv)
    if not debug_mode():  # Hydra's own report of a bad command line, in debug mode
        try:
            check_overrides(args)
        except ConfigError as err:
            raise SystemExit(one_line("tar-rl train", err)) from None
    saved = sys.argv
    sys.argv = ["tar-rl train", *args]
    try:
        with sigterm_raises():  # SIGTERM (a scheduler ending the job) stops it as Ctrl-C does
            _main()
    finally:
        sys.argv = saved
    return 0
