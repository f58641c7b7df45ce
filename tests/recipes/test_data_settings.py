"""Data settings of the training job that cannot work, refused before any training step with one line naming the
setting and what it may be: a segment longer than every episode, ``data.tasks`` that are not a ``data.path``
dataset's tasks."""

from __future__ import annotations

import numpy as np
import pytest
from data_helpers import LENGTHS, robomimic_file
from recipe_helpers import TASK, compose_config, tiny

from tar_rl.collectors.metaworld.dataset import build_dataset
from tar_rl.importers import import_robomimic
from tar_rl.recipes import ConfigError, train, validate
from tar_rl.runs import CHECKPOINT


@pytest.fixture
def lift(tmp_path):
    """An imported dataset of the task Lift, episodes of 6 and 5 steps."""
    return import_robomimic(robomimic_file(tmp_path / "lift.hdf5"), "state", out=tmp_path / "data", verbose=False)


def _job(tmp_path, ds, *overrides):
    settings = ("data.slice_len=3", "eval.rollouts=0", f"runs_root={tmp_path / 'runs'}")
    return compose_config(f"data.path={ds.path}", *settings, *overrides)


def test_a_slice_longer_than_the_longest_given_episode_is_refused_before_work(tmp_path, lift):
    longest = max(LENGTHS)
    message = (
        rf"data\.slice_len={longest + 1} is longer than the longest episode of the dataset {lift.path} \({longest} "
        rf"steps\), so every segment would be padded; choose data\.slice_len between 1 and {longest}"
    )
    with pytest.raises(ConfigError, match=message):
        train(_job(tmp_path, lift, f"data.slice_len={longest + 1}"))
    assert not (tmp_path / "runs").exists()
    validate(_job(tmp_path, lift, f"data.slice_len={longest}"))  # the longest episode fills one segment


def test_a_slice_longer_than_the_longest_collected_episode_is_refused_before_the_first_step(tmp_path, data_root):
    # A collected dataset's episodes are known once it is collected: refused then, before any step (400: within
    # MetaWorld's 500-step horizon, which is refused before collecting, below).
    config = tiny(tmp_path, data_root, "data.slice_len=400")
    with pytest.raises(ConfigError, match=r"data\.slice_len=400 is longer than the longest episode") as err:
        train(config)
    ds = build_dataset(data_root, [TASK], 2, workers=1, progress=False, verbose=False)
    longest = int(np.unique(ds.data["episode"].numpy(), return_counts=True)[1].max())  # counted here, by numpy
    assert f"({longest} steps)" in str(err.value) and f"between 1 and {longest}" in str(err.value)
    assert not list((tmp_path / "runs").glob(f"*/{CHECKPOINT}"))


@pytest.mark.parametrize("suite", ["metaworld", "dm_control"])
def test_a_slice_longer_than_any_demonstration_a_suite_collects_is_refused_before_collecting(
    suite, tmp_path, monkeypatch
):
    from tar_rl.collectors import dmc
    from tar_rl.collectors.metaworld import demos

    def no_collection(*args, **kwargs):
        raise AssertionError("collected demonstrations for a job refused before collecting")

    monkeypatch.setattr(demos, "collect", no_collection)
    monkeypatch.setattr(dmc, "expert_episodes", no_collection)
    longest = {"metaworld": 500, "dm_control": 1000}[suite]  # each suite's episode limit, its experts' too
    tasks = {"metaworld": [], "dm_control": ["data.tasks=[point_mass-easy]", "eval.rollouts=0"]}[suite]
    config = tiny(tmp_path, tmp_path / "data", f"data.suite={suite}", *tasks, "data.slice_len=100000")
    message = (
        rf"data\.slice_len=100000 is longer than any demonstration the {suite} suite collects \(at most {longest} "
        rf"steps\), so every segment would be padded; choose data\.slice_len between 1 and {longest}"
    )
    with pytest.raises(ConfigError, match=message):
        train(config)
    assert not (tmp_path / "data").exists() or not any((tmp_path / "data").iterdir())
    validate(tiny(tmp_path, tmp_path / "data", f"data.suite={suite}", *tasks, f"data.slice_len={longest}"))


def test_data_tasks_that_disagree_with_a_given_dataset_are_refused(tmp_path, lift, data_root):
    disagree = r"data\.tasks=\['reach'\] disagrees with the tasks of data\.path=.*\['Lift'\]"
    with pytest.raises(ConfigError, match=disagree):
        validate(_job(tmp_path, lift, "data.tasks=[reach]"))
    validate(_job(tmp_path, lift, "data.tasks=[Lift]"))  # the dataset's own tasks
    validate(_job(tmp_path, lift))  # left at the default: the dataset's tasks
    # A MetaWorld dataset: names and groups resolve in its suite first.
    reach = build_dataset(data_root, [TASK], 2, workers=1, progress=False, verbose=False)
    with pytest.raises(ConfigError, match=r"data\.tasks=\['mt10'\] disagrees with the tasks of data\.path="):
        validate(_job(tmp_path, reach, "data.tasks=[mt10]"))
    validate(_job(tmp_path, reach, "data.tasks=[reach]"))
    assert not (tmp_path / "runs").exists()
