"""Evaluation collector: roll a TensorDict policy out on MetaWorld v3 tasks, one table row per rollout.

Protocol (TAR paper, Sec. III-A): rollout ``k`` of a task runs on variation
``tasks.variation(task, seed, k)`` and stops at its first success or at the horizon ``H``;
``steps`` (s) counts the executed environment steps, ``rho = s / H``. Success rate, Fast20 and NEPS
are computed from these rows by ``tar_rl.metrics``.

Execution. The (task, rollout) pairs, in ``TASKS`` order, are cut into ``workers`` contiguous
shards, one worker process each (a :class:`RolloutPool`'s, kept for the job's next evaluation). A
worker runs its shard (interleaved over its tasks) on ``envs_per_worker`` slots of one batched
TorchRL env (``envs.make_batched_env``: a ``GymWrapper`` around a vector of MetaWorld envs that
steps only the running slots): the policy is called once per step on the whole batch (under
``torch.no_grad``, in eval mode). A slot whose rollout ends gets the shard's next rollout (the
next rollout of its own task if any, keeping its env; else its env swapped; then reset through
torchrl's partial ``_reset``), so batches stay full. Bare MetaWorld envs are reused by later
rollouts of their task and kept in the process for the pool's next evaluation; a new env of a
task copies the task's compiled MuJoCo model (``tasks.make_env``). Workers get the variations
from the parent when it has them, and hand back the ones they built. The ``task_id`` entry tells
each row of the batch its task.

The policy is sent to the workers by pickling: it must be picklable (an ``nn.Module``-based
``TensorDictModule`` is; a lambda inside it is not). ``workers=1`` runs in this process.

A rollout whose environment raises or becomes numerically unstable is recorded with
``success=False``, ``steps=H`` (a failure consumes the budget, as for any failed rollout) and the
reason in ``failure``; the other rollouts go on. A policy returning a wrong action shape or
non-finite actions is a bug in the policy: it raises, naming the task and step.
"""

from __future__ import annotations

import contextlib
import itertools
import math
import os
import pickle
import traceback
import warnings
from collections.abc import Iterable
from concurrent.futures.process import BrokenProcessPool
from multiprocessing.reduction import ForkingPickler

import numpy as np
import pandas as pd
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from tar_rl.collectors.metaworld import tasks
from tar_rl.collectors.metaworld.rollouts import ACTION_DIM, EnvCache, interleave, known_variations, run_shard
from tar_rl.collectors.suite import COLUMNS
from tar_rl.errors import children_ignore_sigint

__all__ = [
    "MAX_HORIZON",
    "ExpertPolicy",
    "RolloutPool",
    "available_cores",
    "default_envs_per_worker",
    "evaluate",
]

MAX_HORIZON = 500  # MetaWorld's own episode length: its envs raise past step 500
# Default batch size of a worker: each batch step costs ~0.8 ms of policy call and TorchRL
# conversion whatever the batch size (measured with a 39-256-256-4 MLP on a 2-core machine), and
# each MetaWorld env a worker builds costs ~0.14 s (its XML model). For S env steps at most, a
# batch of B envs costs ~0.8e-3 * S / B + 0.14 * B, least at B = sqrt(S * 0.8e-3 / 0.14). A
# copied env costs ~6 ms, yet larger batches (24 or 36 slots for 60 rollouts) are no faster:
# more envs per batch step run colder in the CPU caches (benchmarks/bench_eval.py).
_BATCH_STEP_OVERHEAD_S = 0.8e-3
_ENV_BUILD_S = 0.14
_MIN_BATCH, _MAX_BATCH = 4, 32


def default_envs_per_worker(rollouts: int, horizon: int) -> int:
    """The batch size that balances per-step overhead against env construction for a worker's shard."""
    best = math.sqrt(rollouts * horizon * _BATCH_STEP_OVERHEAD_S / _ENV_BUILD_S)
    return max(1, min(rollouts, max(_MIN_BATCH, min(_MAX_BATCH, round(best)))))


