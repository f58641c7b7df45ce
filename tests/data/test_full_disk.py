"""Collection into a disk without room for the dataset: one line, nothing left half-written.

The disk is reported full (``shutil.disk_usage``, what the OS says of the folder's file system) for the
test's own dataset folder only; the tiny job collects its dataset there (reach, 2 demonstrations).
"""

from __future__ import annotations

import shutil

import pytest
from recipe_helpers import TASK, tiny

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


def _without_times(metadata: dict) -> dict:
    return {k: v for k, v in metadata.items() if k not in ("created", "collection_seconds")}


def test_demonstrations_collected_before_the_disk_filled_are_kept_and_written_by_the_next_build(
    tmp_path, monkeypatch, capsys
):
    """The disk has no room for the dataset once its demonstrations are collected (the write refused, as
    ``write_dataset`` refuses it), but room for the demonstrations as collected: they are kept beside where the dataset
    goes, the message says where, and the same build after space is freed writes them without collecting again, the
    dataset equal to one collected afresh."""
    import errno
    import os

    from tar_rl.collectors.metaworld import dataset as mw_dataset
    from tar_rl.collectors.metaworld import demos
    from tar_rl.errors import DiskFullError

    root = tmp_path / "data"

    def no_room(folder, name, data, metadata):
        raise DiskFullError(folder / name, OSError(errno.ENOSPC, os.strerror(errno.ENOSPC)), "it needs 9.9 MB")

    with monkeypatch.context() as full:
        full.setattr(mw_dataset, "write_dataset", no_room)
        with pytest.raises(DiskFullError) as info:
            mw_dataset.build_dataset(root, [TASK], 2, workers=1, progress=False, verbose=False)
    kept = root / f".{info.value.path.name}{mw_dataset.KEPT_SUFFIX}"
    assert str(info.value).startswith(f"no space left on device while writing {info.value.path} (disk full: it needs ")
    note = f"9.9 MB; the 2 collected demonstrations are kept in {kept}, which the same command writes instead of"
    assert note in str(info.value)
    assert sorted(p.name for p in root.iterdir()) == [kept.name]

    def no_collection(*args, **kwargs):
        raise AssertionError("collected again")

    monkeypatch.setattr(demos, "collect", no_collection)
    built = mw_dataset.build_dataset(root, [TASK], 2, workers=1, progress=False, verbose=False)
    assert f"the demonstrations collected earlier for {built.path}, kept in {kept}" in capsys.readouterr().out
    assert sorted(p.name for p in root.iterdir()) == [built.path.name]  # the kept file goes once written
    monkeypatch.undo()
    fresh = mw_dataset.build_dataset(tmp_path / "fresh", [TASK], 2, workers=1, progress=False, verbose=False)
    assert fresh.path.name == built.path.name and _without_times(built.metadata) == _without_times(fresh.metadata)
    assert all((built.data[k] == fresh.data[k]).all() for k in fresh.data.keys(True, True))


def test_an_unreadable_kept_collection_is_removed_and_collected_again(tmp_path, capsys):
    from tar_rl.collectors.metaworld import dataset as mw_dataset

    root = tmp_path / "data"
    first = mw_dataset.build_dataset(root, [TASK], 2, workers=1, progress=False, verbose=False)
    shutil.rmtree(first.path)
    kept = root / f".{first.path.name}{mw_dataset.KEPT_SUFFIX}"
    kept.write_bytes(b"not a collection")
    again = mw_dataset.build_dataset(root, [TASK], 2, workers=1, progress=False, verbose=False)
    out = capsys.readouterr().out
    assert f"removing {kept}: it cannot be read (ValueError: not an npz archive); collecting again" in out
    assert sorted(p.name for p in root.iterdir()) == [again.path.name]
