"""Chunk execution at inference (tar_rl.policies.chunking): temporal ensembling, open loop, history windows.

Expected actions are computed by hand from a fake model whose predictions encode when they were made.
"""

from __future__ import annotations

import pickle

import pytest
import torch
from tensordict import TensorDict
from torch import nn

from tar_rl.policies.chunking import ChunkedActor


class _Clock(nn.Module):
    """Chunk entry j of the prediction made at call s is (100 s + j) / 1000, the same for every slot.

    Records the windows it was given.
    """

    def __init__(self, horizon):
        super().__init__()
        self.horizon, self.calls, self.windows = horizon, 0, []

    def predict_chunk(self, history, history_valid, task_id):
        self.windows.append((history.clone(), history_valid.clone()))
        n = history.shape[0]
        values = (100 * self.calls + torch.arange(self.horizon, dtype=torch.float32)) / 1000
        self.calls += 1
        return values[None, :, None].expand(n, self.horizon, 2).clone()


def _step(actor, obs, init):
    n = len(init)
    td = TensorDict(
        {
            "observation": torch.as_tensor(obs, dtype=torch.float32).reshape(n, 1),
            "task_id": torch.zeros(n, dtype=torch.long),
            "is_init": torch.tensor(init).reshape(n, 1),
        },
        [n],
    )
    return actor(td)["action"][:, 0]


def test_temporal_ensemble_weights_older_predictions_more():
    # H = 3, exp(m) = 2: the prediction made i steps after the oldest one weighs 2 ** -i.
    actor = ChunkedActor(_Clock(3), horizon=3, execution="ensemble", ensemble_decay=float(torch.log(torch.tensor(2.0))))
    got = [float(_step(actor, [0.0], [t == 0])[0]) for t in range(4)]
    expected = [
        0.0,
        (1 * 0.001 + 0.5 * 0.100) / 1.5,
        (1 * 0.002 + 0.5 * 0.101 + 0.25 * 0.200) / 1.75,
        (1 * 0.102 + 0.5 * 0.201 + 0.25 * 0.300) / 1.75,  # the chunk of step 0 has run out
    ]
    assert got == pytest.approx(expected, abs=1e-6)


def test_ensemble_restarts_where_is_init():
    actor = ChunkedActor(_Clock(3), horizon=3, execution="ensemble", ensemble_decay=0.0)
    _step(actor, [0.0, 0.0], [True, True])
    out = _step(actor, [0.0, 0.0], [False, True])  # slot 1 starts a new rollout at call 1
    assert out.tolist() == pytest.approx([(0.001 + 0.100) / 2, 0.100], abs=1e-6)


def test_open_loop_executes_k_actions_per_chunk():
    actor = ChunkedActor(_Clock(4), horizon=4, execution="open_loop", execute_steps=2)
    got = [float(_step(actor, [0.0], [t == 0])[0]) for t in range(5)]
    # chunk 0 gives its actions 0, 1; chunk 1 (made at call 1) its 0, 1; chunk 2 its 0
    assert got == pytest.approx([0.000, 0.001, 0.100, 0.101, 0.200], abs=1e-6)
    assert actor.model.calls == 3


def test_open_loop_refills_only_the_slot_that_restarts():
    actor = ChunkedActor(_Clock(4), horizon=4, execution="open_loop", execute_steps=4)
    _step(actor, [0.0, 0.0], [True, True])
    out = _step(actor, [0.0, 0.0], [False, True])
    assert out.tolist() == pytest.approx([0.001, 0.100], abs=1e-6)


def test_history_window_follows_the_rollout_and_restarts():
    model = _Clock(2)
    actor = ChunkedActor(model, horizon=2, history=3)
    calls = [([1.0, 5.0], [True, True]), ([2.0, 6.0], [False, False]), ([3.0, 7.0], [False, True])]
    for t, (obs, init) in enumerate(calls):
        _step(actor, obs, init)
        window, valid = model.windows[t]
        assert window.shape == (2, 3, 1) and valid.shape == (2, 3)
    window, valid = model.windows[2]
    assert window[0, :, 0].tolist() == [1.0, 2.0, 3.0] and valid[0].tolist() == [True, True, True]
    assert window[1, :, 0].tolist() == [7.0, 7.0, 7.0] and valid[1].tolist() == [False, False, True]
    window, valid = model.windows[1]
    assert window[0, :, 0].tolist() == [1.0, 1.0, 2.0] and valid[0].tolist() == [False, True, True]


class _Big(nn.Module):
    def predict_chunk(self, history, history_valid, task_id):
        return torch.full((history.shape[0], 2, 2), 5.0)


def test_actions_are_clipped_and_a_pickled_copy_starts_fresh():
    actor = ChunkedActor(_Big(), horizon=2)
    assert _step(actor, [0.0], [True]).tolist() == [1.0]
    copy = pickle.loads(pickle.dumps(actor))
    assert copy._window is None and copy._sum is None


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"execution": "chunky"}, "execution"),
        ({"execution": "open_loop", "execute_steps": 9}, "execute_steps"),
        ({"ensemble_decay": -1.0}, "ensemble_decay"),
    ],
)
def test_bad_settings_are_refused(kwargs, message):
    with pytest.raises(ValueError, match=message):
        ChunkedActor(_Clock(4), horizon=4, **kwargs)
