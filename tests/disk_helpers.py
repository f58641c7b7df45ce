"""A file on a full disk, for the tests of what a failing write leaves behind."""

from __future__ import annotations

import errno
import os


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