class ExpertPolicy(TensorDictModuleBase):
    """MetaWorld's scripted experts as a TensorDict policy: ``observation``, ``task_id`` -> ``action``.

    Each row of the batch gets the expert of its own task (looked up from ``task_id``), applied to
    its observation; actions are clipped to the action box [-1, 1]. Picklable.
    """

    in_keys = ["observation", "task_id"]
    out_keys = ["action"]

    def __init__(self):
        super().__init__()
        self._experts: dict[int, object] = {}

    def _expert(self, task_id: int):
        if task_id not in self._experts:
            if not 0 <= task_id < len(tasks.TASKS):
                raise ValueError(f"ExpertPolicy: task_id {task_id} is not a MetaWorld task index (0..49)")
            self._experts[task_id] = tasks.expert(tasks.TASKS[task_id])
        return self._experts[task_id]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs = tensordict.get("observation")
        ids = tensordict.get("task_id")
        flat_obs = obs.reshape(-1, obs.shape[-1]).double().numpy()
        flat_ids = ids.reshape(-1).tolist()
        with warnings.catch_warnings():  # the experts warn on every action outside [-1, 1]; they are clipped here
            warnings.filterwarnings("ignore", "Constant\\(s\\) may be too high", UserWarning)
            actions = np.stack([self._expert(i).get_action(o) for i, o in zip(flat_ids, flat_obs)])
        action = torch.from_numpy(np.clip(actions, -1.0, 1.0).astype(np.float32))
        tensordict.set("action", action.reshape(*obs.shape[:-1], ACTION_DIM))
        return tensordict


def _check_args(policy, rollouts_per_task, horizon, workers, envs_per_worker) -> None:
    if not isinstance(policy, TensorDictModuleBase):
        raise TypeError(
            f"policy must be a TensorDictModule (reading 'observation', writing 'action'), got {type(policy).__name__}"
        )
    for name, value, low, high in (
        ("rollouts_per_task", rollouts_per_task, 1, None),
        ("horizon", horizon, 1, MAX_HORIZON),
        ("workers", workers, 1, None),
        ("envs_per_worker", envs_per_worker, 1, None),
    ):
        if value is None and name in ("workers", "envs_per_worker"):
            continue
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
            raise TypeError(f"{name} must be an int, got {value!r}")
        if value < low or (high is not None and value > high):
            bounds = f"between {low} and {high}" if high is not None else f">= {low}"
            raise ValueError(f"{name} must be {bounds}, got {value}")


def available_cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def evaluate(
    policy: TensorDictModuleBase,
    tasks_spec: str | Iterable[str],
    rollouts_per_task: int = 50,
    seed: int = 1000,
    horizon: int = MAX_HORIZON,
    workers: int | None = None,
    envs_per_worker: int | None = None,
    progress: bool = True,
    shard: tuple[int, int] = (0, 1),
    image_size: int = 0,
    pool: RolloutPool | None = None,
) -> pd.DataFrame:
    """Evaluate ``policy`` on ``tasks_spec`` (see ``tasks.resolve_tasks``); one row per rollout (``COLUMNS``).

    Args:
        policy: a picklable TensorDictModule reading ``observation`` (float32 [..., 39]) and optionally
            ``task_id`` (int64), writing ``action`` ([..., 4], finite; the env clips it to [-1, 1]).
        tasks_spec: task and group names.
        rollouts_per_task: rollouts per task; rollout ``k`` uses ``tasks.variation(task, seed, k)``.
        seed: base seed of the variations (the paper uses 1000).
        horizon: step budget H (1..500).
        workers: processes (default: every available core, at most one per batch of rollouts);
            1 runs in this process.
        envs_per_worker: rollouts batched together in a worker (default: ``default_envs_per_worker``
            of the largest shard, 4..32).
        progress: show a tqdm bar over rollouts.
        shard: ``(index, count)``: run only the rollouts ``index, index + count, ...`` of the
            (task, rollout) list, e.g. one share per process of a distributed job. The rows of
            the ``count`` shards, concatenated and sorted by ``task_id`` and ``variation_index``,
            are the rows of the whole evaluation (each rollout depends only on its variation).
        image_size: ``S > 0``: the policy also reads ``pixels`` (``[N, 3, S, S]`` uint8), the
            camera image of each slot's current observation (:mod:`tar_rl.collectors.metaworld.render`).
            Rendering runs in worker processes (at least one) started with ``MUJOCO_GL=egl``
            unless it is set.
        pool: the :class:`RolloutPool` of the job's evaluations (its worker processes and idle envs
            serve this call and the next ones); default: a pool of this call alone, closed before it returns.

    Rows are ordered by task (``TASKS`` order) then rollout, whatever the number of workers.
    """
    if pool is not None and pool.closed:
        raise ValueError("evaluate: the RolloutPool is closed")
    _check_args(policy, rollouts_per_task, horizon, workers, envs_per_worker)
    shards, batch = _plan(tasks_spec, rollouts_per_task, horizon, workers, envs_per_worker, shard)
    if not shards:
        return pd.DataFrame([], columns=list(COLUMNS))
    if isinstance(image_size, bool) or not isinstance(image_size, int) or image_size < 0:
        raise ValueError(f"image_size must be a non-negative integer (0: no images), got {image_size!r}")
    if image_size:
        from tar_rl.collectors.metaworld.render import headless_gl

        headless_gl()  # before the worker processes start: MuJoCo reads it when imported

    from tqdm import tqdm

    with contextlib.ExitStack() as stack:
        if pool is None:
            pool = stack.enter_context(RolloutPool())
        bar = stack.enter_context(
            tqdm(total=sum(map(len, shards)), desc="evaluate", unit="rollout", disable=not progress)
        )
        if len(shards) == 1 and not image_size:
            rows = run_shard(policy, shards[0], seed, horizon, batch, pool.envs, bar.update)
        else:
            rows = pool._run(policy, shards, seed, horizon, batch, image_size, bar.update)
    rows.sort(key=lambda row: (row["task_id"], row["variation_index"]))
    return pd.DataFrame(rows, columns=list(COLUMNS))


