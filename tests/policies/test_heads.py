"""The contract every registered policy head keeps (tar_rl.policies), checked on each of them.

Per head: the per-step loss keeps the segment axes ``[B, L, ...]`` and step ``t``'s loss depends on
step ``t``'s inputs only; padded steps and padded chunk entries do not reach the objective; the
loss goes down on a tiny fixed dataset within a few dozen steps; every parameter gets a gradient;
inference gives finite actions of shape ``[N, 4]`` inside ``[-1, 1]``; a state-dict round trip gives
identical actions; a pickled actor (what the evaluation workers receive) acts like the original;
and one tiny training job runs through the recipe. Head-specific checks live in ``test_head_*.py``.
"""

from __future__ import annotations

import json
import math
import pickle

import pandas as pd
import pytest
import torch
from recipe_helpers import tiny
from tensordict import TensorDict

from tar_rl import TARLoss
from tar_rl.collectors.metaworld.tasks import TASKS
from tar_rl.policies import POLICIES, DataInfo, build_policy
from tar_rl.recipes import make_objective, train
from tar_rl.recipes.config import objective_config

HEADS = sorted(POLICIES)
B, L, H, K = 4, 16, 8, 2
INFO = DataInfo(chunk_horizon=H, history=K)


def _head(name: str, seed: int = 0):
    torch.manual_seed(seed)
    return build_policy({"name": name}, INFO)


def _objective(policy, weighting: str = "uniform") -> TARLoss:
    return make_objective(objective_config(weighting)(name=weighting, start=0.0, ramp=0.0), 100, 0, policy)


def _batch(seed: int = 0) -> TensorDict:
    """``[B, L]`` segments: every task id appears; the last segment ends early (padded steps) and the
    chunks of its last real steps run past the end of their episode; the first step of each segment
    starts an episode (no past observation)."""
    g = torch.Generator().manual_seed(seed)
    obs = torch.randn(B, L, 39, generator=g)
    history = torch.cat([torch.randn(B, L, K - 1, 39, generator=g), obs[:, :, None]], dim=2)
    history_valid = torch.ones(B, L, K, dtype=torch.bool)
    history_valid[:, 0, :-1] = False
    valid = torch.ones(B, L, dtype=torch.bool)
    valid[-1, 12:] = False
    chunk_valid = torch.ones(B, L, H, dtype=torch.bool)
    for t in range(8, 12):
        chunk_valid[-1, t, 12 - t :] = False
    # A smooth target, so that a few dozen steps can fit it: the action depends on the observation.
    chunk = torch.tanh(obs[..., None, :4] + 0.1 * torch.arange(H)[:, None])
    return TensorDict(
        {
            "observation": obs,
            "task_id": (torch.arange(B * L) % len(TASKS)).reshape(B, L),
            "action": chunk[:, :, 0].clone(),
            "action_chunk": chunk,
            "action_chunk_valid": chunk_valid,
            "observation_history": history,
            "observation_history_valid": history_valid,
            "episode": torch.arange(B)[:, None].expand(B, L).clone(),
            "step": torch.arange(L).expand(B, L).clone(),
            ("collector", "mask"): valid,
        },
        [B, L],
    )


def _step_losses(objective: TARLoss, batch: TensorDict, seed: int = 7) -> torch.Tensor:
    torch.manual_seed(seed)  # stochastic heads (diffusion, flow, CVAE) draw the same noise each call
    return objective.step_losses(batch)


def _inference_input(n: int = 5, seed: int = 3) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    return TensorDict(
        {
            "observation": torch.randn(n, 39, generator=g),
            "task_id": torch.arange(n) * 7 % len(TASKS),
            "is_init": torch.ones(n, 1, dtype=torch.bool),
        },
        [n],
    )


def _act(actor, steps: int = 3) -> torch.Tensor:
    """Actions of a few consecutive calls (a rollout's start, then two more steps)."""
    out = []
    with torch.no_grad():
        for t in range(steps):
            td = _inference_input(seed=3 + t)
            td.set("is_init", torch.full((5, 1), t == 0))
            out.append(actor(td)["action"])
    return torch.stack(out)


