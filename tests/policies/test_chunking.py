"""What chunked heads share (tar_rl.policies.chunking): chunk execution at inference (temporal ensembling,
open loop, history windows), the one ChunkLoss, the shared settings.

Expected actions are computed by hand from a fake model whose predictions encode when they were made;
expected losses from a fake model whose loss is a known function of its inputs.
"""

from __future__ import annotations

import pickle

import pytest
import torch
from objective_helpers import tar_loss
from tensordict import TensorDict
from torch import nn

from tar_rl.objectives import perturb_target
from tar_rl.policies import POLICIES
from tar_rl.policies.chunking import ChunkedActor, ChunkedHeadConfig, ChunkLoss


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


# -- The loss and the settings ----------------------------------------------------------------


class _Chunker(nn.Module):
    """Reads the current observation and the chunk; its chunk loss is ``observation + chunk`` per element
    (observation ``[*B, 1]``), and its extras a scalar loss and a diagnostic. Records what it was given."""

    loss_inputs = ("observation", "action_chunk", "action_chunk_valid", "valid")
    loss_extras = ("loss_extra", "note")
    reads_pixels = False

    def __init__(self):
        super().__init__()
        self.seen = []

    def chunk_loss(self, observation, action_chunk, action_chunk_valid=None, valid=None):
        self.seen.append((action_chunk_valid, valid))
        return observation[..., None] + action_chunk, {"loss_extra": torch.tensor(2.0), "note": torch.tensor(3.0)}


def _segments():
    return TensorDict(
        {
            "observation": torch.tensor([[[1.0], [2.0]]]),
            "action_chunk": torch.tensor([[[[0.5], [0.25]], [[-1.0], [0.0]]]]),  # [1, 2, H=2, A=1]
            "action_chunk_valid": torch.tensor([[[True, True], [True, False]]]),
            ("collector", "mask"): torch.tensor([[True, True]]),
        },
        [1, 2],
    )


def test_chunk_loss_passes_what_the_model_lists_and_returns_its_loss_and_extras():
    model = _Chunker()
    loss = ChunkLoss(model, "loss_toy")
    assert loss.in_keys == ["observation", "action_chunk", "action_chunk_valid", ("collector", "mask")]
    assert loss.out_keys == ["loss_toy", "loss_extra", "note"] and loss.target_key == "action_chunk"
    out = loss(_segments())
    assert out["loss_toy"].tolist() == [[[[1.5], [1.25]], [[1.0], [2.0]]]]
    assert float(out["loss_extra"]) == 2.0 and float(out["note"]) == 3.0
    # the two masks are optional: absent, the model gets None
    loss(_segments().exclude("action_chunk_valid", ("collector", "mask")))
    assert model.seen[-1] == (None, None)
    bad = _segments()
    bad["action_chunk_valid"] = bad["action_chunk_valid"].float()
    with pytest.raises(ValueError, match="action_chunk_valid"):
        loss(bad)


def test_the_objective_corrupts_the_declared_target():
    objective = tar_loss(ChunkLoss(_Chunker(), "loss_toy"), "perturb_high", loss_key="loss_toy")
    assert objective.tensor_keys.action == "action_chunk"
    data = _segments()
    chosen = torch.tensor([[False, True]])
    out = perturb_target(data, "action_chunk", chosen, 0.5, torch.Generator().manual_seed(3))
    noise = torch.randn(1, 2, 2, 1, generator=torch.Generator().manual_seed(3))
    expected = data["action_chunk"].clone()
    expected[0, 1] += 0.5 * noise[0, 1]  # the chosen step's whole chunk, nothing else
    assert torch.equal(out["action_chunk"], expected)
    assert torch.equal(data["action_chunk"], _segments()["action_chunk"])  # the input is not modified


def test_every_chunked_head_takes_the_shared_settings_with_the_same_defaults():
    shared = {"task_conditioning": "embedding", "execution": "ensemble", "execute_steps": 1, "ensemble_decay": 0.01}
    shared |= {"normalize_obs": True, "observation": "state"}
    chunked = [name for name in POLICIES if issubclass(POLICIES[name].config, ChunkedHeadConfig)]
    assert chunked == ["act", "octo_linear", "octo_diffusion", "flow"]
    for name in chunked:
        cfg = POLICIES[name].config()
        assert cfg.name == name and {k: getattr(cfg, k) for k in shared} == shared