def _plan(tasks_spec, rollouts_per_task, horizon, workers, envs_per_worker, shard) -> tuple[list[list], int]:
    """The (task, k) pairs of this ``shard`` cut into one interleaved list per worker, and the batch size."""
    index, count = shard
    if not (isinstance(count, int) and count >= 1 and isinstance(index, int) and 0 <= index < count):
        raise ValueError(f"shard must be (index, count) with 0 <= index < count, got {shard!r}")
    names = tasks.resolve_tasks(tasks_spec)
    jobs = [(task, k) for task in names for k in range(rollouts_per_task)][index::count]
    if not jobs:
        return [], 0
    if workers is None:
        workers = max(1, min(available_cores(), math.ceil(len(jobs) / _MIN_BATCH)))
    workers = min(workers, len(jobs))
    batch = envs_per_worker or default_envs_per_worker(math.ceil(len(jobs) / workers), horizon)
    bounds = np.linspace(0, len(jobs), workers + 1).round().astype(int)
    return [interleave(jobs[a:b]) for a, b in itertools.pairwise(bounds) if b > a], batch


class RolloutPool:
    """The evaluation worker processes of a job and the bare MetaWorld envs kept between its evaluations.

    A training job evaluates every few thousand steps; starting a process and importing torch takes
    seconds, building a MetaWorld env ~0.14 s. Whoever runs a job's evaluations (the training job,
    ``tar-rl eval``, a benchmark) creates one pool, passes it to each :func:`evaluate` call and closes it
    at the end::

        with RolloutPool() as pool:
            early = evaluate(policy, "mt10", pool=pool)
            final = evaluate(policy, "mt10", pool=pool)  # the same processes, envs and variations

    Worker processes ('spawn' context, one torch thread, Ctrl-C ignored: see
    ``tar_rl.errors.children_ignore_sigint``) start at the first evaluation that needs them and are
    replaced when one asks for another number of them or runs under another ``MUJOCO_GL`` (MuJoCo
    reads it once, when a worker imports it), when one of them has died, and after an interrupted
    evaluation. Each worker keeps its own idle envs and variations; ``envs`` holds the ones of the
    evaluations run in this process (``workers=1``).

    ``close()``, or leaving the ``with`` block (an exception included), ends the workers and closes the
    envs; a closed pool refuses evaluations. A worker also exits when its pipe to this process
    closes, so none outlives a killed parent, and is daemonic, so none outlives a parent that exits
    without closing its pool.
    """

    #: Seconds an idle worker gets to close its envs and exit before it is terminated.
    exit_timeout = 10.0

    def __init__(self) -> None:
        self.envs = EnvCache()
        self._workers: list[_Worker] = []
        self._gl: str | None = None
        self._closed = False

    def __enter__(self) -> RolloutPool:
        if self._closed:
            raise ValueError("the RolloutPool is closed")
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def closed(self) -> bool:
        """Whether ``close()`` was called."""
        return self._closed

    @property
    def pids(self) -> tuple[int, ...]:
        """The process ids of the running workers (empty before the first evaluation that needs them)."""
        return tuple(worker.process.pid for worker in self._workers)

    def close(self) -> None:
        """End the worker processes and close the idle envs; the pool refuses evaluations from then on."""
        self._closed = True
        self._stop_workers()
        self.envs.clear()

    def _run(self, policy, shards, seed, horizon, batch, image_size, progress) -> list[dict]:
        """Run each shard on its own worker; the rows in shard order (raises the first shard's error, if any)."""
        # Every job is pickled before any is sent: a policy that does not pickle leaves the workers idle.
        jobs = [
            ForkingPickler.dumps((policy, shard, seed, horizon, batch, known_variations(shard, seed), image_size))
            for shard in shards
        ]
        workers = self._start_workers(len(shards))
        try:
            for worker, job in zip(workers, jobs):
                worker.send(job)
            replies = _gather(workers, progress)
        except BaseException:
            self._stop_workers()  # interrupted or a worker died: the running shards are not waited for
            raise
        rows: list[dict] = []
        for (kind, result, trace), worker in zip(replies, workers):
            if kind == "error":
                raise result from _RemoteTraceback(f"in evaluation worker {worker.process.pid}:\n{trace}")
            shard_rows, built = result
            rows.extend(shard_rows)
            tasks.add_variations(built)  # the next evaluation's workers get them
        return rows

    def _start_workers(self, n: int) -> list[_Worker]:
        gl = os.environ.get("MUJOCO_GL")
        if len(self._workers) != n or self._gl != gl or not all(w.process.is_alive() for w in self._workers):
            self._stop_workers()
            import multiprocessing as mp

            ctx = mp.get_context("spawn")
            with children_ignore_sigint():
                for _ in range(n):  # one at a time: if a start fails, close() still ends the ones started
                    self._workers.append(_Worker(ctx))
            self._gl = gl
        return self._workers

    def _stop_workers(self) -> None:
        """End the workers: an idle one closes its envs and exits, a busy one is terminated at once."""
        workers, self._workers = self._workers, []
        for worker in workers:
            if worker.busy:
                worker.process.terminate()
            worker.conn.close()  # an idle worker's recv ends: it exits
        for worker in workers:
            worker.process.join(self.exit_timeout)
            if worker.process.is_alive():
                worker.process.terminate()
                worker.process.join()


