"""The rollouts of one evaluation shard in one process: batched TorchRL environments over MetaWorld envs, slots
refilled as rollouts end, one row per rollout (:mod:`.evaluate` describes the protocol and runs the shards,
in this process or on a :class:`~tar_rl.collectors.metaworld.evaluate.RolloutPool`'s workers).

``run_shard`` runs a shard's (task, rollout) pairs on at most ``batch`` slots of one batched env
(``envs.make_batched_env``); ``EnvCache`` keeps a process's idle bare envs for later rollouts and
evaluations; ``interleave`` orders a shard round-robin over its tasks and ``Pending`` hands out its next
rollout per slot; ``known_variations`` are the task variations a process holds, sent to workers so they
need not build them again.
"""

from __future__ import annotations

import collections

import numpy as np
import torch

from tar_rl.collectors.metaworld import tasks
from tar_rl.collectors.metaworld.envs import make_batched_env

__all__ = ["ACTION_DIM", "EnvCache", "Pending", "interleave", "known_variations", "run_shard"]

ACTION_DIM = 4


def interleave(shard: list) -> list:
    """Order a shard's (task, k) pairs round-robin over its tasks.

    A batch then holds a few rollouts of each of the shard's tasks, and each task needs only about
    ``batch / n_tasks`` environments for the whole shard instead of ``batch``: building a MetaWorld
    env (~0.15 s, its XML model) would otherwise cost about as much as the TorchRL overhead.
    """
    by_task: dict[str, list] = {}
    for job in shard:
        by_task.setdefault(job[0], []).append(job)
    columns = list(by_task.values())
    return [col[i] for i in range(max(map(len, columns))) for col in columns if i < len(col)]