@pytest.mark.parametrize("name", HEADS)
def test_per_step_loss_keeps_the_segment_axes_and_mixes_no_steps(name):
    policy = _head(name)
    objective = _objective(policy)
    batch = _batch()
    losses = _step_losses(objective, batch)
    assert losses.shape == (B, L) and torch.isfinite(losses[batch["collector", "mask"]]).all()
    # Changing step 5 of segment 0 changes that step's loss and no other.
    changed = batch.clone()
    changed["observation"][0, 5] += 1.0
    changed["observation_history"][0, 5, -1] += 1.0
    changed["action"][0, 5] *= -1
    changed["action_chunk"][0, 5] *= -1
    other = _step_losses(objective, changed)
    differs = (other - losses).abs() > 1e-6
    assert differs[0, 5]
    differs[0, 5] = False
    assert not differs.any(), f"{name}: a change at one step moved the losses of others at {differs.nonzero().tolist()}"


@pytest.mark.parametrize("name", HEADS)
def test_padding_does_not_reach_the_objective(name):
    policy = _head(name)
    objective = _objective(policy, "tar")
    objective.eval()  # no schedule step
    batch = _batch()
    torch.manual_seed(7)
    reference = objective(batch)["loss_tar"]
    garbled = batch.clone()
    pad = ~batch["collector", "mask"]
    garbled["observation"][pad] = 1e3
    garbled["action"][pad] = 0.5
    garbled["action_chunk"][pad] = -0.5
    chunk_pad = ~batch["action_chunk_valid"]
    garbled["action_chunk"][chunk_pad] = 0.9
    torch.manual_seed(7)
    assert torch.equal(objective(garbled)["loss_tar"], reference)


@pytest.mark.parametrize("name", HEADS)
def test_loss_decreases_on_a_tiny_dataset_and_every_parameter_learns(name):
    policy = _head(name)
    objective = _objective(policy)
    batch = _batch()
    mask = batch["collector", "mask"]
    before = _step_losses(objective, batch)[mask].mean()
    params = [p for p in objective.parameters() if p.requires_grad]
    optimizer = torch.optim.Adam(params, lr=1e-3)
    for step in range(40):
        optimizer.zero_grad()
        loss = objective(batch)["loss_tar"]
        loss.backward()
        if step == 0:
            names = [n for n, p in objective.named_parameters() if p.requires_grad]
            dead = [n for n, p in zip(names, params) if p.grad is None or not p.grad.abs().sum() > 0]
            assert not dead, f"{name}: no gradient reaches {dead}"
        optimizer.step()
    after = _step_losses(objective, batch)[mask].mean()
    assert after < 0.8 * before, f"{name}: loss {float(before):.4f} -> {float(after):.4f} in 40 steps"


@pytest.mark.parametrize("name", HEADS)
def test_inference_shape_bounds_and_round_trips(name):
    policy = _head(name)
    actor = policy.actor.eval()
    actions = _act(actor)
    assert actions.shape == (3, 5, 4) and torch.isfinite(actions).all()
    assert actions.abs().max() <= 1.0
    # A state-dict round trip into a head built with other random weights acts identically.
    other = _head(name, seed=1).actor.eval()
    assert not torch.equal(_act(other), actions)
    other.load_state_dict(actor.state_dict())
    assert torch.equal(_act(other), actions)
    # A pickled copy (as sent to evaluation workers) acts identically, from a fresh start.
    assert torch.equal(_act(pickle.loads(pickle.dumps(_head(name).actor.eval()))), actions)


@pytest.mark.parametrize("name", HEADS)
def test_inference_is_deterministic_across_runs(name):
    first = _act(_head(name).actor.eval())
    torch.manual_seed(12345)  # the global RNG must not matter at inference
    second = _act(_head(name).actor.eval())
    assert torch.equal(first, second)


@pytest.mark.slow
@pytest.mark.parametrize("name", HEADS)
def test_a_tiny_job_trains_and_evaluates_each_head_through_the_recipe(name, tmp_path, data_root):
    config = tiny(tmp_path, data_root, f"policy={name}", "objective=tar", "optim.steps=12")
    run_dir = train(config)
    assert run_dir.parent == tmp_path / "runs" and run_dir.name.startswith(f"tar-{name}-")
    rollouts = pd.read_csv(run_dir / "eval_rollouts.csv")
    assert len(rollouts) == 1 and rollouts.steps.between(1, 20).all()
    metrics = pd.read_csv(run_dir / "metrics.csv")
    losses = metrics[(metrics.phase == "train") & (metrics.name == "loss")]
    assert list(losses.step) == [5, 10, 12] and losses.value.map(math.isfinite).all()
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["finished"] and summary["policy"] == name and summary["steps"] == 12
