"""MetaWorld demonstration datasets: scripted-expert demonstrations (:mod:`.demos`) stored in the dataset
format of :mod:`tar_rl.data`.

``build_dataset(root, tasks, n_demos, ...)`` collects the demonstrations and writes them as the folder
``root/metaworld-demos-<key>``. The key is a hash of everything that determines the content, so a second
``build_dataset`` with the same settings loads the existing folder; a folder that fails the format's
checks is removed and built again. Demonstrations collected for a folder the disk has no room for are kept,
as collected, in ``root/.metaworld-demos-<key>.collected.npz`` where they fit: the next build of that
folder writes them instead of collecting again.

MetaWorld specifics of the stored steps: ``observation`` [39], ``action`` [4] (the expert action clipped
to [-1, 1]; ``action_raw`` unclipped), ``("next", "terminated")`` on the success step that ends every
kept episode, ``task_id`` the index in :data:`tar_rl.collectors.metaworld.tasks.TASKS` (the 50 v3 names in
alphabetical order: ``task_names`` lists all of them, so ids are global), ``pixels`` rendered by
:mod:`.render`. The metadata records every variation seed the experts tried (``variation_seeds``), which
:func:`check_disjoint` compares with the evaluation's.
"""

from __future__ import annotations

import os
import shutil
import time
import zipfile
from collections.abc import Iterable
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict

from tar_rl.data import (
    FORMAT_VERSION,
    DatasetError,
    DemoDataset,
    array_stats,
    cache_key,
    clean_temp_siblings,
    load_dataset,
    package_version,
    positive_int,
    steps_tensordict,
    write_dataset,
)
from tar_rl.errors import DiskFullError
from tar_rl.io import atomic_write, require_free_space

from . import demos as _demos
from . import tasks as _tasks

__all__ = ["NAME_PREFIX", "build_dataset", "check_disjoint"]

NAME_PREFIX = "metaworld-demos-"
KEPT_SUFFIX = ".collected.npz"
ACTION_TARGET = "expert action clipped to the action space [-1, 1]; the unclipped action is action_raw"


def _settings(
    tasks: tuple[str, ...],
    n_demos: int,
    seed: int,
    chunk_horizon: int,
    history: int,
    max_attempts: int,
    image_size: int = 0,
) -> dict:
    extra = {"image_size": image_size} if image_size else {}  # absent: the cache keys of state-only datasets
    return {
        **extra,
        "tasks": list(tasks),
        "n_demos": n_demos,
        "seed": seed,
        "chunk_horizon": chunk_horizon,
        "history": history,
        "max_attempts": max_attempts,
        "format_version": FORMAT_VERSION,
        "metaworld": package_version("metaworld"),
    }


def _to_tensordict(results: dict[str, _demos.TaskDemos], horizon: int, history: int = 1) -> TensorDict:
    """One flat ``[N]`` TensorDict of all tasks, episodes numbered in task order."""
    cat = {
        k: np.concatenate([getattr(r, k) for r in results.values()])
        for k in (
            "observation",
            "action",
            "action_raw",
            "next_observation",
            "reward",
            "terminated",
            "truncated",
            "step",
        )
    }
    lengths = np.concatenate([r.lengths for r in results.values()])
    task_id = np.concatenate([np.full(r.steps, _tasks.task_index(r.task), dtype=np.int64) for r in results.values()])
    pixels = all(r.pixels is not None for r in results.values())
    data = steps_tensordict(
        observation=cat["observation"],
        action=cat["action"],
        action_raw=cat["action_raw"],
        next_observation=cat["next_observation"],
        reward=cat["reward"],
        terminated=cat["terminated"],
        truncated=cat["truncated"],
        lengths=lengths,
        task_id=task_id,
        horizon=horizon,
        history=history,
        pixels=np.concatenate([r.pixels for r in results.values()]) if pixels else None,
    )
    if not np.array_equal(data["step"].numpy(), cat["step"]):
        raise RuntimeError("the collected step indices disagree with the episode lengths")
    return data