class _RemoteTraceback(Exception):
    """The traceback of a worker's error, as text (the ``__cause__`` of the error raised here)."""

    def __str__(self) -> str:
        return str(self.args[0])


class _Worker:
    """One worker process (running ``_serve``) and this process's end of the pipe to it."""

    def __init__(self, ctx) -> None:
        self.conn, there = ctx.Pipe()
        self.process = ctx.Process(target=_serve, args=(there,), name="tar-rl-evaluate", daemon=True)
        self.process.start()
        there.close()  # the worker holds the only other end: it reads EOF once this process closes its own
        self.busy = False  # a job was sent whose reply is not read yet

    def send(self, job: bytes) -> None:
        self.busy = True
        self.conn.send_bytes(job)


def _gather(workers: list[_Worker], progress) -> list[tuple]:
    """Each worker's reply ``(kind, result, traceback)`` to its job; its progress messages go to ``progress``."""
    from multiprocessing.connection import wait

    replies: list = [None] * len(workers)
    waiting = {worker.conn: i for i, worker in enumerate(workers)}
    while waiting:
        for conn in wait(list(waiting)):
            i = waiting[conn]
            try:
                message = conn.recv()
            except EOFError:  # the worker ended without replying
                process = workers[i].process
                process.join(1.0)
                raise BrokenProcessPool(
                    f"evaluation worker {process.pid} ended while running its rollouts (exit code {process.exitcode})"
                ) from None
            if message[0] == "progress":
                progress(message[1])
                continue
            workers[i].busy = False
            replies[i] = message
            del waiting[conn]
    return replies


def _serve(conn) -> None:
    """A worker process: run each job received on ``conn``, send back its progress and its reply, until EOF.

    A job is ``(policy, shard, seed, horizon, batch, variations, image_size)``; the reply is
    ``("done", (rows, variations of the shard), "")`` or ``("error", exception, traceback text)``. The
    idle envs of the process (``EnvCache``) serve the next jobs.
    """
    torch.set_num_threads(1)
    envs = EnvCache()
    try:
        while True:
            try:
                job = conn.recv_bytes()
            except EOFError:  # the pool closed, or its process ended
                return
            conn.send(_run_job(job, envs, lambda n: conn.send(("progress", n))))
    finally:
        envs.clear()


def _run_job(job: bytes, envs: EnvCache, progress) -> tuple:
    try:
        policy, shard, seed, horizon, batch, variations, image_size = pickle.loads(job)
        tasks.add_variations(variations)
        rows = run_shard(policy, shard, seed, horizon, batch, envs, progress, image_size=image_size)
        return "done", (rows, known_variations(shard, seed)), ""
    except Exception as err:
        trace = traceback.format_exc()
        try:
            pickle.loads(ForkingPickler.dumps(err))
        except Exception:  # an error that does not pickle (or unpickle) goes back as its text
            err = RuntimeError(f"{type(err).__name__}: {err}")
        return "error", err, trace
