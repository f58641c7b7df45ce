"""The checks of a dataset folder: its file names, the content digest (the size and SHA-256 of every file,
``digest.json``), the stored arrays against the metadata, their values, and the integer arguments of the
data functions.

A check that fails raises :class:`DatasetError` naming the folder or file and what is wrong with it.
Nothing here runs code from a file: ``metadata.json`` and ``digest.json`` are parsed as JSON, the arrays
are raw bytes whose element type, shape and file come from the metadata, checked against fixed lists first
(``docs/security.md``).
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict

from tar_rl.errors import TarRLError
from tar_rl.io import read_json_object, write_json_atomic

__all__ = [
    "DIGEST_FILE",
    "DTYPES",
    "METADATA_FILE",
    "DatasetError",
    "array_specs",
    "check_content",
    "check_ids",
    "check_listed",
    "check_metadata",
    "check_no_links",
    "check_storage_files",
    "check_values",
    "content_digest",
    "data_digest",
    "dtype_name",
    "key_name",
    "leaf_specs",
    "positive_int",
    "read_json",
    "seal",
    "storage_file",
]

METADATA_FILE = "metadata.json"
DIGEST_FILE = "digest.json"
#: The element types a stored array may have, by the name the metadata gives; no other name is looked up.
DTYPES = {
    name: getattr(torch, name)
    for name in ("bool", "uint8", "int8", "int16", "int32", "int64", "float16", "bfloat16", "float32", "float64")
}
#: One part of an entry's name (``next.observation`` has two): letters, digits and ``_``, so that the file it
#: names (``next/observation.memmap``) lies inside the storage folder.
_NAME_PART = re.compile(r"[A-Za-z0-9_]+")
#: Metadata entries that record when and how long a build took, not what it holds (left out of :func:`data_digest`).
_BUILD_TIMES = ("created", "collection_seconds", "import_seconds")


class DatasetError(TarRLError, RuntimeError):
    """A dataset folder is incomplete, inconsistent with its metadata, or changed since it was written."""


def positive_int(name: str, value) -> int:
    """``value`` as an int; ``ValueError`` naming ``name`` unless it is a positive integer."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ValueError(f"{name} must be a positive integer, got {value!r}.")
    return int(value)


def read_json(file: Path, what: str) -> dict:
    """The JSON object in ``file`` (a dataset's metadata or digest); ``DatasetError`` naming the file otherwise."""
    return read_json_object(file, what, DatasetError)


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


def check_content(path: str | os.PathLike) -> dict:
    """Compare every file listed in ``path/digest.json`` with its recorded size and SHA-256; the listed files.

    Raises:
        DatasetError: the digest is unreadable, or a listed file is missing or differs (named).
    """
    path = Path(path)
    digest_path = path / DIGEST_FILE
    recorded = read_json(digest_path, "a content digest")
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


def check_listed(path: Path, files: dict, read: list[Path]) -> None:
    """Every file a load reads is listed in the content digest (else its content would go unchecked)."""
    for file in read:
        rel = file.relative_to(path).as_posix()
        if rel not in files:
            raise DatasetError(f"{file} is not listed in {path / DIGEST_FILE}, so its content cannot be checked")


def check_no_links(path: Path) -> None:
    """No file or folder inside the dataset folder is a symbolic link (which could point anywhere on the disk)."""
    for parent, folders, files in os.walk(path):
        for name in [*folders, *files]:
            if os.path.islink(os.path.join(parent, name)):
                raise DatasetError(
                    f"{os.path.join(parent, name)} is a symbolic link; a dataset folder holds plain files only"
                )


def seal(path: Path) -> Path:
    """Record the content digest of a dataset folder (``digest.json``); the file written."""
    return write_json_atomic(content_digest(path), path / DIGEST_FILE)


def data_digest(metadata: dict, arrays: dict[str, str]) -> str:
    """The identity of a dataset's content: ``sha256:`` and the SHA-256 of its metadata without the build's
    times and of ``arrays`` (each stored entry's name -> the SHA-256 of its file). Two builds of the same data
    have the same identity."""
    blob = {"metadata": {k: v for k, v in metadata.items() if k not in _BUILD_TIMES}, "arrays": arrays}
    text = json.dumps(blob, sort_keys=True, separators=(",", ":"))
    return "sha256:" + hashlib.sha256(text.encode()).hexdigest()


