"""The dataset format: demonstrations on disk as raw arrays plus a metadata file, read into a TorchRL replay buffer.

A dataset folder holds one row per environment step: each entry of the stored ``[N]`` TensorDict is one
file of raw bytes (C order, little-endian) under ``<folder>/buffer/storage``, and ``metadata.json`` beside
it describes the content, each entry's element type and per-step shape included (``keys``). A suite's
dataset builder (e.g. :mod:`tar_rl.collectors.metaworld.dataset`) or an importer (:mod:`tar_rl.importers`)
turns episode-contiguous step arrays into that TensorDict with :func:`steps_tensordict` and writes the
folder crash-safely with :func:`write_dataset`; :func:`load_dataset` opens any of them as a
``TensorDictReplayBuffer`` over a ``TensorStorage`` of the files' memory maps (no copy).

Layout of one dataset folder::

    <name>/
        buffer/storage/      one <entry>.memmap per stored entry (next.reward: next/reward.memmap)
        metadata.json        the description of the content
        digest.json          written last: the SHA-256 and size of every other file of the folder

Nothing in a dataset folder is code: the loader parses the two JSON files and maps the arrays the
metadata names (element types from a fixed list, names of letters, digits and ``_``, exact file sizes,
no symbolic links); it unpickles nothing (``docs/security.md``). Format versions before 4 were
written with TorchRL's ``rb.dumps``, whose folder holds a pickled file that ``rb.loads`` unpickles:
they are refused, with how to build them again.

Crash safety: a dataset is written in a temporary sibling folder ``.<name>.tmp-<pid>-<rand>`` and
renamed into place only when complete. A folder that fails the checks on load (missing or
unparsable metadata, missing storage files, a size that disagrees with the metadata, a file
whose content differs from ``digest.json``: an edited metadata number, a flipped byte in a memmap,
a NaN or Inf in an entry) raises :class:`~tar_rl.data.checks.DatasetError`; the builders remove such
a folder and write it again. The content check reads every file once per load (about 7 ms for the
default job's 6 MB dataset, well under 1% of the job's start-up: ``python -m benchmarks.bench_data
--sections startup``). A folder without a digest is refused: :func:`seal_dataset` (``tar-rl data seal``) records
one after the other checks pass, for a folder whose content its user trusts.

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
from torchrl.data import TensorDictReplayBuffer, TensorStorage

from tar_rl.io import require_free_space, write_json_atomic

from .checks import (
    DIGEST_FILE,
    METADATA_FILE,
    DatasetError,
    array_specs,
    check_content,
    check_ids,
    check_listed,
    check_metadata,
    check_no_links,
    check_storage_files,
    check_values,
    data_digest,
    key_name,
    leaf_specs,
    read_json,
    seal,
    storage_file,
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
    "seal_dataset",
    "steps_tensordict",
    "write_dataset",
]

# 2: observation_history; 3: task_names and source in every dataset's metadata; 4: raw arrays, no pickled file
FORMAT_VERSION = 4
BUFFER_DIR = "buffer"
STORAGE_DIR = f"{BUFFER_DIR}/storage"  # the arrays' folder inside a dataset folder


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

    Each entry's raw bytes are written in a temporary sibling folder, then ``metadata.json``, then
    ``digest.json`` (the content digest of the other files), then the folder is renamed into place. If
    another process completed ``root/name`` first, its folder is kept; an incomplete one there is replaced.

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
        for key, value in data.items(True, True):
            file = storage_file(tmp / STORAGE_DIR, key_name(key))
            file.parent.mkdir(parents=True, exist_ok=True)
            # The bytes of the C-order array (a view as bytes: any element type, bool and bfloat16 included).
            value.detach().cpu().contiguous().reshape(-1).view(torch.uint8).numpy().tofile(file)
        write_json_atomic(metadata, tmp / METADATA_FILE)
        seal(tmp)  # last: over everything above
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
    """Open the dataset folder ``path`` (memory-mapped, no copy), after checking all of it.

    Checked, in this order and before any array is mapped: the metadata (JSON) and its format version,
    the content digest (every file's size and SHA-256 against ``digest.json``; every file read is listed
    there), the stored entries the metadata names (element types, shapes, exact file sizes, no symbolic
    links); then the values (finite numbers, bools of 0 or 1). Nothing is written.

    Raises:
        DatasetError: the folder is missing, has no content digest, is of another format version, or
            fails a check (the message names the folder or file, in one line).
    """
    return _open(Path(path), sealed=True)


def seal_dataset(path: str | os.PathLike) -> DemoDataset:
    """Record the content digest of a dataset folder that has none, after every other check of
    :func:`load_dataset` passes: for a folder whose content its user trusts as it is (``tar-rl data seal``).

    Raises:
        DatasetError: the folder already has a digest, or fails a check.
    """
    path = Path(path)
    if (path / DIGEST_FILE).exists():
        raise DatasetError(
            f"{path} already has a content digest ({DIGEST_FILE}); to record a new one (after editing the folder "
            f"on purpose), remove {path / DIGEST_FILE} first"
        )
    _open(path, sealed=False)
    seal(path)
    return load_dataset(path)


def _open(path: Path, sealed: bool) -> DemoDataset:
    """:func:`load_dataset`; with ``sealed=False`` the digest is neither needed nor read (:func:`seal_dataset`)."""
    if not path.is_dir():
        raise DatasetError(f"no dataset folder at {path}")
    check_no_links(path)  # before reading any file: a linked metadata.json could be any file of the disk
    meta_path = path / METADATA_FILE
    if not meta_path.is_file():
        raise DatasetError(f"{meta_path} is missing (the build did not finish)")
    metadata = read_json(meta_path, "dataset metadata")
    version = metadata.get("format_version")
    if version != FORMAT_VERSION:
        raise DatasetError(_version_message(path, version))
    check_metadata(meta_path, metadata)
    total = metadata["total_steps"]
    files = None
    if sealed:
        if not (path / DIGEST_FILE).exists():
            raise DatasetError(
                f"{path} has no content digest ({DIGEST_FILE}), so its files cannot be checked: if you trust its "
                f"content as it is, record one with `tar-rl data seal {path}`"
            )
        files = check_content(path)
    specs = array_specs(metadata)
    storage_dir = path / STORAGE_DIR
    if files is not None:
        check_listed(path, files, [meta_path, *(storage_file(storage_dir, name) for name in specs)])
    # Before mapping: each file holds exactly its entry's bytes (a truncated or padded file is named, not mapped).
    check_storage_files(storage_dir, specs, total)
    data = TensorDict(batch_size=[total])
    for name, (dtype, shape) in specs.items():
        numel = total * int(np.prod(shape, dtype=np.int64))
        # A private map (shared=False): the file is read lazily and never written, whatever is done to the tensor.
        value = torch.from_file(str(storage_file(storage_dir, name)), shared=False, size=numel, dtype=dtype)
        value = value.reshape(total, *shape)
        check_values(path, name, value)
        data.set(tuple(name.split(".")), value)
    check_ids(path, data, len(metadata["task_names"]))
    arrays = None
    if files is not None:
        arrays = {name: files[storage_file(Path(STORAGE_DIR), name).as_posix()]["sha256"] for name in specs}
    buffer = TensorDictReplayBuffer(storage=TensorStorage(data))
    return DemoDataset(path, buffer, metadata, data_digest(metadata, arrays) if arrays is not None else None)


def _version_message(path: Path, version) -> str:
    if isinstance(version, int) and not isinstance(version, bool) and version < FORMAT_VERSION:
        return (
            f"{path} is a dataset of format version {version}, which this tar-rl no longer reads (its folder holds "
            "a pickled file, which could run code): build it again (`tar-rl train` collects a suite's "
            "demonstrations again in a new folder; run the same `tar-rl data import ...` again for imported ones)"
        )
    if isinstance(version, int) and not isinstance(version, bool):
        return f"{path} is a dataset of format version {version}, newer than this tar-rl reads ({FORMAT_VERSION})"
    return f"{path / METADATA_FILE}: format_version is {version!r}, not a dataset format version"


class DemoDataset:
    """A demonstration dataset: a ``TensorDictReplayBuffer`` over memory-mapped storage plus metadata.

    Attributes:
        path: the dataset folder.
        buffer: the ``TensorDictReplayBuffer`` (a ``TensorStorage`` of the arrays under ``path/buffer/storage``,
            mapped privately: the files are never written).
        metadata: the parsed ``metadata.json``.
        digest: the identity of the content (:func:`~tar_rl.data.checks.data_digest`: ``sha256:...``), which a
            run records so that it resumes on the same data only; ``None`` while the folder has no content
            digest (inside :func:`seal_dataset` only).
    """

    def __init__(self, path: Path, buffer: TensorDictReplayBuffer, metadata: dict, digest: str | None = None):
        self.path = Path(path)
        self.buffer = buffer
        self.metadata = metadata
        self.digest = digest

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

        Its tensors are views of the private memory maps of the files: writing to them changes this
        process's copy only (clone before modifying).
        """
        return self.buffer[:]

    @property
    def longest_episode(self) -> int:
        """The number of steps of the longest episode."""
        return int(torch.bincount(self.data["episode"]).max())

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
