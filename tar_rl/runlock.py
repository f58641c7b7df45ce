"""One writer per run folder: an OS-level lock on a file inside it.

A training job holds ``run_dir/.lock`` with ``fcntl.flock`` for as long as it may write the folder.
The operating system releases the lock when the process ends, however it ends (a normal exit, an
exception, SIGKILL, a crash), so a lock is never left behind by a dead process: its file may still
name that process, and the next job takes the lock over (and says so). A second job on the same
folder while the first runs is refused with the holder's PID, host and start time.

The lock file holds one JSON line about the holder (``pid``, ``host``, ``started``), for the
message of a refused job; the lock itself is the ``flock``, not the file's content.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import socket
import time
from collections.abc import Iterator
from pathlib import Path

from tar_rl.errors import TarRLError

__all__ = ["LOCK_FILE", "RunFolderBusy", "run_lock"]

LOCK_FILE = ".lock"


class RunFolderBusy(TarRLError):
    """Another process holds the run folder's lock."""


def _holder(fd: int) -> dict:
    """The holder the lock file describes (empty when none is written or it cannot be read)."""
    try:
        text = os.pread(fd, 4096, 0).decode()
        info = json.loads(text) if text.strip() else {}
    except (OSError, ValueError):
        return {}
    return info if isinstance(info, dict) else {}


def _describe(info: dict) -> str:
    if not info:
        return "another process (it wrote no details)"
    return f"process {info.get('pid', '?')} on {info.get('host', '?')} (started {info.get('started', '?')})"


@contextlib.contextmanager
def run_lock(run_dir: str | os.PathLike) -> Iterator[dict]:
    """Hold ``run_dir``'s lock for the ``with`` block; yields what the lock file says about this process.

    Raises:
        RunFolderBusy: another process holds it (the message names its PID, host and start time).
    """
    run_dir = Path(run_dir)
    path = run_dir / LOCK_FILE
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)  # not inherited by child processes
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise RunFolderBusy(
                f"{run_dir} is in use by {_describe(_holder(fd))}: wait for that run to end (or stop it), "
                "or choose another run_dir"
            ) from None
        stale = _holder(fd)
        if stale:
            print(f"{run_dir}: taking over the lock left by {_describe(stale)}, which is no longer running")
        me = {
            "pid": os.getpid(),
            "host": socket.gethostname(),
            "started": time.strftime("%Y-%m-%d %H:%M:%S %z"),
        }
        os.ftruncate(fd, 0)
        os.pwrite(fd, (json.dumps(me) + "\n").encode(), 0)
        try:
            yield me
        finally:
            with contextlib.suppress(OSError):
                os.ftruncate(fd, 0)  # released normally: no holder to report
    finally:
        os.close(fd)  # releases the flock
