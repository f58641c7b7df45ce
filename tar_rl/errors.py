"""Errors a user can cause or meet, and how the commands report them.

Every such error carries a one-line message that names what happened, where (the setting, file or
folder) and what to do. The ``tar-rl`` commands print that line and exit non-zero; the whole
traceback is printed only in debug mode (``tar-rl --debug ...`` or ``HYDRA_FULL_ERROR=1``).
"""

from __future__ import annotations

import contextlib
import errno
import os
import signal
import threading
from collections.abc import Iterator
from pathlib import Path

__all__ = [
    "DEBUG_ENV",
    "DiskFullError",
    "RunInterrupted",
    "TarRLError",
    "Terminated",
    "children_ignore_sigint",
    "debug_mode",
    "disk_full_cause",
    "interrupted",
    "one_line",
    "sigterm_raises",
    "terminated",
]

#: The environment variable that asks for whole tracebacks (Hydra's own name for it).
DEBUG_ENV = "HYDRA_FULL_ERROR"
#: The errno values of a full disk or an exhausted quota.
_NO_SPACE = (errno.ENOSPC, errno.EDQUOT)


class TarRLError(Exception):
    """An error a user can cause or meet (bad settings or data, another process, a full disk, a diverging run).

    Its message is one line: what happened, where, and what to do.
    """


class DiskFullError(TarRLError, OSError):
    """No space left on the device (or quota exhausted) while writing ``path``; the file there is unchanged.

    An ``OSError`` (``errno``, ``filename`` set), so code that handles failed writes still catches it.
    """

    def __init__(self, path: str | os.PathLike, cause: OSError, detail: str = ""):
        super().__init__(cause.errno, os.strerror(cause.errno), str(path))
        self.path = Path(path)
        self.detail = detail
        kind = "disk quota exceeded" if cause.errno == errno.EDQUOT else "disk full"
        #: What happened and where, without the consequence (for callers that add their own).
        self.what = f"no space left on device while writing {self.path} ({kind}{': ' + detail if detail else ''})"

    def __str__(self) -> str:
        return f"{self.what}; the previous {self.path.name}, if any, is unchanged"

    def __reduce__(self):  # picklable (errors cross process boundaries in the evaluator and Hydra launchers)
        return (_disk_full, (str(self.path), self.errno, self.detail))


def _disk_full(path: str, code: int, detail: str = "") -> DiskFullError:
    return DiskFullError(path, OSError(code, os.strerror(code)), detail)


class RunInterrupted(KeyboardInterrupt):
    """A training run stopped by Ctrl-C (SIGINT); the message says where it stopped and how to resume.

    A ``KeyboardInterrupt``, so code that lets Ctrl-C through still does.
    """


class Terminated(KeyboardInterrupt):
    """SIGTERM received inside :func:`sigterm_raises`: the job stops as on Ctrl-C, and the command exits 143.

    A ``KeyboardInterrupt``, so everything that ends a job cleanly on Ctrl-C does so on SIGTERM too.
    """


def _raise_terminated(signum, frame) -> None:
    raise Terminated("SIGTERM")


@contextlib.contextmanager
def sigterm_raises() -> Iterator[None]:
    """Inside the block SIGTERM raises :class:`Terminated` in the main thread instead of ending the process silently.

    Outside the main thread, where signal handlers cannot be set, this does nothing. Worker processes
    start with SIGTERM's default action (they are spawned), so ending them still ends them.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous if previous is not None else signal.SIG_DFL)


def _chain(err: BaseException | None) -> Iterator[BaseException]:
    """``err``, then the exception it was raised from or while handling, and so on."""
    seen: set[int] = set()
    while err is not None and id(err) not in seen:
        seen.add(id(err))
        yield err
        err = err.__cause__ or err.__context__


def disk_full_cause(err: BaseException) -> OSError | None:
    """The ``OSError`` of a full disk behind ``err`` (``err`` itself, its cause or its context), or None.

    torch reports a failed write inside ``torch.save`` as a ``RuntimeError`` whose context is the
    ``OSError`` the file raised; this finds it there.
    """
    return next((e for e in _chain(err) if isinstance(e, OSError) and e.errno in _NO_SPACE), None)


def interrupted(err: BaseException) -> bool:
    """Whether ``err`` is, or was raised while handling, a ``KeyboardInterrupt`` (Ctrl-C).

    Some libraries' clean-up code fails on the way out of an interrupted call (tensordict's
    ``to_module`` context raises a ``RuntimeError`` when Ctrl-C lands inside it); the Ctrl-C is
    then found in the context.
    """
    return any(isinstance(e, KeyboardInterrupt) for e in _chain(err))


def terminated(err: BaseException) -> bool:
    """Whether ``err`` is, or was raised while handling, a :class:`Terminated` (SIGTERM)."""
    return any(isinstance(e, Terminated) for e in _chain(err))


def debug_mode() -> bool:
    """Whether whole tracebacks are asked for (``HYDRA_FULL_ERROR=1``, which ``tar-rl --debug`` sets)."""
    return os.environ.get(DEBUG_ENV, "") == "1"


def one_line(command: str, err: BaseException) -> str:
    """``"<command>: <message>"`` on one line (a multi-line message is joined with ``" | "``)."""
    text = " | ".join(line.strip() for line in str(err).splitlines() if line.strip())
    return f"{command}: {text or type(err).__name__}"


@contextlib.contextmanager
def children_ignore_sigint() -> Iterator[None]:
    """Processes started inside the block ignore Ctrl-C (SIGINT): this process alone reports it and ends them.

    A terminal's Ctrl-C reaches every process of the foreground group, and each worker process
    would print its own traceback. A Python process that starts with SIGINT ignored keeps it
    ignored. A Ctrl-C that arrives during the block itself is lost (the block only starts
    processes). Outside the main thread, where signal handlers cannot be set, this does nothing.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous if previous is not None else signal.SIG_DFL)
