"""Atomic writes: the target is either the old file or the complete new one."""

from __future__ import annotations

import json
import os

import pandas as pd
import pytest

from tar_rl.io import atomic_write, write_csv_atomic, write_json_atomic


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
