"""The time axis and the reduction over it, on hand-made tensors: TAR's weights are tar-rl's ``tar_weights`` and
the paper's (the plain-Python reference of tar-rl's tests), padding never counts, ``[B]`` per item."""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import pytest
import torch
from lerobot_policy_tar.tar_source import tar_weights
from lerobot_policy_tar.time_axis import ElementLosses, effective_sample_size, fold_segments, reduce_over_time

REPO = Path(__file__).resolve().parents[2]
TAR = {"gamma": 1.0, "w_max": 3.0, "eps": 1e-8, "cap": "paper"}


def _reference():
    """tar-rl's independent plain-Python reading of Eqs. 3-8 (tests/tar_reference.py)."""
    spec = importlib.util.spec_from_file_location("tar_reference", REPO / "tests" / "tar_reference.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _step_loss(loss: torch.Tensor, valid: torch.Tensor) -> float:
    """A step's loss by hand: the mean over its valid chunk entries of each entry's mean over the action dims."""
    entries = [sum(loss[h].tolist()) / loss.shape[1] for h in range(loss.shape[0]) if valid[h]]
    return sum(entries) / len(entries) if entries else 0.0


def test_weights_are_tar_rls_and_the_papers_on_the_same_step_losses():
    generator = torch.Generator().manual_seed(0)
    loss = torch.rand(24, 5, 3, generator=generator, dtype=torch.float64) ** 3  # B=4 segments of L=6 steps, H=5, A=3
    entry_valid = torch.rand(24, 5, generator=generator) > 0.3
    segments = torch.rand(4, 6, generator=generator) > 0.2
    segments[:, 0] = True
    steps = torch.tensor([_step_loss(loss[n], entry_valid[n]) for n in range(24)], dtype=torch.float64).reshape(4, 6)
    for kw in (TAR, {**TAR, "gamma": 2.5, "w_max": 1.5, "cap": "exact"}, {**TAR, "w_max": math.inf}):
        out = reduce_over_time(ElementLosses(loss, entry_valid), segments=segments, mix=1.0, **kw)
        valid = segments & entry_valid.any(-1).reshape(4, 6)
        torch.testing.assert_close(out.losses, steps)
        assert torch.equal(out.valid, valid)
        assert torch.equal(out.weights, tar_weights(out.losses, valid, mix=1.0, **kw))
        reference = _reference().ref_tar(steps, valid, gamma=kw["gamma"], w_max=kw["w_max"], cap=kw["cap"])
        torch.testing.assert_close(out.weights, reference, rtol=1e-9, atol=1e-12)
        by_hand = [
            sum(out.weights[b, t].item() * steps[b, t].item() for t in range(6) if valid[b, t]) / int(valid[b].sum())
            for b in range(4)
        ]
        torch.testing.assert_close(out.per_item, torch.tensor(by_hand, dtype=torch.float64))


def test_hand_computed_chunk_weights_and_padding_that_never_counts():
    # One chunk of 5 entries, the last padded (and holding a huge loss and a NaN), one action dim: losses 1, 1, 1, 9.
    loss = torch.tensor([[[1.0], [1.0], [1.0], [9.0], [float("nan")]]], dtype=torch.float64)
    valid = torch.tensor([[True, True, True, True, False]])
    out = reduce_over_time(ElementLosses(loss, valid), segments=None, mix=1.0, **{**TAR, "w_max": math.inf})
    # Eqs. 4-7 by hand (tar-rl's tests/objectives/test_tar_math_imports.py): w = (a, a, a, b), r = e^(4/sqrt(3)).
    r = math.exp(4 / math.sqrt(3))
    a, b = 4 / (3 + r), 4 * r / (3 + r)
    torch.testing.assert_close(out.weights[0], torch.tensor([a, a, a, b, 0.0], dtype=torch.float64))
    torch.testing.assert_close(out.per_item, torch.tensor([(3 * a + 9 * b) / 4], dtype=torch.float64))


def test_the_schedule_off_gives_the_mean_over_valid_entries_and_the_regulariser_is_added_unweighted():
    loss = torch.tensor([[[2.0, 4.0], [6.0, 8.0], [100.0, 100.0]]])  # entries 3, 7 and a padded one
    valid = torch.tensor([[True, True, False]])
    out = reduce_over_time(ElementLosses(loss, valid, torch.tensor([0.5])), segments=None, mix=0.0, **TAR)
    torch.testing.assert_close(out.per_item, torch.tensor([(3.0 + 7.0) / 2 + 0.5]))
    # In segment mode the regulariser is averaged over the valid steps: steps (3, 7) and (11, -), KL 1 and 3.
    loss = torch.tensor([[[2.0, 4.0], [6.0, 8.0]], [[10.0, 12.0], [0.0, 0.0]]])
    entries = torch.tensor([[True, True], [True, False]])
    out = reduce_over_time(
        ElementLosses(loss, entries, torch.tensor([1.0, 3.0])), segments=torch.tensor([[True, True]]), mix=0.0, **TAR
    )
    torch.testing.assert_close(out.losses, torch.tensor([[5.0, 11.0]]))
    torch.testing.assert_close(out.per_item, torch.tensor([(5.0 + 11.0) / 2 + (1.0 + 3.0) / 2]))


def test_effective_sample_size_by_hand():
    # (2, 1, 1) over 3 real steps: 4^2 / (3 * 6) = 8/9; (1, 1): 1; a segment without a real step does not count.
    weights = torch.tensor([[2.0, 1.0, 1.0, 0.0], [1.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0]])
    valid = torch.tensor([[True, True, True, False], [True, True, False, False], [False] * 4])
    assert effective_sample_size(weights, valid).item() == pytest.approx((8 / 9 + 1) / 2)
    one_step = torch.tensor([[4.0, 0.0, 0.0, 0.0]])
    assert effective_sample_size(one_step, torch.ones(1, 4, dtype=torch.bool)).item() == pytest.approx(1 / 4)


def test_the_uniform_loss_is_the_mean_over_valid_steps_whatever_the_weights():
    # Steps 1, 1, 1, 9 (and a padded NaN) with full TAR: the weighted loss is above the uniform one, 3, plus KL 0.5.
    loss = torch.tensor([[[1.0], [1.0], [1.0], [9.0], [float("nan")]]], dtype=torch.float64)
    valid = torch.tensor([[True, True, True, True, False]])
    out = reduce_over_time(ElementLosses(loss, valid, torch.tensor([0.5], dtype=torch.float64)), segments=None,
                           mix=1.0, **TAR)  # fmt: skip
    torch.testing.assert_close(out.uniform, torch.tensor([3.0 + 0.5], dtype=torch.float64))
    assert out.per_item.item() > out.uniform.item()


def test_fold_segments_gives_each_step_its_own_observation_window_and_chunk():
    b, length, chunk = 2, 3, 4
    state = torch.arange(b * 5 * 2, dtype=torch.float32).reshape(b, 5, 2)  # n_obs_steps 3 -> 3 + 2 frames
    action = torch.arange(b * 6, dtype=torch.float32).reshape(b, 6, 1)  # chunk 4 -> 4 + 2 actions
    action_is_pad = torch.zeros(b, 6, dtype=torch.bool)
    action_is_pad[1, 3:] = True  # item 1's episode ends after its third action (delta -2 + 3 = index 3 is pad)
    batch = {
        "observation.state": state,
        "observation.state_is_pad": torch.zeros(b, 5, dtype=torch.bool),
        "action": action,
        "action_is_pad": action_is_pad,
        "task": ["a", "b"],
        "index": torch.tensor([10, 20]),
    }
    folded, valid = fold_segments(
        batch,
        slice_len=length,
        observation_keys=["observation.state"],
        observation_window=3,
        action_window=chunk,
        action_offset=2,  # Diffusion's action deltas start at 1 - n_obs_steps = -2
    )
    for i in range(b):
        for t in range(length):
            n = i * length + t
            assert torch.equal(folded["observation.state"][n], state[i, t : t + 3])
            assert torch.equal(folded["action"][n], action[i, t : t + chunk])
            assert torch.equal(folded["action_is_pad"][n], action_is_pad[i, t : t + chunk])
            assert folded["task"][n] == ["a", "b"][i]
            assert folded["index"][n] == [10, 20][i]
    # step t's current action is index t + 2: item 1's steps 0 (index 2) is real, 1 and 2 (indices 3, 4) are not
    assert valid.tolist() == [[True, True, True], [True, False, False]]
    # a base policy that reads one observation step without a time axis (ACT)
    folded, _ = fold_segments(
        {"observation.state": state[:, :3], "action": action[:, :6]},
        slice_len=3,
        observation_keys=["observation.state"],
        observation_window=None,
        action_window=4,
        action_offset=0,
    )
    assert folded["observation.state"].shape == (6, 2)
    assert torch.equal(folded["observation.state"][4], state[1, 1])


def test_fold_segments_refuses_a_batch_of_other_delta_timestamps():
    with pytest.raises(ValueError, match="needs 6 actions per item"):
        fold_segments(
            {"action": torch.zeros(2, 4, 1)},
            slice_len=3,
            observation_keys=[],
            observation_window=None,
            action_window=4,
            action_offset=0,
        )
