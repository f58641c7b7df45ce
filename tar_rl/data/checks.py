"""The checks of a dataset folder: its file names, the content digest (the size and SHA-256 of every file,
``digest.json``), the storage files against the metadata, and the integer arguments of the data functions.

A check that fails raises :class:`DatasetError` naming the folder or file and what is wrong with it.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict

from tar_rl.errors import TarRLError
from tar_rl.io import write_json_atomic

__all__ = [
    "DIGEST_FILE",
    "METADATA_FILE",
    "DatasetError",
    "check_content",
    "check_storage_files",
    "content_digest",
    "dtype_name",
    "key_name",
    "leaf_specs",
    "positive_int",
    "seal",
]

METADATA_FILE = "metadata.json"
DIGEST_FILE = "digest.json"


class DatasetError(TarRLError, RuntimeError):
    """A dataset folder is incomplete, inconsistent with its metadata, or changed since it was written."""


def positive_int(name: str, value) -> int:
    """``value`` as an int; ``ValueError`` naming ``name`` unless it is a positive integer."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ValueError(f"{name} must be a positive integer, got {value!r}.")
    return int(value)


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


def seal(path: Path) -> None:
    """Record the content digest of a folder that has none (written before datasets had one)."""
    try:
        write_json_atomic(content_digest(path), path / DIGEST_FILE)
    except OSError as err:
        print(f"dataset {path} has no content digest and none can be written ({err}); its content is not checked")
        return
    print(f"dataset {path} had no content digest (an earlier tar-rl wrote it): recorded one; later loads check it")


def key_name(key) -> str:
    return ".".join(key) if isinstance(key, tuple) else key


def dtype_name(dtype: torch.dtype) -> str:
    return str(dtype).removeprefix("torch.")


def leaf_specs(data: TensorDict) -> dict[str, dict]:
    """``{"next.observation": {"shape": [39], "dtype": "float32"}, ...}``: each entry's per-step shape."""
    return {key_name(k): {"shape": list(v.shape[1:]), "dtype": dtype_name(v.dtype)} for k, v in data.items(True, True)}


def check_storage_files(storage_dir: Path, metadata: dict, total: int) -> None:
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
