"""A tar-rl dataset folder (format 4) read as data: ``metadata.json``, ``digest.json`` and raw arrays.

tar-rl writes its demonstrations (MetaWorld's, dm_control's, imported ones) as a folder of raw little-endian arrays
under ``buffer/storage/`` described by ``metadata.json`` and sealed by ``digest.json`` (the size and SHA-256 of every
other file): tar-rl's ``docs/data.md``. This module reads such a folder with torch, numpy and the standard library
alone, so the LeRobot environment needs none of tar-rl's own dependencies (TorchRL, tensordict, MetaWorld) to read
it. Nothing in the folder is code: the JSON files are parsed, the arrays are mapped by the element type and shape the
metadata gives, checked against fixed lists first.

The checks are tar-rl's loader's (``tar_rl.data.format.load_dataset``), in its order and with its messages, so a
folder tar-rl refuses is refused here with the same line (the plugin's tests compare the two on the same folders):
no symbolic links, the metadata and its format version, the entries every reader reads, the content digest (a
folder without one, unsealed, is refused), each stored entry's type, shape and file size, then the values (finite
numbers, bools of 0 or 1) and the episode and task ids.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

__all__ = ["DIGEST_FILE", "FORMAT_VERSION", "METADATA_FILE", "DatasetError", "TarDataset", "read_tar_dataset"]

#: The format version this reader reads (tar-rl's ``tar_rl.data.FORMAT_VERSION``).
FORMAT_VERSION = 4
METADATA_FILE = "metadata.json"
DIGEST_FILE = "digest.json"
STORAGE_DIR = "buffer/storage"
#: The element types a stored array may have, by the name the metadata gives; no other name is looked up.
DTYPES = {
    name: getattr(torch, name)
    for name in ("bool", "uint8", "int8", "int16", "int32", "int64", "float16", "bfloat16", "float32", "float64")
}
#: One part of an entry's name: letters, digits and ``_`` (so the file it names lies inside the storage folder).
_NAME_PART = re.compile(r"[A-Za-z0-9_]+")


class DatasetError(RuntimeError):
    """A tar-rl dataset folder is missing, unsealed, of another format, inconsistent or changed since it was written
    (tar-rl's ``DatasetError``, with its messages)."""


@dataclass(frozen=True)
class TarDataset:
    """A checked tar-rl dataset folder.

    Attributes:
        path: the folder.
        metadata: the parsed ``metadata.json``.
        arrays: each stored entry by its name (``observation``, ``next.reward``, ...): ``[N, *shape]`` tensors mapped
            privately from the files (never written).
    """

    path: Path
    metadata: dict
    arrays: dict[str, torch.Tensor]

    @property
    def total_steps(self) -> int:
        return int(self.metadata["total_steps"])


def read_tar_dataset(path: str | os.PathLike) -> TarDataset:
    """Open the tar-rl dataset folder ``path`` after checking all of it (tar-rl's ``load_dataset``); nothing is
    written.

    Raises:
        DatasetError: the folder is missing, has no content digest, is of another format version, or fails a check
            (the message, one line, names the folder or file).
    """
    path = Path(path)
    if not path.is_dir():
        raise DatasetError(f"no dataset folder at {path}")
    _check_no_links(path)  # before reading any file: a linked metadata.json could be any file of the disk
    meta_path = path / METADATA_FILE
    if not meta_path.is_file():
        raise DatasetError(f"{meta_path} is missing (the build did not finish)")
    metadata = _read_json(meta_path, "dataset metadata")
    version = metadata.get("format_version")
    if version != FORMAT_VERSION:
        raise DatasetError(_version_message(path, version))
    _check_metadata(meta_path, metadata)
    total = metadata["total_steps"]
    if not (path / DIGEST_FILE).exists():
        raise DatasetError(
            f"{path} has no content digest ({DIGEST_FILE}), so its files cannot be checked: if you trust its "
            f"content as it is, record one with `tar-rl data seal {path}`"
        )
    files = _check_content(path)
    specs = _array_specs(metadata)
    storage_dir = path / STORAGE_DIR
    for file in [meta_path, *(_storage_file(storage_dir, name) for name in specs)]:
        if file.relative_to(path).as_posix() not in files:
            raise DatasetError(f"{file} is not listed in {path / DIGEST_FILE}, so its content cannot be checked")
    _check_storage_files(storage_dir, specs, total)
    arrays = {}
    for name, (dtype, shape) in specs.items():
        numel = total * int(np.prod(shape, dtype=np.int64))
        # A private map (shared=False): the file is read lazily and never written, whatever is done to the tensor.
        value = torch.from_file(str(_storage_file(storage_dir, name)), shared=False, size=numel, dtype=dtype)
        value = value.reshape(total, *shape)
        _check_values(path, name, value)
        arrays[name] = value
    _check_ids(path, arrays, len(metadata["task_names"]))
    return TarDataset(path, metadata, arrays)


# -- tar-rl's checks (tar_rl.data.checks, tar_rl.data.format), with its messages -----------------------------------


def _read_json(file: Path, what: str) -> dict:
    try:
        value = json.loads(Path(file).read_text())
    except (OSError, UnicodeDecodeError, ValueError, RecursionError) as err:
        raise DatasetError(f"{file} cannot be read as {what}: {type(err).__name__}: {err}") from None
    if not isinstance(value, dict):
        raise DatasetError(f"{file} cannot be read as {what}: it holds a {type(value).__name__}, not an object")
    return value


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


def _check_no_links(path: Path) -> None:
    for parent, folders, files in os.walk(path):
        for name in [*folders, *files]:
            if os.path.islink(os.path.join(parent, name)):
                raise DatasetError(
                    f"{os.path.join(parent, name)} is a symbolic link; a dataset folder holds plain files only"
                )


def _is_int(value, low: int) -> bool:
    return type(value) is int and value >= low


def _str_list(value) -> bool:
    return isinstance(value, list) and all(isinstance(v, str) for v in value)


def _finite_list(value) -> bool:
    return isinstance(value, list) and all(type(v) in (int, float) and math.isfinite(v) for v in value)


def _short(value) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


def _check_metadata(meta_path: Path, metadata: dict) -> None:
    def refuse(entry: str, rule: str):
        raise DatasetError(f"{meta_path}: {entry} is {_short(metadata.get(entry.split('.')[0]))}; it must be {rule}")

    m = metadata
    if not isinstance(m.get("source"), str):
        refuse("source", "a name")
    names = m.get("task_names")
    if not _str_list(names) or not names:
        refuse("task_names", "a non-empty list of task names")
    if not _str_list(m.get("tasks")) or not m["tasks"]:
        refuse("tasks", "a non-empty list of task names")
    ids = m.get("task_ids")
    if not isinstance(ids, dict) or sorted(ids) != sorted(m["tasks"]):
        refuse("task_ids", "a task id for each of its tasks")
    if not all(_is_int(i, 0) and i < len(names) and names[i] == t for t, i in ids.items()):
        refuse("task_ids", "each task's index in task_names")
    texts = m.get("instructions", {})
    if not isinstance(texts, dict) or not all(v is None or isinstance(v, str) for v in texts.values()):
        refuse("instructions", "a text (or null) per task name")
    for entry, low in (("total_steps", 1), ("total_episodes", 1), ("chunk_horizon", 1), ("history", 1)):
        if not _is_int(m.get(entry), low):
            refuse(entry, f"an integer >= {low}")
    if not _is_int(m.get("image_size", 0), 0):
        refuse("image_size", "an integer >= 0")
    stats = m.get("stats")
    for part in ("observation", "action"):
        entry = stats.get(part) if isinstance(stats, dict) else None
        ok = isinstance(entry, dict) and all(_finite_list(entry.get(k)) and entry.get(k) for k in ("mean", "std"))
        if not ok:
            refuse("stats", f"per-dimension lists of finite numbers at stats.{part}.mean and stats.{part}.std")


def _sha256(file: Path) -> str:
    digest = hashlib.sha256()
    buffer = bytearray(1 << 20)
    view = memoryview(buffer)
    with open(file, "rb", buffering=0) as f:
        while n := f.readinto(buffer):
            digest.update(view[:n])
    return digest.hexdigest()


def _check_content(path: Path) -> dict:
    digest_path = path / DIGEST_FILE
    recorded = _read_json(digest_path, "a content digest")
    files = recorded.get("files")
    if recorded.get("algorithm") != "sha256" or not isinstance(files, dict) or METADATA_FILE not in files:
        raise DatasetError(f"{digest_path} cannot be read: it is not a sha256 digest of the folder's files")
    for rel, entry in files.items():
        file = path / rel
        if not isinstance(entry, dict) or not isinstance(entry.get("sha256"), str):
            raise DatasetError(f"{digest_path} cannot be read: its entry for {rel} is {entry!r}")
        if ".." in Path(rel).parts or Path(rel).is_absolute():
            raise DatasetError(f"{digest_path} lists {rel!r}, which is not a file of the folder")
        if not file.is_file():
            raise DatasetError(f"{file} is missing (listed in {digest_path})")
        if file.stat().st_size != entry.get("size") or _sha256(file) != entry["sha256"]:
            raise DatasetError(
                f"{file} differs from its content digest in {DIGEST_FILE}: edited or damaged since the dataset "
                "was written (build or import the dataset again)"
            )
    return files


def _storage_file(storage_dir: Path, name: str) -> Path:
    return storage_dir.joinpath(*name.split(".")).with_suffix(".memmap")


def _array_specs(metadata: dict) -> dict[str, tuple[torch.dtype, tuple[int, ...]]]:
    keys = metadata.get("keys")
    if not isinstance(keys, dict) or not keys:
        raise DatasetError("the metadata lists no stored entries ('keys')")
    specs = {}
    for name, spec in keys.items():
        if not all(_NAME_PART.fullmatch(part) for part in name.split(".")):
            raise DatasetError(f"the metadata's entry name {name!r} is not letters, digits and _ (dot-separated)")
        dtype = spec.get("dtype") if isinstance(spec, dict) else None
        shape = spec.get("shape") if isinstance(spec, dict) else None
        if not isinstance(dtype, str) or dtype not in DTYPES:
            raise DatasetError(f"the metadata's entry {name!r} has element type {dtype!r}, not one of {list(DTYPES)}")
        if not isinstance(shape, list) or not all(type(n) is int and n >= 0 for n in shape):
            raise DatasetError(f"the metadata's entry {name!r} has shape {shape!r}, not a list of sizes")
        specs[name] = (DTYPES[dtype], tuple(shape))
    return specs


def _check_storage_files(storage_dir: Path, specs: dict, total: int) -> None:
    for name, (dtype, shape) in specs.items():
        file = _storage_file(storage_dir, name)
        need = total * int(np.prod(shape, dtype=np.int64)) * torch.empty((), dtype=dtype).element_size()
        if not file.is_file():
            raise DatasetError(f"storage file {file} is missing")
        size = file.stat().st_size
        if size != need:
            state = "truncated" if size < need else "longer than its entry"
            raise DatasetError(f"storage file {file} holds {size} bytes, {need} expected ({state})")


def _check_values(path: Path, name: str, value: torch.Tensor) -> None:
    if value.dtype.is_floating_point:
        bad = ~torch.isfinite(value)
        rule = "holds NaN or Inf; every value of a dataset must be finite"
    elif value.dtype == torch.bool:
        bad = value.view(torch.uint8) > 1
        rule = "holds a byte other than 0 or 1; a bool entry is 0 (False) or 1 (True)"
    else:
        return
    if bool(bad.any()):
        step = int(bad.reshape(len(value), -1).any(1).nonzero()[0, 0])
        raise DatasetError(f"{path}: entry {name!r} {rule} (first at step {step})")


def _check_ids(path: Path, arrays: dict[str, torch.Tensor], n_tasks: int) -> None:
    for name, high in (("episode", None), ("task_id", n_tasks)):
        value = arrays.get(name)
        if value is None or value.dtype != torch.int64 or value.dim() != 1:
            raise DatasetError(f"{path}: entry {name!r} must be stored, one int64 per step")
        bad = (value < 0) | (value >= high) if high is not None else value < 0
        if bool(bad.any()):
            allowed = f"0..{high - 1} (the ids of task_names)" if high is not None else ">= 0"
            step = int(bad.nonzero()[0, 0])
            raise DatasetError(f"{path}: entry {name!r} is {int(value[step])} at step {step}; it must be {allowed}")
