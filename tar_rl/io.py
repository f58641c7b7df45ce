"""Atomic file writes: a temporary file in the target's folder, flushed to disk, then renamed.

A crash at any point leaves either the previous file or the new one, never a partial file. A write
that fails for want of space (``ENOSPC``, ``EDQUOT``; torch reports it inside ``torch.save`` as a
``RuntimeError``) raises :class:`tar_rl.errors.DiskFullError` naming the file.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any

from tar_rl.errors import DiskFullError, disk_full_cause

__all__ = [
    "atomic_write",
    "check_writable",
    "require_free_space",
    "save_torch_atomic",
    "write_csv_atomic",
    "write_json_atomic",
]

#: Room kept free beside a file of known size, for the small files written with it (metadata, digests).
SPARE_BYTES = 1 << 20


def require_free_space(folder: str | os.PathLike, nbytes: int, path: str | os.PathLike) -> None:
    """Refuse to write ``nbytes`` (plus :data:`SPARE_BYTES`) as ``path`` into ``folder`` unless its disk has room.

    A memory-mapped file whose pages find no room on the disk kills the process with SIGBUS, which Python
    cannot catch (no message, a temporary folder left behind); writes into memory maps are checked here first.

    Raises:
        DiskFullError: naming ``path``, the bytes needed and the bytes free.
    """
    free = shutil.disk_usage(folder).free
    if free < nbytes + SPARE_BYTES:
        need = f"it needs {(nbytes + SPARE_BYTES) / 1e6:.1f} MB, {free / 1e6:.1f} MB are free under {folder}"
        raise DiskFullError(path, OSError(errno.ENOSPC, os.strerror(errno.ENOSPC)), need)


def check_writable(folder: str | os.PathLike) -> Path:
    """Make ``folder`` (and its parents) if needed and create and remove a file in it: a folder the results of
    some work are to be written to, checked before the work.

    Raises:
        OSError: the folder cannot be made or written to (read-only, no permission, a file in its place).
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    fd, probe = tempfile.mkstemp(dir=folder, prefix=".write-test.", suffix=".tmp")
    os.close(fd)
    os.unlink(probe)
    return folder


def atomic_write(path: str | os.PathLike, write: Callable[[IO], object], binary: bool = False) -> Path:
    """Call ``write(f)`` on a file (text, or bytes with ``binary=True``) that becomes ``path`` only once complete.

    The folder is created if needed; the file gets ordinary permissions (0644, not mkstemp's 0600).

    Raises:
        DiskFullError: no space left (or quota exhausted) while writing; ``path`` is unchanged.
    """
    path = Path(path)
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
        with _open(fd, binary, path) as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException as err:
        if tmp is not None and os.path.exists(tmp):
            os.unlink(tmp)
        full = disk_full_cause(err)
        if full is not None and not isinstance(err, DiskFullError):
            raise DiskFullError(path, full) from err
        raise
    return path


def _open(fd: int, binary: bool, path: Path) -> IO:
    """The temporary file of :func:`atomic_write` that becomes ``path`` (a seam for tests that simulate a full disk)."""
    return os.fdopen(fd, "wb") if binary else os.fdopen(fd, "w", newline="")


def write_csv_atomic(df, path: str | os.PathLike, float_format: str | None = None) -> Path:
    """Write a pandas DataFrame as CSV (no index) atomically; ``float_format`` (e.g. ``"%.9g"``) formats its floats,
    which pandas otherwise writes with the 17 digits that round-trip float64."""
    return atomic_write(path, lambda f: df.to_csv(f, index=False, float_format=float_format))


def write_json_atomic(obj: Any, path: str | os.PathLike) -> Path:
    """Write ``obj`` as indented JSON atomically."""
    return atomic_write(path, lambda f: json.dump(obj, f, indent=1))


def save_torch_atomic(obj: Any, path: str | os.PathLike) -> Path:
    """``torch.save(obj)`` atomically: a crash leaves the previous file, never a truncated one."""
    import torch

    return atomic_write(path, lambda f: torch.save(obj, f), binary=True)


def read_json_object(file: Path, what: str, error: type[Exception] = ValueError) -> dict:
    """The JSON object in ``file``; ``error`` naming the file and ``what`` it should hold otherwise (unreadable,
    not JSON, nested too deep, or JSON that is not an object)."""
    try:
        value = json.loads(Path(file).read_text())
    except (OSError, UnicodeDecodeError, ValueError, RecursionError) as err:
        raise error(f"{file} cannot be read as {what}: {type(err).__name__}: {err}") from None
    if not isinstance(value, dict):
        raise error(f"{file} cannot be read as {what}: it holds a {type(value).__name__}, not an object")
    return value
