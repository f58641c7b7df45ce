"""The ``flow`` head's ranking signals and its per-segment training times.

* ``action_error``: the error of the chunk the predicted velocity implies, recomputed here from the interpolation
  (``A_hat = x_tau - tau * v_hat``), and ``tau ** 2`` times the velocity loss;
* ``time_normalized``: the loss over a running mean per time bin (:class:`TimeNormalizer`), against hand values,
  and resumed exactly from a checkpoint of the objective;
* ``policy.time_sampling=segment``: one time and one noise chunk per segment, the segments' times stratified.

Expected values are computed here by hand, never read from the code under test.
"""

from __future__ import annotations

import copy
import math

import pytest
import torch
from tensordict import TensorDict

from tar_rl.collectors.metaworld.tasks import INSTRUCTIONS, TASKS
from tar_rl.objectives.signals import TimeNormalizer
from tar_rl.policies import POLICIES, DataInfo, build_policy
from tar_rl.policies.chunking import ChunkLoss
from tar_rl.policies.flow import FlowConfig, FlowPolicy
from tar_rl.recipes import make_objective
from tar_rl.recipes.config import objective_config

H, K, A, D = 4, 3, 4, 39
SMALL = dict(dim=16, heads=2, layers=1, readouts=2)
INFO = DataInfo(chunk_horizon=H, history=K, instructions=tuple(INSTRUCTIONS[t] for t in TASKS))


def segment_batch(b: int = 4, length: int = 6, seed: int = 0) -> TensorDict:
    """``[b, length]`` segments; the last step's chunk runs past its episode, the last segment ends early."""
    g = torch.Generator().manual_seed(seed)
    chunk_valid = torch.ones(b, length, H, dtype=torch.bool)
    chunk_valid[:, -1, 2:] = False
    history_valid = torch.ones(b, length, K, dtype=torch.bool)
    history_valid[:, 0, :-1] = False
    mask = torch.ones(b, length, dtype=torch.bool)
    mask[-1, -2:] = False
    return TensorDict(
        {
            "observation_history": torch.randn(b, length, K, D, generator=g),
            "observation_history_valid": history_valid,
            "task_id": torch.randint(0, 50, (b, length), generator=g),
            "action_chunk": torch.rand(b, length, H, A, generator=g) * 2 - 1,
            "action_chunk_valid": chunk_valid,
            ("collector", "mask"): mask,
        },
        [b, length],
    )


def spy_on_velocity(monkeypatch, model: FlowPolicy) -> dict:
    """Record what the action expert is given and what it predicts."""
    seen, real = {}, model.velocity

    def velocity(x, tau, features):
        v = real(x, tau, features)
        seen.update(x=x.detach().clone(), tau=tau.detach().clone(), v=v.detach().clone())
        return v

    monkeypatch.setattr(model, "velocity", velocity)
    return seen


