"""Post-training (``init.from``): the round trip, the fresh task rows, the identity and every refusal.

Real MetaWorld, tiny: the shared reach dataset (``recipe_helpers.tiny``) trains a source run once
per module; post-training runs start from it.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch
from recipe_helpers import tiny
from tensordict import TensorDict

from tar_rl import distributed
from tar_rl.collectors.metaworld.tasks import task_index
from tar_rl.recipes import ConfigError, Trainer, run_name, train, validate
from tar_rl.recipes.config import config_dict
from tar_rl.runs import CHECKPOINT, load_checkpoint, save_checkpoint


@pytest.fixture(scope="module")
def source(tmp_path_factory, data_root) -> Path:
    """A finished uniform run with embedding task conditioning (trained on reach only)."""
    tmp = tmp_path_factory.mktemp("source")
    return train(tiny(tmp, data_root, "objective=uniform", "diagnostics.heldout_demos=0"))


def _post(tmp_path, data_root, source, *overrides):
    return tiny(tmp_path, data_root, f"init.from={source}", "seed=7", "diagnostics.heldout_demos=0", *overrides)


def _trainer(config: dict) -> Trainer:
    job = validate(config)
    run_dir = Path(config["runs_root"]) / run_name(config_dict(job.config))
    run_dir.mkdir(parents=True)
    return Trainer(job, run_dir, None, distributed.init("cpu"))


def _batch(n: int = 6) -> TensorDict:
    gen = torch.Generator().manual_seed(3)
    return TensorDict(
        {
            "observation": torch.randn(n, 39, generator=gen),
            "task_id": torch.full((n,), task_index("reach"), dtype=torch.long),
        },
        [n],
    )


def test_first_forward_equals_the_source_and_unseen_task_rows_stay_fresh(tmp_path, data_root, source):
    state = load_checkpoint(source / CHECKPOINT)
    trainer = _trainer(_post(tmp_path, data_root, source))
    from tar_rl.recipes import policy_from_checkpoint

    source_actor = policy_from_checkpoint(state)
    with torch.no_grad():
        expected = source_actor(_batch())["action"]
        got = trainer.policy.actor(_batch())["action"]
    torch.testing.assert_close(got, expected, rtol=0, atol=0)
    # Rows of the 49 task ids the source never trained are this run's fresh rows (seed 7), not the source's.
    key = "module.task_embedding.embedding.weight"
    weights = trainer.policy.actor.state_dict()[key]
    reach = task_index("reach")
    assert torch.equal(weights[reach], state["policy"][key][reach])
    torch.manual_seed(7)
    fresh = _trainer(tiny(tmp_path / "fresh", data_root, "seed=7", "diagnostics.heldout_demos=0"))
    fresh_rows = fresh.policy.actor.state_dict()[key]
    others = [i for i in range(weights.shape[0]) if i != reach]
    assert torch.equal(weights[others], fresh_rows[others])
    assert not torch.equal(weights[others], state["policy"][key][others])


def test_instruction_rows_of_unseen_words_stay_fresh(tmp_path, data_root):
    src = train(
        tiny(tmp_path / "src", data_root, "objective=uniform", "policy.task_conditioning=instruction",
             "diagnostics.heldout_demos=0")
    )  # fmt: skip
    state = load_checkpoint(src / CHECKPOINT)
    trainer = _trainer(_post(tmp_path, data_root, src, "policy.task_conditioning=instruction"))
    encoder = trainer.policy.actor.module.task_embedding
    words = trainer.policy.actor.state_dict()["module.task_embedding.words.weight"]
    saved = state["policy"]["module.task_embedding.words.weight"]
    # reach's instruction in tar_rl.collectors.metaworld.tasks: its words keep the source's rows, the others do not
    reach_words = set(encoder.word_ids[task_index("reach")][encoder.word_mask[task_index("reach")]].tolist())
    assert reach_words
    assert torch.equal(words[0], torch.zeros_like(words[0]))  # the padding word
    for row in range(1, words.shape[0]):
        same = torch.equal(words[row], saved[row])
        assert same == (row in reach_words), row


def test_post_training_run_records_its_source_and_is_named_by_it(tmp_path, data_root, source):
    config = _post(tmp_path, data_root, source)
    run = train(config)
    summary = json.loads((run / "summary.json").read_text())
    assert summary["init"]["source"] == source.name == summary["config"]["init"]["source"]
    assert summary["init"]["source_step"] == 30
    # the same job without init.from is another run; a moved source keeps the post-training run's name
    plain = tiny(tmp_path, data_root, "seed=7", "diagnostics.heldout_demos=0")
    validate(plain)
    assert run_name(plain) != run.name
    moved = tmp_path / "moved" / source.name
    shutil.copytree(source, moved)
    again = _post(tmp_path, data_root, moved)
    assert run_name(config_dict(validate(again).config)) == run.name


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (("policy.hidden=[16,16]",), "parameter module.net.0.weight has shape (32, 71) in the source and (16, 71)"),
        (("policy=act",), "the source is a 'mlp' policy, this run trains 'act'"),
        (("policy.task_conditioning=onehot",), "module.net.0.weight has shape (32, 71) in the source and (32, 89)"),
    ],
)
def test_a_source_of_another_head_or_size_is_refused_before_work(tmp_path, data_root, source, overrides, message):
    config = _post(tmp_path, data_root, source, *overrides)
    with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace(")", r"\)").replace("[", r"\[")):
        train(config)
    assert not (tmp_path / "runs").exists()


def test_missing_unfinished_and_corrupt_sources_are_refused(tmp_path, data_root, source):
    with pytest.raises(ConfigError, match=r"init\.from=.*nowhere: no such run directory or checkpoint"):
        validate(_post(tmp_path, data_root, tmp_path / "nowhere"))
    state = load_checkpoint(source / CHECKPOINT)
    unfinished = tmp_path / "unfinished"
    save_checkpoint({**state, "finished": False, "step": 10}, unfinished)
    with pytest.raises(ConfigError, match=r"the source run is unfinished \(step 10 of 30\)"):
        validate(_post(tmp_path, data_root, unfinished))
    corrupt = tmp_path / "corrupt.pt"
    corrupt.write_bytes(b"not a checkpoint")
    with pytest.raises(ConfigError, match=r"corrupt\.pt is not a readable tar-rl checkpoint"):
        validate(_post(tmp_path, data_root, corrupt))
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ConfigError, match="no checkpoint at"):
        validate(_post(tmp_path, data_root, empty))
    no_tasks = tmp_path / "no_tasks"
    save_checkpoint({k: v for k, v in state.items() if k != "task_ids"}, no_tasks)
    with pytest.raises(ConfigError, match="the checkpoint lacks 'task_ids'"):
        validate(_post(tmp_path, data_root, no_tasks))
    assert not (tmp_path / "runs").exists()


class _Crash(Exception):
    pass


def test_a_killed_post_training_run_resumes_to_the_same_final_weights(tmp_path, data_root, source, monkeypatch):
    from tar_rl.data import SegmentSampler

    whole = train(_post(tmp_path / "whole", data_root, source))
    config = _post(tmp_path / "killed", data_root, source)
    calls = {"n": 0}
    original = SegmentSampler.sample

    def sample(self):
        calls["n"] += 1
        if calls["n"] == 17:  # steps 1..16 done, the checkpoint of step 10 written
            raise _Crash
        return original(self)

    monkeypatch.setattr(SegmentSampler, "sample", sample)
    with pytest.raises(_Crash):
        train(config)
    monkeypatch.setattr(SegmentSampler, "sample", original)
    resumed = train(config)
    assert resumed.name == whole.name
    a, b = load_checkpoint(whole)["policy"], load_checkpoint(resumed)["policy"]
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
