"""``SegmentSampler`` on a small synthetic storage (no simulator): the ``episode_length`` it writes."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import LazyMemmapStorage, TensorDictReplayBuffer

from tar_rl.data import EPISODE_LENGTH_KEY, SegmentSampler

LENGTHS = (5, 17, 3, 9, 12)  # some shorter than a segment, so segments are padded


def _storage(tmp_path, lengths=LENGTHS) -> LazyMemmapStorage:
    steps = TensorDict(
        {
            "observation": torch.randn(sum(lengths), 2),
            "episode": torch.cat([torch.full((n,), e) for e, n in enumerate(lengths)]),
            "step": torch.cat([torch.arange(n) for n in lengths]),
        },
        [sum(lengths)],
    )
    storage = LazyMemmapStorage(sum(lengths), scratch_dir=tmp_path)
    TensorDictReplayBuffer(storage=storage).extend(steps)
    return storage


def test_every_batch_holds_each_steps_episode_length(tmp_path):
    sampler = SegmentSampler(_storage(tmp_path), 16, 6, generator=torch.Generator().manual_seed(0))
    assert sampler.episode_lengths.tolist() == list(LENGTHS)
    seen = set()
    for _ in range(5):
        batch = sampler.sample()
        length = batch[EPISODE_LENGTH_KEY]
        assert EPISODE_LENGTH_KEY == "episode_length"
        assert length.shape == (16, 6) and length.dtype == torch.int64
        expected = torch.tensor(LENGTHS)[batch["episode"]]
        assert torch.equal(length, expected)
        valid = batch["collector", "mask"]
        assert (batch["step"][valid] < length[valid]).all()
        seen |= set(batch["episode"][:, 0].tolist())
    assert seen == set(range(len(LENGTHS)))


def test_episode_length_may_be_named_among_the_keys(tmp_path):
    sampler = SegmentSampler(_storage(tmp_path), 4, 6, keys=["step", "episode_length"])
    batch = sampler.sample()
    assert set(batch.keys(True, True)) == {"step", "episode", "index", "episode_length", ("collector", "mask")}
    assert torch.equal(batch["episode_length"], torch.tensor(LENGTHS)[batch["episode"]])
    with pytest.raises(KeyError, match="not_there"):
        SegmentSampler(_storage(tmp_path / "other"), 4, 6, keys=["not_there"])


def test_episode_ids_need_not_be_contiguous(tmp_path):
    # ids 0, 2, 3 (no episode 1): the table counts each id's steps
    steps = TensorDict(
        {"observation": torch.randn(9, 2), "episode": torch.tensor([0, 0, 2, 2, 2, 2, 3, 3, 3])},
        [9],
    )
    storage = LazyMemmapStorage(9, scratch_dir=tmp_path)
    TensorDictReplayBuffer(storage=storage).extend(steps)
    sampler = SegmentSampler(storage, 8, 2, generator=torch.Generator().manual_seed(1))
    assert sampler.episode_lengths.tolist() == [2, 0, 4, 3]
    batch = sampler.sample()
    assert torch.equal(batch["episode_length"], torch.tensor([2, 0, 4, 3])[batch["episode"]])
