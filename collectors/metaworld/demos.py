"""Scripted-expert demonstrations on MetaWorld v3 (installed as ``tar_rl.collectors.metaworld.demos``).

``collect_task`` rolls MetaWorld's scripted expert out on the variations ``tasks.variation(task,
seed, j)`` for ``j = 0, 1, 2, ...`` and keeps the episodes that succeed, stopping each episode at
its FIRST success (``info["success"]``) or at the 500-step horizon. Failed episodes are counted
and discarded. The environment is clipped-action stepped: the expert's raw action can reach
+-12, and the stored supervision target ``action`` is that action clipped to the action space
``[-1, 1]`` (the raw one is kept as ``action_raw``).

``collect`` shards a list of tasks over independent worker processes (one task per job, the
``spawn`` start method, one torch thread per worker), shows a progress bar per finished task
and prints a summary. Results come back as numpy arrays, one :class:`TaskDemos` per task.

The per-step loop writes into preallocated numpy arrays and does nothing else in Python, so that
collection runs at nearly the bare expert-rollout rate.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import sys
import time
import warnings
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field

import numpy as np

from tar_rl.collectors.metaworld import tasks as _tasks
from tar_rl.errors import children_ignore_sigint

__all__ = [
    "ACTION_DIM",
    "HORIZON",
    "OBS_DIM",
    "TaskDemos",
    "collect",
    "collect_task",
    "default_max_attempts",
    "demos_arrays",
    "demos_from_arrays",
]

HORIZON = 500  # MetaWorld v3's episode length: step 500 returns truncated=True, step 501 raises
OBS_DIM = 39
ACTION_DIM = 4


def default_max_attempts(n_demos: int) -> int:
    """Episodes tried per task before giving up: ``3 * n_demos + 5``."""
    return 3 * n_demos + 5


@dataclass
class TaskDemos:
    """The kept (successful) demonstrations of one task, concatenated episode after episode.

    ``N`` is the total number of steps, ``E`` the number of kept episodes.

    Attributes:
        task: the MetaWorld v3 task name.
        observation: ``[N, 39]`` float32, the observation the expert acted on.
        action_raw: ``[N, 4]`` float32, the expert's unclipped action.
        action: ``[N, 4]`` float32, ``clip(action_raw, -1, 1)``: the action the env executed and
            the supervision target.
        next_observation: ``[N, 39]`` float32.
        reward: ``[N]`` float32.
        terminated: ``[N]`` bool, True on the step that first reached success (each episode's last).
        truncated: ``[N]`` bool, True on step 500 (the horizon).
        step: ``[N]`` int64, the step index within its episode (0-based).
        lengths: ``[E]`` int64, episode lengths (sum = ``N``).
        variation_index: ``[E]`` int64, ``j`` in ``tasks.variation(task, seed, j)``.
        variation_seed: ``[E]`` int64, the MT1 seed that variation comes from.
        seed: the base seed.
        attempts: episodes rolled out (kept + rejected).
        rejected: failed episodes (no success within the horizon), discarded.
        rejected_index: the ``j`` of the rejected episodes.
        env_steps: environment steps taken, rejected episodes included.
        seconds: wall time of the collection in the worker.
        pixels: ``[N, 3, S, S]`` uint8 images of ``observation`` (``collect_task(image_size=S)``,
            see :mod:`tar_rl.collectors.metaworld.render`), or ``None``.
    """

    task: str
    observation: np.ndarray
    action_raw: np.ndarray
    action: np.ndarray
    next_observation: np.ndarray
    reward: np.ndarray
    terminated: np.ndarray
    truncated: np.ndarray
    step: np.ndarray
    lengths: np.ndarray
    variation_index: np.ndarray
    variation_seed: np.ndarray
    seed: int
    attempts: int
    rejected: int
    rejected_index: list[int] = field(default_factory=list)
    env_steps: int = 0
    seconds: float = 0.0
    pixels: np.ndarray | None = None

    @property
    def kept(self) -> int:
        """Number of kept episodes."""
        return len(self.lengths)

    @property
    def steps(self) -> int:
        """Number of stored steps."""
        return len(self.step)


_ARRAYS = (
    "observation",
    "action_raw",
    "action",
    "next_observation",
    "reward",
    "terminated",
    "truncated",
    "step",
    "lengths",
    "variation_index",
    "variation_seed",
)
_NUMBERS = {"seed": int, "attempts": int, "rejected": int, "env_steps": int, "seconds": float}


def demos_arrays(results: Mapping[str, TaskDemos]) -> dict[str, np.ndarray]:
    """The demonstrations of every task as named arrays (what ``np.savez`` stores), in task order; read back by
    :func:`demos_from_arrays`."""
    out = {"tasks": np.array(list(results))}
    for i, r in enumerate(results.values()):
        out |= {f"t{i}_{name}": getattr(r, name) for name in _ARRAYS}
        out |= {f"t{i}_{name}": np.asarray(getattr(r, name)) for name in _NUMBERS}
        out[f"t{i}_rejected_index"] = np.asarray(r.rejected_index, dtype=np.int64)
        if r.pixels is not None:
            out[f"t{i}_pixels"] = r.pixels
    return out


def demos_from_arrays(arrays: Mapping[str, np.ndarray]) -> dict[str, TaskDemos]:
    """The demonstrations :func:`demos_arrays` stored, by task.

    Raises:
        KeyError: an array is missing.
    """
    out = {}
    for i, task in enumerate(str(t) for t in arrays["tasks"]):
        out[task] = TaskDemos(
            task=task,
            **{name: arrays[f"t{i}_{name}"] for name in _ARRAYS},
            **{name: kind(arrays[f"t{i}_{name}"]) for name, kind in _NUMBERS.items()},
            rejected_index=arrays[f"t{i}_rejected_index"].tolist(),
            pixels=arrays[f"t{i}_pixels"] if f"t{i}_pixels" in arrays else None,
        )
    return out


def _check_positive_int(name: str, value) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ValueError(f"{name} must be a positive integer, got {value!r}.")
    return int(value)


def _check_seed(seed) -> int:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}.")
    return int(seed)


def _rollout(env, policy, buf: dict[str, np.ndarray], render=None) -> tuple[int, bool]:
    """One expert episode into the preallocated buffers; returns (length, succeeded).

    With ``render`` (a :class:`~tar_rl.collectors.metaworld.render.PixelRenderer`), ``buf["pix"][t]`` gets
    the image of observation ``t``.
    """
    obs_buf, raw_buf, act_buf, rew_buf = buf["obs"], buf["raw"], buf["act"], buf["rew"]
    pix_buf = buf.get("pix")
    obs, _ = env.reset()
    obs_buf[0] = obs
    if render is not None:
        pix_buf[0] = render(env)
    get_action = policy.get_action
    step = env.step
    for t in range(HORIZON):
        raw = get_action(obs)
        raw_buf[t] = raw
        act = np.clip(raw, -1.0, 1.0)
        act_buf[t] = act
        obs, reward, _terminated, truncated, info = step(act)
        obs_buf[t + 1] = obs
        rew_buf[t] = reward
        if info["success"]:
            return t + 1, True
        if truncated:
            return t + 1, False
        if render is not None:
            pix_buf[t + 1] = render(env)  # the image of the next step's observation
    return HORIZON, False  # unreachable: MetaWorld truncates at step 500


@contextlib.contextmanager
def _clipped_actions_unannounced() -> Iterator[None]:
    """MetaWorld's experts warn on every action outside [-1, 1] (``Constant(s) may be too high``); the actions are
    clipped here, so inside this block the warning is not shown (in this process and in spawned workers alike)."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r"Constant\(s\) may be too high", category=UserWarning)
        yield


def _task_args(task, n_demos, seed, max_attempts) -> tuple[str, int, int, int]:
    """``collect_task``'s arguments checked: one task name resolved, counts and seed as ints (``ValueError``)."""
    if not isinstance(task, str):
        raise ValueError(f"collect_task takes one task name (a str), got {task!r}.")
    resolved = _tasks.resolve_tasks([task])  # raises listing the valid names
    if len(resolved) != 1:
        raise ValueError(f"collect_task takes one task name, got the group {task!r}: use collect() for groups.")
    n_demos = _check_positive_int("n_demos", n_demos)
    seed = _check_seed(seed)
    max_attempts = default_max_attempts(n_demos) if max_attempts is None else max_attempts
    max_attempts = _check_positive_int("max_attempts", max_attempts)
    if max_attempts < n_demos:
        raise ValueError(f"max_attempts ({max_attempts}) must be >= n_demos ({n_demos}).")
    return resolved[0], n_demos, seed, max_attempts


def collect_task(
    task: str, n_demos: int, seed: int = 0, max_attempts: int | None = None, image_size: int = 0
) -> TaskDemos:
    """Roll the scripted expert out on ``task`` until ``n_demos`` episodes succeed.

    Episode ``j`` (``j = 0, 1, ...``) uses variation ``tasks.variation(task, seed, j)``; one
    environment is built and reused. Each episode stops at its first success (kept) or at the
    horizon (rejected).

    Args:
        task: a MetaWorld v3 task name (the ``-v3`` suffix is optional).
        n_demos: successful episodes to keep.
        seed: base seed of the variations.
        max_attempts: episodes to try at most; default ``3 * n_demos + 5``.
        image_size: ``S > 0`` also records ``[3, S, S]`` images of every observation (needs
            off-screen rendering: :mod:`tar_rl.collectors.metaworld.render`); 0: none.

    Returns:
        A :class:`TaskDemos` with ``n_demos`` episodes.

    Raises:
        ValueError: bad arguments or an unknown task (listing the valid names).
        RuntimeError: fewer than ``n_demos`` successes within ``max_attempts`` episodes, naming
            the task and the counts.
    """
    task, n_demos, seed, max_attempts = _task_args(task, n_demos, seed, max_attempts)
    start = time.perf_counter()
    env = _tasks.make_env(task)
    policy = _tasks.expert(task)
    buf = {
        "obs": np.empty((HORIZON + 1, OBS_DIM), np.float32),
        "raw": np.empty((HORIZON, ACTION_DIM), np.float32),
        "act": np.empty((HORIZON, ACTION_DIM), np.float32),
        "rew": np.empty((HORIZON,), np.float32),
    }
    render = None
    if image_size:
        from tar_rl.collectors.metaworld.render import PixelRenderer

        render = PixelRenderer(image_size)
        buf["pix"] = np.empty((HORIZON, 3, image_size, image_size), np.uint8)
    pixels: list[np.ndarray] = []
    episodes: list[tuple[np.ndarray, ...]] = []
    kept_index: list[int] = []
    rejected_index: list[int] = []
    j = 0
    env_steps = 0
    while len(kept_index) < n_demos and j < max_attempts:
        env.set_task(_tasks.variation(task, seed, j))
        with _clipped_actions_unannounced():
            length, ok = _rollout(env, policy, buf, render)
        env_steps += length
        if ok and render is not None:
            pixels.append(buf["pix"][:length].copy())
        if ok:
            episodes.append(
                (
                    buf["obs"][: length + 1].copy(),
                    buf["raw"][:length].copy(),
                    buf["act"][:length].copy(),
                    buf["rew"][:length].copy(),
                )
            )
            kept_index.append(j)
        else:
            rejected_index.append(j)
        j += 1
    env.close()
    if render is not None:
        render.close()
    if len(kept_index) < n_demos:
        raise RuntimeError(
            f"task {task!r}: the scripted expert succeeded in only {len(kept_index)} of {j} episodes "
            f"(seed {seed}, max_attempts={max_attempts}), {n_demos} demonstrations were asked for. "
            "Raise max_attempts or ask for fewer demonstrations."
        )

    lengths = np.array([len(e[1]) for e in episodes], dtype=np.int64)
    ends = np.cumsum(lengths)
    terminated = np.zeros(int(ends[-1]), dtype=bool)
    terminated[ends - 1] = True
    truncated = np.concatenate([np.arange(1, n + 1) == HORIZON for n in lengths])
    return TaskDemos(
        task=task,
        observation=np.concatenate([e[0][:-1] for e in episodes]),
        action_raw=np.concatenate([e[1] for e in episodes]),
        action=np.concatenate([e[2] for e in episodes]),
        next_observation=np.concatenate([e[0][1:] for e in episodes]),
        reward=np.concatenate([e[3] for e in episodes]),
        terminated=terminated,
        truncated=truncated,
        step=np.concatenate([np.arange(n, dtype=np.int64) for n in lengths]),
        lengths=lengths,
        variation_index=np.array(kept_index, dtype=np.int64),
        variation_seed=np.array([seed + k // _tasks.VARIATIONS_PER_SEED for k in kept_index], dtype=np.int64),
        seed=seed,
        attempts=j,
        rejected=len(rejected_index),
        rejected_index=rejected_index,
        env_steps=env_steps,
        seconds=time.perf_counter() - start,
        pixels=np.concatenate(pixels) if render is not None else None,
    )


def _worker_init() -> None:
    # One intra-op thread per worker. Collection itself never uses torch, so a worker does not
    # import it (~2 s); if something loads it later, OMP_NUM_THREADS makes it start with one.
    os.environ["OMP_NUM_THREADS"] = "1"
    torch = sys.modules.get("torch")
    if torch is not None:
        torch.set_num_threads(1)


def _job(args: tuple[str, int, int, int | None, int]) -> TaskDemos:
    return collect_task(*args)


def collect(
    tasks_spec: str | Iterable[str],
    n_demos: int,
    seed: int = 0,
    workers: int | None = None,
    max_attempts: int | None = None,
    *,
    image_size: int = 0,
    progress: bool = True,
    verbose: bool = True,
) -> dict[str, TaskDemos]:
    """Collect ``n_demos`` successful expert demonstrations for every task of ``tasks_spec``.

    Tasks are sharded over ``workers`` independent processes (``spawn`` start method; each
    sets ``torch.set_num_threads(1)``). ``workers`` 0 or 1 collects in this process.

    Args:
        tasks_spec: a task, group or list of them, see ``tasks.resolve_tasks``.
        n_demos: successful episodes to keep per task.
        seed: base seed of the variations (the same for every task).
        workers: processes; default ``os.cpu_count()``, never more than the number of tasks.
        max_attempts: episodes to try per task at most; default ``3 * n_demos + 5``.
        image_size: ``S > 0`` records ``[3, S, S]`` images of every observation; rendering runs in
            worker processes (at least one) started with ``MUJOCO_GL=egl`` unless set already.
        progress: show a tqdm bar advancing per finished task.
        verbose: print a summary (tasks, demos kept/rejected, steps, time).

    Returns:
        ``{task: TaskDemos}`` in ``TASKS`` order.

    Raises:
        ValueError: unknown tasks (listing the valid ones) or bad arguments, before any work.
        RuntimeError: a task whose expert did not reach ``n_demos`` successes (see ``collect_task``).
    """
    names = _tasks.resolve_tasks(tasks_spec)
    n_demos = _check_positive_int("n_demos", n_demos)
    seed = _check_seed(seed)
    if max_attempts is not None:
        _check_positive_int("max_attempts", max_attempts)
        if max_attempts < n_demos:
            raise ValueError(f"max_attempts ({max_attempts}) must be >= n_demos ({n_demos}).")
    if workers is None:
        workers = os.cpu_count() or 1
    if isinstance(workers, bool) or not isinstance(workers, (int, np.integer)) or workers < 0:
        raise ValueError(f"workers must be a non-negative integer or None, got {workers!r}.")
    workers = min(int(workers), len(names))
    if isinstance(image_size, bool) or not isinstance(image_size, (int, np.integer)) or image_size < 0:
        raise ValueError(f"image_size must be a non-negative integer (0: no images), got {image_size!r}.")
    if image_size:
        from tar_rl.collectors.metaworld.render import headless_gl

        headless_gl()
        workers = max(workers, 1)

    from tqdm.auto import tqdm

    start = time.perf_counter()
    # Longest first (harder groups have longer episodes): less idle time at the end of the pool.
    rank = {"very_hard": 0, "hard": 1, "medium": 2, "easy": 3}
    ordered = sorted(names, key=lambda n: rank[_tasks.group_of(n)])
    jobs = [(name, n_demos, seed, max_attempts, int(image_size)) for name in ordered]
    results: dict[str, TaskDemos] = {}
    bar = tqdm(total=len(names), desc="demonstrations", unit="task", disable=not progress, file=sys.stderr)
    try:
        if workers == 0 or (workers == 1 and not image_size):
            for job in jobs:
                out = _job(job)
                results[out.task] = out
                bar.update(1)
        else:
            ctx = multiprocessing.get_context("spawn")
            with children_ignore_sigint():  # Ctrl-C is reported here; leaving the block terminates the pool
                pool = ctx.Pool(workers, initializer=_worker_init)
            with pool:
                for out in pool.imap_unordered(_job, jobs):
                    results[out.task] = out
                    bar.update(1)
                    bar.set_postfix_str(out.task, refresh=False)
    finally:
        bar.close()
    elapsed = time.perf_counter() - start
    results = {name: results[name] for name in names}
    if verbose:
        kept = sum(r.kept for r in results.values())
        rejected = sum(r.rejected for r in results.values())
        steps = sum(r.steps for r in results.values())
        print(
            f"collected {len(names)} tasks: {kept} demonstrations kept, {rejected} rejected, "
            f"{steps} steps in {elapsed:.1f} s ({steps / max(elapsed, 1e-9):.0f} steps/s, "
            f"{max(workers, 1)} worker{'s' if workers > 1 else ''})"
        )
        for r in results.values():
            if r.rejected:
                print(f"  {r.task}: {r.rejected} of {r.attempts} episodes rejected (no success in {HORIZON} steps)")
    return results