def _metadata(settings: dict, key: str, results: dict[str, _demos.TaskDemos], data: TensorDict, secs: float) -> dict:
    import tar_rl

    seed = settings["seed"]
    per_task = {}
    for r in results.values():
        per_task[r.task] = {
            "task_id": _tasks.task_index(r.task),
            "instruction": _tasks.INSTRUCTIONS[r.task],
            "kept": r.kept,
            "rejected": r.rejected,
            "attempts": r.attempts,
            "steps": r.steps,
            "env_steps": r.env_steps,
            "variation_seeds": list(_tasks.variation_seeds(seed, r.attempts)),
            "episode_variation_index": r.variation_index.tolist(),
            "episode_variation_seed": r.variation_seed.tolist(),
            "episode_lengths": r.lengths.tolist(),
            "rejected_variation_index": list(r.rejected_index),
        }
    all_seeds = sorted({s for t in per_task.values() for s in t["variation_seeds"]})
    return {
        "format_version": FORMAT_VERSION,
        "source": "metaworld",
        "cache_key": key,
        "settings": settings,
        "tasks": list(results),
        "task_ids": {name: p["task_id"] for name, p in per_task.items()},
        "task_names": list(_tasks.TASKS),
        "instructions": {name: _tasks.INSTRUCTIONS[name] for name in _tasks.TASKS},
        "seed": seed,
        "n_demos": settings["n_demos"],
        "max_attempts": settings["max_attempts"],
        "variation_seeds": all_seeds,
        "per_task": per_task,
        "total_steps": int(data.shape[0]),
        "total_episodes": sum(p["kept"] for p in per_task.values()),
        "total_rejected": sum(p["rejected"] for p in per_task.values()),
        "chunk_horizon": settings["chunk_horizon"],
        "history": settings["history"],
        "image_size": settings.get("image_size", 0),
        "horizon": _demos.HORIZON,
        "action_target": ACTION_TARGET,
        "stats": {
            "observation": array_stats(data["observation"].numpy()),
            "action": array_stats(data["action"].numpy()),
            "action_raw": array_stats(data["action_raw"].numpy()),
        },
        "versions": {
            "tar_rl": tar_rl.__version__,
            "torch": torch.__version__,
            "torchrl": package_version("torchrl"),
            "tensordict": package_version("tensordict"),
            "metaworld": package_version("metaworld"),
            "mujoco": package_version("mujoco"),
            "numpy": np.__version__,
        },
        "collection_seconds": secs,
        "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }


def build_dataset(
    root: str | os.PathLike,
    tasks: str | Iterable[str],
    n_demos: int,
    seed: int = 0,
    chunk_horizon: int = 8,
    workers: int | None = None,
    max_attempts: int | None = None,
    *,
    history: int = 2,
    image_size: int = 0,
    progress: bool = True,
    verbose: bool = True,
) -> DemoDataset:
    """Collect (or load from the cache under ``root``) a MetaWorld demonstration dataset.

    Args:
        root: folder holding datasets; each lives in ``root/metaworld-demos-<key>``.
        tasks: tasks or groups, see ``tasks.resolve_tasks`` (errors list the valid names).
        n_demos: successful demonstrations per task.
        seed: base seed of the variations (``tasks.variation(task, seed, j)``).
        chunk_horizon: ``H`` of ``action_chunk`` (``[H, 4]`` per step).
        history: ``K`` of ``observation_history`` (``[K, 39]`` per step).
        image_size: ``S > 0`` also stores ``pixels`` (``[3, S, S]`` uint8 per step); 0: state only.
        workers: collection processes, default ``os.cpu_count()``; 0 or 1: in this process.
        max_attempts: episodes per task at most; default ``3 * n_demos + 5``.
        progress: show a progress bar while collecting.
        verbose: print a summary of the collection.

    Returns:
        The :class:`DemoDataset`.

    Raises:
        ValueError: unknown tasks or bad arguments, before any collection.
        RuntimeError: a task whose expert did not reach ``n_demos`` successes.
    """
    names = _tasks.resolve_tasks(tasks)
    n_demos = positive_int("n_demos", n_demos)
    chunk_horizon = positive_int("chunk_horizon", chunk_horizon)
    history = positive_int("history", history)
    if isinstance(image_size, bool) or not isinstance(image_size, (int, np.integer)) or image_size < 0:
        raise ValueError(f"image_size must be a non-negative integer (0: no images), got {image_size!r}.")
    image_size = int(image_size)
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}.")
    seed = int(seed)
    max_attempts = _demos.default_max_attempts(n_demos) if max_attempts is None else max_attempts
    max_attempts = positive_int("max_attempts", max_attempts)
    if max_attempts < n_demos:
        raise ValueError(f"max_attempts ({max_attempts}) must be >= n_demos ({n_demos}).")

    root = Path(root)
    settings = _settings(names, n_demos, seed, chunk_horizon, history, max_attempts, image_size)
    key = cache_key(settings)
    name = NAME_PREFIX + key
    final = root / name
    root.mkdir(parents=True, exist_ok=True)
    clean_temp_siblings(root, name)

    if final.exists():
        try:
            found = load_dataset(final)
            if found.metadata.get("cache_key") != key or found.metadata.get("settings") != settings:
                raise DatasetError(f"its metadata describes other settings ({found.metadata.get('settings')})")
            return found
        except DatasetError as err:
            print(f"dataset {final} is incomplete or corrupt ({err}); removing it and building it again")
            shutil.rmtree(final)

    kept = root / f".{name}{KEPT_SUFFIX}"
    found_kept = _read_kept(kept, key)
    if found_kept is not None:
        results, secs = found_kept
        print(f"writing the demonstrations collected earlier for {final}, kept in {kept}")
    else:
        start = time.perf_counter()
        results = _demos.collect(
            names,
            n_demos,
            seed=seed,
            workers=workers,
            max_attempts=max_attempts,
            image_size=image_size,
            progress=progress,
            verbose=verbose,
        )
        secs = time.perf_counter() - start
    data = _to_tensordict(results, chunk_horizon, history)
    try:
        written = write_dataset(root, name, data, _metadata(settings, key, results, data, secs))
    except DiskFullError as err:
        raise _keep(kept, key, results, secs, err) from None
    kept.unlink(missing_ok=True)
    return load_dataset(written)


