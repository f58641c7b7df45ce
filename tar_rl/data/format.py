"""The dataset format: demonstrations on disk as a TorchRL replay buffer plus a metadata file.

A dataset folder holds one row per environment step in a ``TensorDictReplayBuffer`` over a
``LazyMemmapStorage`` under ``<folder>/buffer`` (written with ``rb.dumps``; ``rb.loads`` reads it back
in place, without copying) and ``metadata.json`` beside it describing the content. A suite's dataset
builder (e.g. :mod:`tar_rl.collectors.metaworld.dataset`) or an importer (:mod:`tar_rl.importers`) turns
episode-contiguous step arrays into the stored ``[N]`` TensorDict with :func:`steps_tensordict` and
writes the folder crash-safely with :func:`write_dataset`; :func:`load_dataset` opens any of them.

Layout of one dataset folder::

    <name>/
        buffer/              rb.dumps(): storage/ (memmaps), storage_metadata.json, ...
        metadata.json        the description of the content
        digest.json          written last: the SHA-256 and size of every other file of the folder

Crash safety: a dataset is written in a temporary sibling folder ``.<name>.tmp-<pid>-<rand>`` and
renamed into place only when complete. A folder that fails the checks on load (missing or
unparsable metadata, missing storage files, a length that disagrees with the metadata, a file
whose content differs from ``digest.json``: an edited metadata number, a flipped byte in a memmap)
raises :class:`~tar_rl.data.checks.DatasetError`; the builders remove such a folder and write it again.
The content check reads every file once per load (about 10 ms for the default job's 6 MB dataset,
well under 1% of the job's start-up: ``benchmarks/bench_data.py --sections startup``). A folder without
a digest gets one on its first load (trust on first use).

Keys per step (``N`` steps, observation size ``D``, action size ``A``, chunk horizon ``H``):

* ``observation`` [D] float32, ``action`` [A] float32 (the supervision target; the metadata's
  ``action_target`` says what it is), ``action_raw`` [A] float32 (the action before any clipping),
* ``("next", "observation")`` [D] float32, ``("next", "reward")`` [1] float32,
  ``("next", "done")``, ``("next", "terminated")``, ``("next", "truncated")`` [1] bool,
* ``episode`` int64 (global id, contiguous in storage), ``task_id`` int64 (the index of the task in
  the metadata's ``task_names``), ``step`` int64 (index within the episode),
* ``action_chunk`` [H, A] float32: the actions ``t .. t+H-1`` of the same episode, past the episode
  end the last action repeated; ``action_chunk_valid`` [H] bool, True on real steps.
* ``observation_history`` [K, D] float32: the observations ``t-K+1 .. t`` of the same episode,
  oldest first (the last entry is ``observation``), before the episode start the first
  observation repeated; ``observation_history_valid`` [K] bool, True on real steps (K: ``history``,
  for heads that read a window of past observations).
* ``pixels`` [3, S, S] uint8, only in datasets with images (``image_size=S > 0``): the camera image of
  ``observation``.

Metadata every dataset carries (besides its source's own entries): ``format_version``, ``source``,
``settings``, ``tasks`` (the dataset's tasks), ``task_ids`` (their ids), ``task_names`` (the name of
every task id, in id order: a suite with a fixed task list numbers all of it, so a policy trained on a
few tasks is evaluated with the same ids), ``instructions`` (task name -> instruction text, where known),
``total_steps``, ``total_episodes``, ``chunk_horizon``, ``history``, ``image_size``, ``stats`` and ``keys``.
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import json
import os
import shutil
import uuid
from collections.abc import Iterable
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict
from torchrl.data import LazyMemmapStorage, TensorDictReplayBuffer

from tar_rl.io import require_free_space, write_json_atomic

from .checks import (
    DIGEST_FILE,
    METADATA_FILE,
    DatasetError,
    check_content,
    check_storage_files,
    content_digest,
    dtype_name,
    key_name,
    leaf_specs,
    seal,
)
from .sampler import SegmentSampler

__all__ = [
    "BUFFER_DIR",
    "FORMAT_VERSION",
    "DemoDataset",
    "array_stats",
    "cache_key",
    "clean_temp_siblings",
    "load_dataset",
    "package_version",
    "steps_tensordict",
    "write_dataset",
]

FORMAT_VERSION = 3  # 2: observation_history; 3: task_names and source in every dataset's metadata
BUFFER_DIR = "buffer"


def package_version(dist: str) -> str | None:
    """The installed version of the distribution ``dist`` (None when it is not installed)."""
    try:
        return importlib.metadata.version(dist)
    except importlib.metadata.PackageNotFoundError:
        return None


def cache_key(settings: dict) -> str:
    """16 hex digits of the SHA-256 of the settings that determine a dataset's content."""
    blob = json.dumps(settings, sort_keys=True, separators=(",", ":")).encode()
    return hashlib.sha256(blob).hexdigest()[:16]


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


def array_stats(x: np.ndarray) -> dict[str, list[float]]:
    """Per-column mean, std, min and max of ``[N, D]`` values (float64), as lists for ``metadata.json``."""
    x = x.astype(np.float64)
    return {
        "mean": x.mean(0).tolist(),
        "std": x.std(0).tolist(),
        "min": x.min(0).tolist(),
        "max": x.max(0).tolist(),
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

    Raises:
        DiskFullError: the disk under ``root`` has no room for the data (checked before anything is written).
    """
    root = Path(root)
    final = root / name
    metadata = {**metadata, "keys": leaf_specs(data)}
    require_free_space(root, sum(v.numel() * v.element_size() for v in data.values(True, True)), final)
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
    check_storage_files(buffer_dir / "storage", metadata, total)
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
    stored = {key_name(k): v for k, v in rb.storage._storage.items(True, True)}
    for name, spec in metadata["keys"].items():
        value = stored.get(name)
        if value is None or list(value.shape) != [total, *spec["shape"]] or dtype_name(value.dtype) != spec["dtype"]:
            raise DatasetError(f"storage entry {name!r} does not match the metadata {spec}")
    if not sealed:
        seal(path)
    return DemoDataset(path, rb, metadata)


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
        """The dataset's task names, in task-id order."""
        return list(self.metadata["tasks"])

    @property
    def source(self) -> str:
        """Where the demonstrations come from: the suite that collected them or the importer's name."""
        return self.metadata["source"]

    def segments(
        self,
        batch_segments: int,
        slice_len: int,
        keys: Iterable | None = None,
        generator: torch.Generator | None = None,
    ) -> SegmentSampler:
        """A sampler of ``[batch_segments, slice_len]`` segments; see :class:`SegmentSampler`."""
        return SegmentSampler(self.buffer.storage, batch_segments, slice_len, keys=keys, generator=generator)