def key_name(key) -> str:
    return ".".join(key) if isinstance(key, tuple) else key


def dtype_name(dtype: torch.dtype) -> str:
    return str(dtype).removeprefix("torch.")


def leaf_specs(data: TensorDict) -> dict[str, dict]:
    """``{"next.observation": {"shape": [39], "dtype": "float32"}, ...}``: each entry's per-step shape."""
    return {key_name(k): {"shape": list(v.shape[1:]), "dtype": dtype_name(v.dtype)} for k, v in data.items(True, True)}


def storage_file(storage_dir: Path, name: str) -> Path:
    """The file of the stored entry ``name`` (``next.observation`` -> ``next/observation.memmap``)."""
    return storage_dir.joinpath(*name.split(".")).with_suffix(".memmap")


def array_specs(metadata: dict) -> dict[str, tuple[torch.dtype, tuple[int, ...]]]:
    """Each stored entry's element type and per-step shape, from the metadata's ``keys``, checked: names of
    letters, digits and ``_`` (dot-separated), an element type of :data:`DTYPES`, non-negative integer sizes.

    Raises:
        DatasetError: no entries, or an entry that breaks one of those rules (named).
    """
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


def _is_int(value, low: int) -> bool:
    return type(value) is int and value >= low


def _str_list(value) -> bool:
    return isinstance(value, list) and all(isinstance(v, str) for v in value)


def _finite_list(value) -> bool:
    return isinstance(value, list) and all(type(v) in (int, float) and np.isfinite(v) for v in value)


def check_metadata(meta_path: Path, metadata: dict) -> None:
    """The metadata entries every reader of a dataset reads, by type and range: ``source``, ``tasks``,
    ``task_ids``, ``task_names``, ``instructions``, ``total_steps``, ``total_episodes``, ``chunk_horizon``,
    ``history``, ``image_size`` and the ``mean``/``std`` of ``stats.observation`` and ``stats.action``
    (finite numbers: the policy normalises with them).

    Raises:
        DatasetError: naming the file, the entry and what it must be.
    """

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


def _short(value) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


def check_storage_files(storage_dir: Path, specs: dict, total: int) -> None:
    """Every entry has its file, a plain file of exactly the size ``total`` steps of its shape and type take."""
    for name, (dtype, shape) in specs.items():
        file = storage_file(storage_dir, name)
        need = total * int(np.prod(shape, dtype=np.int64)) * torch.empty((), dtype=dtype).element_size()
        if not file.is_file():
            raise DatasetError(f"storage file {file} is missing")
        size = file.stat().st_size
        if size != need:
            state = "truncated" if size < need else "longer than its entry"
            raise DatasetError(f"storage file {file} holds {size} bytes, {need} expected ({state})")


def check_values(path: Path, name: str, value: torch.Tensor) -> None:
    """A stored entry's values: finite numbers (a float entry), 0 or 1 (a bool entry); else ``DatasetError``
    naming the folder, the entry and the first step."""
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


def check_ids(path: Path, data: TensorDict, n_tasks: int) -> None:
    """``episode`` and ``task_id``: int64 per step, episode ids >= 0, task ids indexing the ``n_tasks``
    names of ``task_names`` (``DatasetError`` naming the entry and the first step otherwise)."""
    for name, high in (("episode", None), ("task_id", n_tasks)):
        value = data.get(name, None)
        if value is None or value.dtype != torch.int64 or value.dim() != 1:
            raise DatasetError(f"{path}: entry {name!r} must be stored, one int64 per step")
        bad = (value < 0) | (value >= high) if high is not None else value < 0
        if bool(bad.any()):
            allowed = f"0..{high - 1} (the ids of task_names)" if high is not None else ">= 0"
            step = int(bad.nonzero()[0, 0])
            raise DatasetError(f"{path}: entry {name!r} is {int(value[step])} at step {step}; it must be {allowed}")
