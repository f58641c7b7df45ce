"""Files that run code when a reader unpickles them or loads them with YAML's Python tags, and a runner of
``tar-rl`` commands that reports what each ended with.

Each payload, if executed, creates the folder ``marker`` (``os.mkdir``): a test that finds no marker after a
command read the file knows that no code from it ran.
"""

from __future__ import annotations

import io
import logging
import os
import pickle
import warnings
from pathlib import Path

import pytest
import torch

from tar_rl.cli import main


class _Payload:
    def __init__(self, marker: Path):
        self.marker = str(marker)

    def __reduce__(self):
        return (os.mkdir, (self.marker,))


def pickle_payload(marker: Path) -> bytes:
    """A pickle that creates ``marker`` when unpickled."""
    return pickle.dumps(_Payload(marker))


def torch_payload(marker: Path) -> bytes:
    """A ``torch.save`` file (a zip holding a pickle) that creates ``marker`` when loaded without ``weights_only``."""
    buffer = io.BytesIO()
    torch.save({"format": 1, "state": _Payload(marker)}, buffer)
    return buffer.getvalue()


def yaml_payload(marker: Path) -> str:
    """YAML whose Python tag creates ``marker`` under ``yaml.unsafe_load`` (or ``yaml.load`` with its full loader)."""
    return f"seed: !!python/object/apply:os.mkdir ['{marker}']\n"


def run(argv: list[str]) -> str | None:
    """``tar-rl ARGV`` in this process: ``None`` if it succeeds, else its error message, which must be one line.

    Warnings are recorded, not raised (as in a user's session): a reader that warns before it unpickles still
    unpickles. An exception other than ``SystemExit`` (a traceback instead of a message) fails the test.
    """
    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level  # what Hydra's launcher sets up for `tar-rl train`
    try:
        with warnings.catch_warnings(record=True):
            warnings.simplefilter("always")
            code = main(argv)
    except SystemExit as err:
        message = str(err.code)
        assert "\n" not in message, f"tar-rl {' '.join(argv)} ended with more than one line: {message}"
        return message
    except Exception as err:  # a traceback instead of a message: the test names the command
        pytest.fail(f"tar-rl {' '.join(argv)} raised {type(err).__name__} instead of one line: {err}")
    finally:
        root.handlers[:] = handlers
        root.setLevel(level)
    assert code == 0
    return None