def _variation_keys(shard, seed) -> set[tuple[str, int]]:
    return {(task, seed + k // tasks.VARIATIONS_PER_SEED) for task, k in shard}


def known_variations(shard, seed) -> dict:
    """The variations of ``shard`` this process holds: a worker receives them instead of building ``MT1``."""
    return tasks.cached_variations(_variation_keys(shard, seed))


class EnvCache:
    """Idle bare MetaWorld envs of one process, kept between evaluations, per (env factory, task).

    At most ``limit`` envs in all. Keyed by the factory so that a replaced ``tasks.make_env`` (tests
    inject failing envs that way) never mixes with others.
    """

    limit = 64

    def __init__(self) -> None:
        self._idle: dict[tuple, list] = {}

    def __len__(self) -> int:
        return sum(map(len, self._idle.values()))

    def take(self, factory, task: str):
        """An idle env of ``task`` built by ``factory``, or None."""
        idle = self._idle.get((factory, task))
        return idle.pop() if idle else None

    def put(self, factory, task: str, env) -> None:
        """Keep ``env`` for a later evaluation (closed instead when ``limit`` envs are kept)."""
        if len(self) < self.limit:
            self._idle.setdefault((factory, task), []).append(env)
        else:
            env.close()

    def clear(self) -> None:
        """Close the kept envs."""
        for envs in self._idle.values():
            for env in envs:
                env.close()
        self._idle.clear()


class _EnvPool:
    """Bare MetaWorld envs of a shard: reused by later rollouts of their task, kept for the next call.

    An env is taken from the shard's free envs of its task, else from the process's idle envs
    (``cache``), else built (``tasks.make_env``: a copy of the task's compiled model after the first).
    Reusing an env is safe: ``set_task`` + ``reset`` put it in the state a fresh env starts in
    (tested). An env whose rollout failed is closed, never reused.
    """

    def __init__(self, jobs, cache: EnvCache):
        self._factory = tasks.make_env
        self._cache = cache
        self._free: dict[str, list] = {}
        self._left = collections.Counter(task for task, _ in jobs)  # rollouts not yet started, per task
        self.built = 0

    def acquire(self, task: str):
        self._left[task] -= 1
        free = self._free.setdefault(task, [])
        if free:
            return free.pop()
        idle = self._cache.take(self._factory, task)
        if idle is not None:
            return idle
        self.built += 1
        return self._factory(task)

    def keep(self, task: str) -> None:
        """A slot keeps its env of ``task`` for the task's next rollout."""
        self._left[task] -= 1

    def release(self, task: str, env) -> None:
        if self._left[task] > 0:
            self._free[task].append(env)
        else:  # no rollout of this task left in the shard
            self._cache.put(self._factory, task, env)

    def close(self) -> None:
        for task, envs in self._free.items():
            for env in envs:
                self._cache.put(self._factory, task, env)
        self._free.clear()


def run_shard(policy, shard, seed, horizon, batch, envs: EnvCache, progress, image_size=0) -> list[dict]:
    was_training = policy.training
    policy.eval()
    pool = _EnvPool(shard, envs)
    render = None
    if image_size:
        from tar_rl.collectors.metaworld.render import PixelRenderer

        render = PixelRenderer(image_size)
    try:
        with torch.no_grad():
            return _run_slots(policy, shard, seed, horizon, min(batch, len(shard)), pool, progress, render)
    finally:
        pool.close()
        if render is not None:
            render.close()
        policy.train(was_training)


def _row(task, k, seed, horizon, success, steps, total, failure) -> dict:
    return {
        "task": task,
        "task_id": tasks.task_index(task),
        "group": tasks.group_of(task),
        "variation_seed": seed + k // tasks.VARIATIONS_PER_SEED,
        "variation_index": k,
        "success": bool(success),
        "steps": int(steps),
        "rho": float(steps) / horizon,
        "return": float(total),
        "failure": failure,
    }


class Pending:
    """The rollouts of a shard not yet started: the next one in shard order, or the next one of a task."""

    def __init__(self, shard):
        self._order = collections.deque(shard)
        self._by_task: dict[str, collections.deque] = {}
        for task, k in shard:
            self._by_task.setdefault(task, collections.deque()).append(k)
        self._left = len(shard)

    def __bool__(self) -> bool:
        return self._left > 0

    def has(self, task: str) -> bool:
        return bool(self._by_task.get(task))

    def pop(self, task: str | None = None) -> tuple[str, int]:
        """The next rollout (of ``task`` if given) as ``(task, k)``; rollouts of a task start in order of ``k``."""
        if task is None:
            while not self._by_task[self._order[0][0]]:  # its task's rollouts were all taken already
                self._order.popleft()
            task = self._order.popleft()[0]
        self._left -= 1
        return task, self._by_task[task].popleft()


def _run_slots(policy, shard, seed, horizon, n, pool: _EnvPool, progress, render=None) -> list[dict]:
    """Run the rollouts ``shard`` ((task, k) pairs) on ``n`` batched env slots.

    Each step, the policy is called once on the whole batch and the running slots are stepped.
    A slot whose rollout ends (first success, failure, horizon) gets the shard's next rollout of
    the same task if there is one (its env stays, ``set_task`` on the new variation), else the
    shard's next rollout (its env swapped for one of the new task); then it is reset through
    torchrl's partial reset (a ``_reset`` mask), so the batch stays full until the shard runs out
    instead of waiting for its slowest rollout. Which slot runs a rollout never changes its row.
    With ``render`` the policy also gets ``pixels``, the image of each running slot's observation.
    """
    pending = Pending(shard)
    slot = [pending.pop() for _ in range(n)]
    bare = []
    for task, k in slot:
        env = pool.acquire(task)
        env.set_task(tasks.variation(task, seed, k))
        bare.append(env)
    env, vec = make_batched_env(bare, [task for task, _ in slot])
    count = np.zeros(n, dtype=np.int64)
    returns = np.zeros(n, dtype=np.float64)
    running = np.ones(n, dtype=bool)
    rows = []
    td = env.reset()
    while running.any():
        if render is not None:
            td.set("pixels", _pixels(render, vec.envs, running))
        td = policy(td)
        _check_action(td.get("action", None), slot, running, count + 1)
        vec.active = running.copy()
        nxt = env.step(td).get("next")
        reward = nxt.get("reward").reshape(n).numpy()
        hit = nxt.get("success").reshape(n).numpy()
        done = nxt.get("done").reshape(n).numpy()
        count[running] += 1
        returns[running] += reward[running]
        restart = np.zeros(n, dtype=bool)
        # done: MetaWorld's own truncation, only at step 500 (the largest horizon). One vectorised
        # test per batch step; the Python loop below visits only the slots whose rollout ended.
        failed = np.fromiter(map(bool, vec.failures), dtype=bool, count=n)
        for i in np.flatnonzero(running & (failed | hit | done | (count >= horizon))):
            failure = vec.failures[i]
            task, k = slot[i]
            success = bool(hit[i]) and not failure
            rows.append(_row(task, k, seed, horizon, success, count[i] if success else horizon, returns[i], failure))
            progress(1)
            if pending and not failure and pending.has(task):
                # The slot's env stays: a new variation of the same task, no env swapped.
                slot[i] = task, k = pending.pop(task)
                pool.keep(task)
                vec.envs[i].set_task(tasks.variation(task, seed, k))
                vec.replace(i, vec.envs[i], tasks.task_index(task))
                count[i], returns[i] = 0, 0.0
                restart[i] = True
                continue
            if failure:  # its simulation state is not trusted for another rollout
                vec.envs[i].close()
            elif pending:  # (else the env stays in its slot until the end)
                pool.release(task, vec.envs[i])
            if pending:
                slot[i] = task, k = pending.pop()
                new = pool.acquire(task)
                new.set_task(tasks.variation(task, seed, k))
                vec.replace(i, new, tasks.task_index(task))
                count[i], returns[i] = 0, 0.0
                restart[i] = True
            else:
                running[i] = False
        if restart.any():
            nxt.set("_reset", torch.from_numpy(restart).unsqueeze(-1))
            td = env.reset(nxt)
        else:
            td = nxt
    for i, (task, _) in enumerate(slot):
        if not vec.failures[i]:  # (a failed slot's env was closed above)
            pool.release(task, vec.envs[i])
    return rows


def _pixels(render, envs, running) -> torch.Tensor:
    """``[N, 3, S, S]`` uint8: the running slots' images, zeros for the others (their envs may be closed)."""
    out = np.zeros((len(envs), 3, render.size, render.size), np.uint8)
    for i in np.flatnonzero(running):
        out[i] = render(envs[i])
    return torch.from_numpy(out)


def _check_action(action, slot, running, step) -> None:
    n = len(slot)
    if not isinstance(action, torch.Tensor):
        raise RuntimeError(
            f"the policy wrote no 'action' tensor (got {type(action).__name__}) at step {int(step.max())} "
            f"of tasks {sorted({task for task, _ in slot})}"
        )
    if tuple(action.shape) != (n, ACTION_DIM):
        raise ValueError(
            f"the policy returned actions of shape {tuple(action.shape)} at step {int(step[running].max())} of "
            f"tasks {sorted({task for task, _ in slot})}; expected ({n}, {ACTION_DIM}): one {ACTION_DIM}-d action "
            "per environment"
        )
    if bool(torch.isfinite(action).all()):  # the usual case: one reduction, no per-slot test
        return
    finite = torch.isfinite(action).all(-1).numpy()
    bad = np.flatnonzero(running & ~finite)
    if bad.size:
        where = ", ".join(f"{slot[i][0]} (rollout {slot[i][1]}) at step {step[i]}" for i in bad[:5])
        raise ValueError(
            f"the policy returned non-finite actions for {where}: {action[torch.as_tensor(bad[:3])].tolist()}"
        )
