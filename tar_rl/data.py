"""MetaWorld demonstration datasets on disk: a TorchRL replay buffer plus a metadata file.

``build_dataset(root, tasks, n_demos, ...)`` collects scripted-expert demonstrations
(:mod:`tar_rl.collectors.demos`) and stores them, one row per environment step, in a
``TensorDictReplayBuffer`` over a ``LazyMemmapStorage`` under ``root/<name>/buffer`` (written
with ``rb.dumps``; ``rb.loads`` reads it back in place, without copying). ``metadata.json``
beside it describes the content. The folder name is a hash of everything that determines the
content, so a second ``build_dataset`` with the same settings loads the existing folder.

Datasets from other sources (:mod:`tar_rl.importers`, e.g. robomimic/LIBERO HDF5 files) use the same
layout and keys: :func:`steps_tensordict` turns episode-contiguous step arrays into the stored
``[N]`` TensorDict and :func:`write_dataset` writes a folder crash-safely; ``load_dataset`` opens
any of them.

Layout of one dataset folder::

    metaworld-demos-<key>/
        buffer/              rb.dumps(): storage/ (memmaps), storage_metadata.json, ...
        metadata.json        the description of the content
        digest.json          written last: the SHA-256 and size of every other file of the folder

Crash safety: a dataset is built in a temporary sibling folder ``.<name>.tmp-<pid>-<rand>`` and
renamed into place only when complete. A folder that fails the checks on load (missing or
unparsable metadata, missing storage files, a length that disagrees with the metadata, a file
whose content differs from ``digest.json``: an edited metadata number, a flipped byte in a memmap)
is reported, removed and rebuilt by ``build_dataset``; ``load_dataset`` raises
:class:`DatasetError` for it. The content check reads every file once per load (about 10 ms for the
default job's 6 MB dataset, well under 1% of the job's start-up: ``benchmarks/bench_data.py --sections
startup``). A folder written before datasets had a digest is checked as before and gets its
``digest.json`` on its first load (trust on first use).

Keys per step (``N`` steps, chunk horizon ``H``):

* ``observation`` [39] float32, ``action`` [4] float32 (the expert action clipped to [-1, 1]:
  the supervision target), ``action_raw`` [4] float32 (unclipped),
* ``("next", "observation")`` [39] float32, ``("next", "reward")`` [1] float32,
  ``("next", "done")``, ``("next", "terminated")``, ``("next", "truncated")`` [1] bool
  (``terminated`` on the success step that ends every kept episode),
* ``episode`` int64 (global id, contiguous in storage), ``task_id`` int64
  (``tasks.task_index``), ``step`` int64 (index within the episode),
* ``action_chunk`` [H, 4] float32: the clipped actions ``t .. t+H-1`` of the same episode, past
  the episode end the last action repeated; ``action_chunk_valid`` [H] bool, True on real steps.
* ``observation_history`` [K, 39] float32: the observations ``t-K+1 .. t`` of the same episode,
  oldest first (the last entry is ``observation``), before the episode start the first
  observation repeated; ``observation_history_valid`` [K] bool, True on real steps (K: ``history``,
  for heads that read a window of past observations).
* ``pixels`` [3, S, S] uint8, only in datasets built with ``image_size=S > 0``: the camera image of
  ``observation`` (:mod:`tar_rl.collectors.render`).
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import json
import os
import shutil
import time
import uuid
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict
from torchrl.data import LazyMemmapStorage, SliceSampler, TensorDictReplayBuffer, TensorStorage

from tar_rl.collectors import demos as _demos
from tar_rl.collectors import tasks as _tasks
from tar_rl.errors import TarRLError
from tar_rl.io import write_json_atomic

__all__ = [
    "FORMAT_VERSION",
    "DatasetError",
    "DemoDataset",
    "SegmentSampler",
    "array_stats",
    "build_dataset",
    "cache_key",
    "check_content",
    "clean_temp_siblings",
    "content_digest",
    "load_dataset",
    "package_version",
    "positive_int",
    "steps_tensordict",
    "write_dataset",
]

FORMAT_VERSION = 2  # 2: observation_history
METADATA_FILE = "metadata.json"
DIGEST_FILE = "digest.json"
BUFFER_DIR = "buffer"
NAME_PREFIX = "metaworld-demos-"
ACTION_TARGET = "expert action clipped to the action space [-1, 1]; the unclipped action is action_raw"
TASK_ORDER = "tar_rl.collectors.tasks.TASKS: the 50 MetaWorld v3 names in alphabetical order; task_id is the index"
VALID_KEY = ("collector", "mask")


class DatasetError(TarRLError, RuntimeError):
    """A dataset folder is incomplete, inconsistent with its metadata, or changed since it was written."""


def package_version(dist: str) -> str | None:
    """The installed version of the distribution ``dist`` (None when it is not installed)."""
    try:
        return importlib.metadata.version(dist)
    except importlib.metadata.PackageNotFoundError:
        return None


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


def cache_key(settings: dict) -> str:
    """16 hex digits of the SHA-256 of the settings that determine a dataset's content."""
    blob = json.dumps(settings, sort_keys=True, separators=(",", ":")).encode()
    return hashlib.sha256(blob).hexdigest()[:16]


