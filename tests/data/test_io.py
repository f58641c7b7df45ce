"""Atomic writes: the target is either the old file or the complete new one."""

from __future__ import annotations

import errno
import json
import os

import pandas as pd
import pytest
import torch
from disk_helpers import FullDisk

from tar_rl import io
from tar_rl.errors import DiskFullError
from tar_rl.io import atomic_write, save_torch_atomic, write_csv_atomic, write_json_atomic


def test_failed_write_keeps_the_old_file_and_leaves_no_temp(tmp_path):
    path = tmp_path / "sub" / "table.csv"
    write_csv_atomic(pd.DataFrame({"a": [1, 2]}), path)

    def broken(f):
        f.write("half a row")
        raise RuntimeError("crash mid-write")

    with pytest.raises(RuntimeError, match="crash mid-write"):
        atomic_write(path, broken)
    assert pd.read_csv(path)["a"].tolist() == [1, 2]
    assert os.listdir(path.parent) == ["table.csv"]
    assert (path.stat().st_mode & 0o777) == 0o644


def test_json_round_trip(tmp_path):
    path = write_json_atomic({"tasks": ["reach-v3"], "n": 3}, tmp_path / "m.json")
    assert json.loads(path.read_text()) == {"tasks": ["reach-v3"], "n": 3}


@pytest.mark.parametrize(
    ("name", "write"),
    [
        ("state.pt", lambda path: save_torch_atomic({"w": torch.zeros(1000)}, path)),  # torch wraps the OSError
        ("table.csv", lambda path: write_csv_atomic(pd.DataFrame({"a": [3]}), path)),
        ("summary.json", lambda path: write_json_atomic({"a": 3}, path)),
    ],
)
def test_a_full_disk_names_the_file_and_keeps_the_old_one(tmp_path, monkeypatch, name, write):
    path = tmp_path / name
    path.write_bytes(b"old content")
    real_open = io._open
    monkeypatch.setattr(io, "_open", lambda fd, binary, target: FullDisk(real_open(fd, binary, target)))
    with pytest.raises(DiskFullError) as info:
        write(path)
    assert str(info.value) == (
        f"no space left on device while writing {path} (disk full); the previous {name}, if any, is unchanged"
    )
    assert isinstance(info.value, OSError) and info.value.errno == errno.ENOSPC
    assert path.read_bytes() == b"old content"
    assert os.listdir(tmp_path) == [name]  # no temporary file left
