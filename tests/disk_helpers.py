"""A file on a full disk and a read-only folder, for the tests of what a failing write leaves behind."""

from __future__ import annotations

import contextlib
import errno
import os
import shutil
import subprocess
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest


class FullDisk:
    """A file on a full disk: every write fails with ENOSPC, as the OS reports it."""

    def __init__(self, f):
        self._f = f

    def write(self, data):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    def __getattr__(self, name):
        return getattr(self._f, name)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self._f.close()


def _can_create_in(folder: Path) -> bool:
    try:
        fd, probe = tempfile.mkstemp(dir=folder)
    except OSError:
        return False
    os.close(fd)
    os.unlink(probe)
    return True


@contextlib.contextmanager
def read_only(folder: Path) -> Iterator[Path]:
    """``folder`` read-only inside the block: mode 0555, and for a process that ignores modes (root) the
    immutable attribute too (``chattr +i``); the test is skipped where neither stops this process writing."""
    folder.chmod(0o555)
    immutable = False
    try:
        if _can_create_in(folder) and shutil.which("chattr"):
            immutable = subprocess.run(["chattr", "+i", str(folder)], capture_output=True).returncode == 0
        if _can_create_in(folder):
            pytest.skip(f"this process can write into {folder} whatever its mode")
        yield folder
    finally:
        if immutable:
            subprocess.run(["chattr", "-i", str(folder)], check=True)
        folder.chmod(0o755)