def positive_int(name: str, value) -> int:
    """``value`` as an int; ``ValueError`` naming ``name`` unless it is a positive integer."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ValueError(f"{name} must be a positive integer, got {value!r}.")
    return int(value)


# -- Building ---------------------------------------------------------------------------------


def _chunks(action: np.ndarray, lengths: np.ndarray, horizon: int) -> tuple[np.ndarray, np.ndarray]:
    """``[N, H, A]`` action chunks and their ``[N, H]`` validity from per-episode lengths."""
    ends = np.repeat(np.cumsum(lengths), lengths)  # [N] one past the last row
    rows = np.arange(len(action))[:, None] + np.arange(horizon)[None, :]  # [N, H]
    valid = rows < ends[:, None]
    rows = np.minimum(rows, ends[:, None] - 1)
    return action[rows], valid


def _history(observation: np.ndarray, lengths: np.ndarray, window: int) -> tuple[np.ndarray, np.ndarray]:
    """``[N, K, D]`` observation windows (oldest first) and their ``[N, K]`` validity."""
    starts = np.repeat(np.cumsum(lengths) - lengths, lengths)  # [N] the episode's first row
    rows = np.arange(len(observation))[:, None] - np.arange(window)[::-1][None, :]  # [N, K]
    valid = rows >= starts[:, None]
    rows = np.maximum(rows, starts[:, None])
    return observation[rows], valid


def steps_tensordict(
    *,
    observation: np.ndarray,
    action: np.ndarray,
    action_raw: np.ndarray,
    next_observation: np.ndarray,
    reward: np.ndarray,
    terminated: np.ndarray,
    truncated: np.ndarray,
    lengths: np.ndarray,
    task_id: np.ndarray,
    horizon: int,
    history: int,
    pixels: np.ndarray | None = None,
) -> TensorDict:
    """One flat ``[N]`` TensorDict in the dataset format from episode-contiguous step arrays.

    Episodes are numbered ``0 .. E-1`` in storage order; ``step``, the action chunks and the
    observation windows are derived from ``lengths``.

    Args:
        observation: ``[N, D]`` float32.
        action: ``[N, A]`` float32, the supervision target.
        action_raw: ``[N, A]`` float32, the action before any clipping.
        next_observation: ``[N, D]`` float32.
        reward: ``[N]`` float32.
        terminated: ``[N]`` bool.
        truncated: ``[N]`` bool.
        lengths: ``[E]`` int, steps per episode (sum ``N``).
        task_id: ``[N]`` int64.
        horizon: ``H`` of ``action_chunk``.
        history: ``K`` of ``observation_history``.
        pixels: optional ``[N, 3, S, S]`` uint8.

    Returns:
        The ``[N]`` TensorDict with the keys listed in this module's docstring.
    """
    lengths = np.asarray(lengths, dtype=np.int64)
    n = int(lengths.sum())
    episode = np.repeat(np.arange(len(lengths), dtype=np.int64), lengths)
    step = np.arange(n, dtype=np.int64) - np.repeat(np.cumsum(lengths) - lengths, lengths)
    chunk, chunk_valid = _chunks(action, lengths, horizon)
    past, past_valid = _history(observation, lengths, history)
    terminated = np.asarray(terminated, dtype=bool)[:, None]
    truncated = np.asarray(truncated, dtype=bool)[:, None]
    t = torch.from_numpy
    return TensorDict(
        {
            "observation": t(observation),
            "action": t(action),
            "action_raw": t(action_raw),
            "episode": t(episode),
            "task_id": t(np.asarray(task_id, dtype=np.int64)),
            "step": t(step),
            "action_chunk": t(np.ascontiguousarray(chunk)),
            "action_chunk_valid": t(chunk_valid),
            "observation_history": t(np.ascontiguousarray(past)),
            "observation_history_valid": t(past_valid),
            **({"pixels": t(pixels)} if pixels is not None else {}),
            "next": {
                "observation": t(next_observation),
                "reward": t(np.asarray(reward)[:, None]),
                "done": t(terminated | truncated),
                "terminated": t(terminated),
                "truncated": t(truncated),
            },
        },
        batch_size=[n],
    )


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


def array_stats(x: np.ndarray) -> dict[str, list[float]]:
    """Per-column mean, std, min and max of ``[N, D]`` values (float64), as lists for ``metadata.json``."""
    x = x.astype(np.float64)
    return {
        "mean": x.mean(0).tolist(),
        "std": x.std(0).tolist(),
        "min": x.min(0).tolist(),
        "max": x.max(0).tolist(),
    }


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
        "cache_key": key,
        "settings": settings,
        "tasks": list(results),
        "task_ids": {name: p["task_id"] for name, p in per_task.items()},
        "instructions": {name: p["instruction"] for name, p in per_task.items()},
        "task_order": TASK_ORDER,
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
        "keys": _leaf_specs(data),
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


def _pid_alive(pid: int) -> bool:
    if pid == os.getpid():
        return False  # our own leftovers (from an earlier failed build in this process) are stale
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def clean_temp_siblings(root: Path, name: str) -> None:
    """Remove temporary build folders of ``name`` left by processes that no longer run."""
    for tmp in root.glob(f".{name}.tmp-*"):
        try:
            pid = int(tmp.name.rsplit(".tmp-", 1)[1].split("-")[0])
        except (IndexError, ValueError):
            pid = -1
        if pid > 0 and _pid_alive(pid):
            continue
        print(f"removing the leftover temporary dataset folder {tmp} (an interrupted build)")
        shutil.rmtree(tmp, ignore_errors=True)


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

    return load_dataset(write_dataset(root, name, data, _metadata(settings, key, results, data, secs)))


def write_dataset(root: str | os.PathLike, name: str, data: TensorDict, metadata: dict) -> Path:
    """Write ``data`` and ``metadata`` as the dataset folder ``root/name``, crash-safely.

    The buffer is written in a temporary sibling folder, then ``metadata.json``, then ``digest.json``
    (the content digest of the other files), then the folder is renamed into place. If another process completed
    ``root/name`` first, its folder is kept; an incomplete one there is replaced.

    Args:
        root: the parent folder (must exist).
        name: the dataset folder's name.
        data: the ``[N]`` TensorDict of steps (see :func:`steps_tensordict`).
        metadata: the metadata; ``keys`` (each entry's per-step shape and dtype) is added.

    Returns:
        The dataset folder ``root/name``.
    """
    root = Path(root)
    final = root / name
    metadata = {**metadata, "keys": _leaf_specs(data)}
    tmp = root / f".{name}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    try:
        tmp.mkdir()
        buffer_dir = tmp / BUFFER_DIR
        storage = LazyMemmapStorage(data.shape[0], scratch_dir=buffer_dir / "storage")
        rb = TensorDictReplayBuffer(storage=storage)
        rb.extend(data)
        rb.dumps(buffer_dir)
        del rb, storage
        write_json_atomic(metadata, tmp / METADATA_FILE)
        write_json_atomic(content_digest(tmp), tmp / DIGEST_FILE)  # last: over everything above
        try:
            os.rename(tmp, final)
        except OSError:
            # Another process finished the same dataset first: use it if it is complete.
            if not final.exists():
                raise
            try:
                load_dataset(final)
            except DatasetError:
                shutil.rmtree(final)
                os.rename(tmp, final)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return final


# -- Loading ----------------------------------------------------------------------------------


def load_dataset(path: str | os.PathLike) -> DemoDataset:
    """Open the dataset folder ``path`` (memory-mapped, no copy).

    Every file is checked against ``digest.json`` (its size and SHA-256); a folder without one
    (written before datasets had a digest) gets it now, after the other checks pass.

    Raises:
        DatasetError: the folder is missing, its metadata is missing or unparsable, a storage
            file is missing or has the wrong size, the stored length disagrees with the
            metadata, or a file differs from the content digest (the message names the folder).
    """
    path = Path(path)
    if not path.is_dir():
        raise DatasetError(f"no dataset folder at {path}")
    meta_path = path / METADATA_FILE
    if not meta_path.is_file():
        raise DatasetError(f"{meta_path} is missing (the build did not finish)")
    try:
        metadata = json.loads(meta_path.read_text())
        total = int(metadata["total_steps"])
        version = metadata["format_version"]
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise DatasetError(f"{meta_path} cannot be read: {err}") from err
    if version != FORMAT_VERSION:
        raise DatasetError(f"{path} has format version {version!r}, this tar-rl reads {FORMAT_VERSION}")
    buffer_dir = path / BUFFER_DIR
    storage_meta = buffer_dir / "storage" / "storage_metadata.json"
    if not storage_meta.is_file():
        raise DatasetError(f"{storage_meta} is missing")
    try:
        stored_len = int(json.loads(storage_meta.read_text())["len"])
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise DatasetError(f"{storage_meta} cannot be read: {err}") from err
    if stored_len != total:
        raise DatasetError(f"the storage holds {stored_len} steps, the metadata says {total}")
    # Before opening: a memory map over a truncated file would be silently zero-extended.
    _check_storage_files(buffer_dir / "storage", metadata, total)
    sealed = (path / DIGEST_FILE).exists()
    if sealed:
        check_content(path)
    try:
        storage = LazyMemmapStorage(total, scratch_dir=buffer_dir / "storage", existsok=True)
        rb = TensorDictReplayBuffer(storage=storage)
        rb.loads(buffer_dir)
    except Exception as err:  # torchrl/tensordict raise many kinds for missing or truncated memmaps
        raise DatasetError(f"the storage in {buffer_dir} cannot be loaded: {type(err).__name__}: {err}") from err
    if len(rb) != total:
        raise DatasetError(f"the storage holds {len(rb)} steps, the metadata says {total}")
    stored = {_key_name(k): v for k, v in rb.storage._storage.items(True, True)}
    for name, spec in metadata["keys"].items():
        value = stored.get(name)
        if value is None or list(value.shape) != [total, *spec["shape"]] or _dtype_name(value.dtype) != spec["dtype"]:
            raise DatasetError(f"storage entry {name!r} does not match the metadata {spec}")
    if not sealed:
        _seal(path)
    return DemoDataset(path, rb, metadata)


# -- Content digest -----------------------------------------------------------------------------


def _sha256(file: Path) -> str:
    digest = hashlib.sha256()
    buffer = bytearray(1 << 20)
    view = memoryview(buffer)
    with open(file, "rb", buffering=0) as f:
        while n := f.readinto(buffer):
            digest.update(view[:n])
    return digest.hexdigest()


def content_digest(folder: str | os.PathLike) -> dict:
    """``{"algorithm": "sha256", "files": {relative path: {"size", "sha256"}}}`` of a dataset folder's files.

    Every regular file counts except ``digest.json`` itself and temporary files (``.*.tmp``).
    """
    folder = Path(folder)
    files = {}
    for file in sorted(folder.rglob("*")):
        rel = file.relative_to(folder).as_posix()
        if rel == DIGEST_FILE or (file.name.startswith(".") and file.name.endswith(".tmp")) or not file.is_file():
            continue
        files[rel] = {"size": file.stat().st_size, "sha256": _sha256(file)}
    return {"algorithm": "sha256", "files": files}


def check_content(path: str | os.PathLike) -> None:
    """Compare every file listed in ``path/digest.json`` with its recorded size and SHA-256.

    Raises:
        DatasetError: the digest is unreadable, or a listed file is missing or differs (named).
    """
    path = Path(path)
    digest_path = path / DIGEST_FILE
    try:
        recorded = json.loads(digest_path.read_text())
        files = recorded["files"]
        if recorded["algorithm"] != "sha256" or not isinstance(files, dict) or METADATA_FILE not in files:
            raise ValueError("not a sha256 digest of the folder's files")
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise DatasetError(f"{digest_path} cannot be read: {err}") from err
    for rel, entry in files.items():
        file = path / rel
        if not file.is_file():
            raise DatasetError(f"{file} is missing (listed in {digest_path})")
        try:
            same = file.stat().st_size == entry["size"] and _sha256(file) == entry["sha256"]
        except (KeyError, TypeError) as err:
            raise DatasetError(f"{digest_path} cannot be read: its entry for {rel} is {entry!r}") from err
        if not same:
            raise DatasetError(
                f"{file} differs from its content digest in {DIGEST_FILE}: edited or damaged since the dataset "
                "was written (build or import the dataset again)"
            )


def _seal(path: Path) -> None:
    """Record the content digest of a folder that has none (written before datasets had one)."""
    try:
        write_json_atomic(content_digest(path), path / DIGEST_FILE)
    except OSError as err:
        print(f"dataset {path} has no content digest and none can be written ({err}); its content is not checked")
        return
    print(f"dataset {path} had no content digest (an earlier tar-rl wrote it): recorded one; later loads check it")


def _key_name(key) -> str:
    return ".".join(key) if isinstance(key, tuple) else key


def _dtype_name(dtype: torch.dtype) -> str:
    return str(dtype).removeprefix("torch.")


def _leaf_specs(data: TensorDict) -> dict[str, dict]:
    """``{"next.observation": {"shape": [39], "dtype": "float32"}, ...}``: each entry's per-step shape."""
    return {
        _key_name(k): {"shape": list(v.shape[1:]), "dtype": _dtype_name(v.dtype)} for k, v in data.items(True, True)
    }


def _check_storage_files(storage_dir: Path, metadata: dict, total: int) -> None:
    """Every entry listed in the metadata has its memmap file, at least as large as ``total`` steps need."""
    keys = metadata.get("keys")
    if not isinstance(keys, dict) or not keys:
        raise DatasetError("the metadata lists no stored entries ('keys')")
    for name, spec in keys.items():
        file = storage_dir / (name.replace(".", os.sep) + ".memmap")
        try:
            itemsize = torch.empty((), dtype=getattr(torch, spec["dtype"])).element_size()
            need = total * int(np.prod(spec["shape"], dtype=np.int64)) * itemsize
        except (AttributeError, KeyError, TypeError) as err:
            raise DatasetError(f"the metadata's entry {name!r} is unreadable: {spec!r}") from err
        if not file.is_file():
            raise DatasetError(f"storage file {file} is missing")
        size = file.stat().st_size
        if size < need:
            raise DatasetError(f"storage file {file} holds {size} bytes, {need} expected (truncated)")


# -- The dataset ------------------------------------------------------------------------------


class _OneGatherSliceSampler(SliceSampler):
    """``SliceSampler`` without its second read of the storage (used by :class:`SegmentSampler` only).

    torchrl 0.14's ``SliceSampler._finalize_index`` gathers every sampled entry of the storage
    (``storage[index]``) to look for a stored ``is_init`` to mark slice starts in, and the buffer
    then gathers them again for the batch. With ``truncated_key=None`` and ``init_key=None``
    that first gather is read by nothing: this returns the same index and mask without it
    (tests/data/test_data.py checks the batches equal those of the plain ``SliceSampler``).
    """

    def _finalize_index(self, *, index, num_slices, seq_length, target_seq_length, mask_flat, storage):
        if self.truncated_key is not None or self.init_key is not None:
            return super()._finalize_index(
                index=index,
                num_slices=num_slices,
                seq_length=seq_length,
                target_seq_length=target_seq_length,
                mask_flat=mask_flat,
                storage=storage,
            )
        info = {} if mask_flat is None else {("collector", "mask"): mask_flat}
        return index.to(torch.long).unbind(-1), info


class SegmentSampler:
    """Draws ``[B, L]`` segments of the dataset's episodes with TorchRL's ``SliceSampler``.

    ``buffer`` is a ``TensorDictReplayBuffer`` sampling with ``SliceSampler(slice_len=L,
    traj_key="episode", strict_length=False, pad_output=True)``; its flat ``[B * L]`` sample is
    reshaped to ``[B, L]``. Segments lie within one episode; ``SliceSampler`` places them so that
    they fit, so only a segment of an episode shorter than ``L`` is cut at the episode's end and
    padded at its end (the last real step repeated). ``("collector", "mask")`` is the ``[B, L]``
    bool validity mask, True on real steps (all True when no segment needed padding). The stored
    ``("next", "truncated")`` is returned as stored (the sampler's slice-end marking is off).

    The buffer's ``TensorStorage`` holds plain-tensor views of the dataset's memory maps (zero
    copy): indexing a ``MemoryMappedTensor`` goes through a Python override per entry, and
    ``SliceSampler`` indexes the storage twice per batch, which made sampling ~40% slower; the
    second read (a look for a stored ``is_init``, which the dataset does not have) is skipped
    (``_OneGatherSliceSampler``).

    Args:
        storage: the dataset's ``LazyMemmapStorage``.
        batch_segments: ``B``.
        slice_len: ``L``.
        keys: the entries to sample (nested keys as tuples); default all. ``"episode"`` is
            always included. Fewer entries sample faster.
        generator: optional ``torch.Generator`` for reproducible sampling.
    """

    def __init__(
        self,
        storage: LazyMemmapStorage,
        batch_segments: int,
        slice_len: int,
        keys: Iterable | None = None,
        generator: torch.Generator | None = None,
    ):
        self.batch_segments = positive_int("batch_segments", batch_segments)
        self.slice_len = positive_int("slice_len", slice_len)
        self.dataset_storage = storage  # keeps the memory maps alive
        stored = storage._storage[: len(storage)]
        if keys is not None:
            keys = list(dict.fromkeys([*keys, "episode"]))
            available = set(stored.keys(True, True))
            unknown = [k for k in keys if k not in available]
            if unknown:
                raise KeyError(f"unknown dataset entries {unknown}; the dataset holds {sorted(map(str, available))}")
            stored = stored.select(*keys)
        views = stored.apply(lambda x: x.as_subclass(torch.Tensor))
        self.buffer = TensorDictReplayBuffer(
            storage=TensorStorage(views),
            sampler=_OneGatherSliceSampler(
                slice_len=self.slice_len,
                traj_key="episode",
                strict_length=False,
                pad_output=True,
                cache_values=True,
                truncated_key=None,
                init_key=None,  # the dataset stores no is_init: nothing to mark
            ),
            batch_size=self.batch_segments * self.slice_len,
            generator=generator,
        )

    def sample(self) -> TensorDict:
        """A ``[B, L]`` TensorDict of segments with the bool mask at ``("collector", "mask")``."""
        batch = self.buffer.sample().reshape(self.batch_segments, self.slice_len)
        if VALID_KEY not in batch.keys(True):
            # SliceSampler writes the mask only when some slice needed padding.
            batch.set(VALID_KEY, torch.ones(batch.shape, dtype=torch.bool))
        return batch

    def __iter__(self) -> Iterator[TensorDict]:
        while True:
            yield self.sample()


class DemoDataset:
    """A demonstration dataset: a ``TensorDictReplayBuffer`` over memory-mapped storage plus metadata.

    Attributes:
        path: the dataset folder.
        buffer: the ``TensorDictReplayBuffer`` (``LazyMemmapStorage`` under ``path/buffer``).
        metadata: the parsed ``metadata.json``.
    """

    def __init__(self, path: Path, buffer: TensorDictReplayBuffer, metadata: dict):
        self.path = Path(path)
        self.buffer = buffer
        self.metadata = metadata

    def __len__(self) -> int:
        """Number of stored steps."""
        return len(self.buffer)

    def __repr__(self) -> str:
        m = self.metadata
        return (
            f"DemoDataset({str(self.path)!r}, tasks={len(m['tasks'])}, episodes={m['total_episodes']}, "
            f"steps={len(self)}, chunk_horizon={m['chunk_horizon']})"
        )

    @property
    def data(self) -> TensorDict:
        """All stored steps as one ``[N]`` TensorDict.

        Its tensors are views of the on-disk memory maps: read them, clone before modifying.
        """
        return self.buffer[:]

    @property
    def tasks(self) -> list[str]:
        """The dataset's task names (MetaWorld's are in ``TASKS`` order; an imported dataset's in task-id order)."""
        return list(self.metadata["tasks"])

    @property
    def source(self) -> str:
        """Where the demonstrations come from: ``metaworld`` (collected here) or the importer's name."""
        return self.metadata.get("source", "metaworld")

    def segments(
        self,
        batch_segments: int,
        slice_len: int,
        keys: Iterable | None = None,
        generator: torch.Generator | None = None,
    ) -> SegmentSampler:
        """A sampler of ``[batch_segments, slice_len]`` segments; see :class:`SegmentSampler`."""
        return SegmentSampler(self.buffer.storage, batch_segments, slice_len, keys=keys, generator=generator)

    def check_disjoint(self, eval_seed: int, n_rollouts: int) -> None:
        """Raise ``ValueError`` if evaluation seeds overlap the seeds the demonstrations used.

        Args:
            eval_seed: base seed of the evaluation variations.
            n_rollouts: evaluation episodes per task (they use ``tasks.variation_seeds(eval_seed, n_rollouts)``).
        """
        _tasks.check_disjoint(self.metadata["variation_seeds"], _tasks.variation_seeds(eval_seed, n_rollouts))