def _keep(kept: Path, key: str, results: dict[str, _demos.TaskDemos], secs: float, err: DiskFullError) -> DiskFullError:
    """Keep the collected ``results`` in ``kept`` when the dataset found no room (``err``); the error to raise,
    naming the kept file, or ``err`` itself when there is no room for that either."""
    if not kept.exists():
        arrays = {**_demos.demos_arrays(results), "cache_key": np.array(key), "seconds": np.array(secs)}
        try:
            require_free_space(kept.parent, sum(a.nbytes for a in arrays.values()), kept)
            atomic_write(kept, lambda f: np.savez(f, **arrays), binary=True)
        except DiskFullError:
            return err
    n = sum(r.kept for r in results.values())
    note = f"the {n} collected demonstrations are kept in {kept}, which the same command writes instead of collecting"
    return DiskFullError(err.path, OSError(err.errno, err.strerror), f"{err.detail}; {note}" if err.detail else note)


def _read_kept(kept: Path, key: str) -> tuple[dict[str, _demos.TaskDemos], float] | None:
    """The demonstrations :func:`_keep` kept for the dataset ``key`` and their collection's seconds; ``None`` when
    there are none (an unreadable file, or one of other settings, is removed)."""
    if not kept.is_file():
        return None
    try:
        if not zipfile.is_zipfile(kept):
            raise ValueError("not an npz archive")
        with np.load(kept, allow_pickle=False) as arrays:
            if str(arrays["cache_key"]) == key:
                return _demos.demos_from_arrays(arrays), float(arrays["seconds"])
            why = "it holds demonstrations of other settings"
    except (OSError, KeyError, ValueError, zipfile.BadZipFile) as err:
        why = f"it cannot be read ({type(err).__name__}: {err})"
    print(f"removing {kept}: {why}; collecting again")
    kept.unlink()
    return None


def check_disjoint(dataset: DemoDataset, eval_seed: int, n_rollouts: int) -> None:
    """Raise ``ValueError`` if evaluation seeds overlap the seeds the demonstrations of ``dataset`` used.

    Args:
        dataset: a MetaWorld dataset (its metadata lists ``variation_seeds``).
        eval_seed: base seed of the evaluation variations.
        n_rollouts: evaluation episodes per task (they use ``tasks.variation_seeds(eval_seed, n_rollouts)``).
    """
    _tasks.check_disjoint(dataset.metadata["variation_seeds"], _tasks.variation_seeds(eval_seed, n_rollouts))
