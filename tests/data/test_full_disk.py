"""Collection into a disk without room for the dataset: one line, nothing left half-written.

The disk is reported full (``shutil.disk_usage``, what the OS says of the folder's file system) for the
test's own dataset folder only; the tiny job collects its dataset there (reach, 2 demonstrations).
"""

from __future__ import annotations

import shutil

import pytest
from recipe_helpers import tiny

from tar_rl.recipes import TrainingError, train


def test_collection_into_a_full_disk_is_one_line_and_leaves_no_temporary_folder(tmp_path, monkeypatch):
    data_root = tmp_path / "data"
    real = shutil.disk_usage

    def disk_usage(path):
        usage = real(path)
        if str(path).startswith(str(data_root)):
            return usage._replace(free=4096)  # 4 kB free: far less than the dataset's few hundred kB
        return usage

    monkeypatch.setattr(shutil, "disk_usage", disk_usage)
    run_dir = tmp_path / "run"
    with pytest.raises(TrainingError) as info:
        train(tiny(tmp_path, data_root, f"run_dir={run_dir}"))
    message = str(info.value)
    assert message.startswith(f"no space left on device while writing {data_root}/metaworld-demos-")
    assert "(disk full: it needs " in message and f"MB, 0.0 MB are free under {data_root})" in message
    assert message.endswith(
        f"; no checkpoint was written yet in {run_dir}: free some space, then run the same command to resume"
    )
    assert "\n" not in message
    assert list(data_root.iterdir()) == []  # no dataset, no temporary folder