def held(chunk: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """The chunk the head learns from: entries past the last valid one hold the last valid action (by hand)."""
    out = chunk.clone()
    for index in valid.logical_not().nonzero().tolist():
        *lead, h = index
        last = int(valid[tuple(lead)].sum()) - 1
        out[(*lead, h)] = chunk[(*lead, last)]
    return out


@pytest.mark.parametrize("sampling", ["step", "segment"])
def test_the_action_error_is_the_error_of_the_implied_chunk(monkeypatch, sampling):
    torch.manual_seed(0)
    model = FlowPolicy(FlowConfig(**SMALL, time_sampling=sampling), INFO)
    seen = spy_on_velocity(monkeypatch, model)
    batch = segment_batch()
    out = ChunkLoss(model, "loss_flow", signal="action_error")(batch)
    signal = out["signal"]
    assert signal.shape == (4, 6) and not signal.requires_grad
    # x_tau = tau * noise + (1 - tau) * A, u = noise - A: the velocity v_hat implies A_hat = x_tau - tau * v_hat
    tau = seen["tau"].double()
    implied = seen["x"].double() - tau[:, None, None] * seen["v"].double()
    chunk = held(batch["action_chunk"], batch["action_chunk_valid"]).double()
    error = (implied.reshape(chunk.shape) - chunk).square()
    valid = batch["action_chunk_valid"][..., None].expand_as(error)
    per_step = (error * valid).sum((-2, -1)) / valid.sum((-2, -1))
    torch.testing.assert_close(signal.double(), per_step, rtol=1e-3, atol=1e-9)
    # tau ** 2 times the velocity loss of the step (its mean over the valid chunk entries)
    velocity_loss = (out["loss_flow"].detach() * valid).sum((-2, -1)) / valid.sum((-2, -1))
    torch.testing.assert_close(signal, (tau.reshape(4, 6) ** 2 * velocity_loss.double()).float())


@pytest.mark.parametrize("kind", ["beta", "uniform"])
def test_segment_sampling_gives_one_stratified_time_and_noise_per_segment(monkeypatch, kind):
    torch.manual_seed(3)
    model = FlowPolicy(FlowConfig(**SMALL, time_distribution=kind, time_sampling="segment"), INFO)
    c = 50.0  # a constant prediction: loss = (c - u) ** 2, so the noise is c - sqrt(loss) + chunk
    seen = {}

    def constant(x, tau, features):
        seen["tau"] = tau.clone()
        return torch.full_like(x, c)

    monkeypatch.setattr(model, "velocity", constant)
    b, length = 8, 5
    batch = segment_batch(b, length)
    chunk = batch["action_chunk"]
    loss = model.step_loss(batch["observation_history"], batch["observation_history_valid"], batch["task_id"], chunk)
    tau = seen["tau"].reshape(b, length).double()
    assert (tau == tau[:, :1]).all()  # one time per segment
    u = (tau[:, 0] - 0.001) / 0.999  # the time distribution's CDF, by hand
    u = u**1.5 if kind == "beta" else u
    assert sorted(math.floor(float(x) * b) for x in u) == list(range(b))  # one time in each stratum
    gaps = u.sort().values.diff()
    torch.testing.assert_close(gaps, torch.full_like(gaps, 1 / b), rtol=0, atol=1e-4)  # (u_0 + i / b) mod 1
    noise = c - loss.sqrt() + chunk
    torch.testing.assert_close(noise, noise[:, :1].expand_as(noise), rtol=0, atol=1e-4)  # one noise per segment
    assert not torch.allclose(noise[0, 0], noise[1, 0])
    # per step (the default): the steps of a segment draw their own times
    model.time_sampling = "step"
    model.step_loss(batch["observation_history"], batch["observation_history_valid"], batch["task_id"], chunk)
    assert len(set(seen["tau"].reshape(b, length)[0].tolist())) == length


def test_the_time_normalizer_by_hand():
    norm = TimeNormalizer(bins=2, decay=0.5)
    valid = torch.ones(4, dtype=torch.bool)
    got = norm(torch.tensor([1.0, 3.0, 10.0, 2.0]), torch.tensor([0.1, 0.4, 0.6, 0.9]), valid, update=True)
    # bin 0 mean 2: total 0.5 * 2 = 1, weight 0.5, estimate 2; bin 1 mean 6: estimate 6
    torch.testing.assert_close(got, torch.tensor([0.5, 1.5, 10 / 6, 2 / 6]))
    torch.testing.assert_close(norm.total, torch.tensor([1.0, 3.0], dtype=torch.float64))
    # a padded step and a NaN loss do not count; bin 0 mean 4: total 0.5 + 2 = 2.5, weight 0.75, estimate 10 / 3;
    # bin 1 mean 2 (its valid step only): total 1.5 + 1 = 2.5, estimate 10 / 3
    losses = torch.tensor([4.0, float("nan"), 2.0, 7.0])
    valid = torch.tensor([True, True, True, False])
    position = torch.tensor([0.0, 0.2, 0.7, 1.0])  # F(tau) = 1 falls in the last bin
    got = norm(losses, position, valid, update=False)
    torch.testing.assert_close(got, torch.tensor([1.2, float("nan"), 0.6, 2.1]), equal_nan=True)
    torch.testing.assert_close(norm.weight, torch.tensor([0.5, 0.5], dtype=torch.float64))  # not kept
    norm(losses, position, valid, update=True)
    torch.testing.assert_close(norm.total, torch.tensor([2.5, 2.5], dtype=torch.float64))
    torch.testing.assert_close(norm.weight, torch.tensor([0.75, 0.75], dtype=torch.float64))


def _objective(sampling: str = "step", signal: str = "time_normalized"):
    torch.manual_seed(0)
    policy = build_policy(FlowConfig(**SMALL, time_sampling=sampling), INFO)
    config = objective_config("tar")(name="tar", start=0.0, ramp=0.0, signal=signal)
    objective = make_objective(config, 100, 0, policy).train()
    objective.return_weights = True
    return objective, torch.optim.SGD(objective.parameters(), lr=0.05)


def _steps(objective, optimizer, first: int, count: int) -> list[tuple]:
    rows = []
    for i in range(first, first + count):
        out = objective(segment_batch(seed=i))
        out["loss_tar"].backward()
        optimizer.step()
        optimizer.zero_grad()
        state = objective.inner.signal_state
        rows.append((out["loss_tar"].detach(), out["weights"], state.total.clone(), state.weight.clone()))
    return rows


@pytest.mark.parametrize("sampling", ["step", "segment"])
def test_the_time_normalization_resumes_exactly_from_a_checkpoint(sampling):
    objective, optimizer = _objective(sampling)
    torch.manual_seed(1)
    _steps(objective, optimizer, 0, 3)
    saved = copy.deepcopy(
        {"objective": objective.state_dict(), "optim": optimizer.state_dict(), "rng": torch.get_rng_state()}
    )
    assert (objective.inner.signal_state.weight > 0).any()
    assert {"inner.signal_state.total", "inner.signal_state.weight"} <= set(saved["objective"])
    expected = _steps(objective, optimizer, 3, 3)

    resumed, resumed_optimizer = _objective(sampling)
    resumed.load_state_dict(saved["objective"])
    resumed_optimizer.load_state_dict(saved["optim"])
    torch.set_rng_state(saved["rng"])
    for got, want in zip(_steps(resumed, resumed_optimizer, 3, 3), expected, strict=True):
        for a, b in zip(got, want, strict=True):
            assert torch.equal(a, b)

    # without the normaliser's state the run differs: the state is what the resumed run continued (per step, the
    # weights too; per segment a segment's steps share their time, so its weights do not depend on the estimate)
    fresh, fresh_optimizer = _objective(sampling)
    state = {k: v for k, v in saved["objective"].items() if "signal_state" not in k}
    fresh.load_state_dict(state, strict=False)
    fresh_optimizer.load_state_dict(saved["optim"])
    torch.set_rng_state(saved["rng"])
    (_, weights, total, _), *_ = _steps(fresh, fresh_optimizer, 3, 1)
    assert not torch.equal(total, expected[0][2])
    if sampling == "step":
        assert not torch.allclose(weights, expected[0][1])
    else:
        torch.testing.assert_close(weights, expected[0][1])


def test_an_inspection_pass_does_not_move_the_state():
    objective, _ = _objective()
    objective(segment_batch())
    state = objective.inner.signal_state.total.clone()
    with torch.no_grad():
        objective(segment_batch(seed=1))
    objective.eval()
    objective.inspect_steps(segment_batch(seed=2))
    assert torch.equal(objective.inner.signal_state.total, state)


def test_the_registered_heads_declare_the_signals_their_losses_offer():
    for name, spec in POLICIES.items():
        policy = build_policy({"name": name}, DataInfo(chunk_horizon=H, history=K))
        assert tuple(getattr(policy.loss, "signals", ("loss",))) == ("loss", *spec.signals), name
    assert POLICIES["flow"].signals == ("action_error", "time_normalized")
