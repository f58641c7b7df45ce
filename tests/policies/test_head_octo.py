"""The Octo-style heads (``octo_linear``, ``octo_diffusion``) and the ``flow`` head.

Expected values are computed by hand here (the cosine schedule, the forward process, DDIM and DDPM
steps, the flow interpolation, Euler steps), never read from the code under test; the generic
head contract (shapes, save/load, gradients) is also checked by tests/recipes/test_recipes.py and
tests/policies/test_heads.py over every registered head.
"""

from __future__ import annotations

import copy
import math
import pickle
from datetime import timedelta

import pandas as pd
import pytest
import torch
from objective_helpers import tar_loss
from tensordict import TensorDict

from tar_rl.collectors.metaworld.tasks import INSTRUCTIONS, TASKS
from tar_rl.policies import POLICIES, DataInfo, build_policy
from tar_rl.policies.diffusion import (
    OctoDiffusion,
    OctoDiffusionConfig,
    cosine_alpha_bar,
    ddim_sample,
    sampling_timesteps,
)
from tar_rl.policies.flow import FlowConfig, FlowPolicy, euler_integrate, sample_flow_time
from tar_rl.policies.octo import OctoBackbone, OctoConfig, OctoLinear, OctoLinearConfig

HEADS = ("octo_linear", "octo_diffusion", "flow")
H, K, A, D = 4, 3, 4, 39
SMALL = dict(dim=16, heads=2, layers=1, readouts=2)  # a tiny backbone for fast tests
INFO = DataInfo(chunk_horizon=H, history=K, instructions=tuple(INSTRUCTIONS[t] for t in TASKS))


def small(name: str, **extra):
    cfg = POLICIES[name].config(**SMALL)
    for key, value in extra.items():
        setattr(cfg, key, value)
    return cfg


def hand_alpha_bar(T: int, s: float = 0.008) -> list[float]:
    """alpha_bar_t = f(t + 1) / f(0), f(u) = cos((u / T + s) / (1 + s) * pi / 2) ** 2; last beta clipped to 0.999."""

    def f(u: float) -> float:
        return math.cos((u / T + s) / (1 + s) * math.pi / 2) ** 2

    out = [f(t + 1) / f(0) for t in range(T - 1)]
    out.append(out[-1] * (1 - 0.999))  # beta_{T-1} = 1 - f(T) / f(T-1) = 1 - ~0 > 0.999: clipped
    return out


def segment_batch(b: int = 3, length: int = 5, seed: int = 0) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    chunk_valid = torch.ones(b, length, H, dtype=torch.bool)
    chunk_valid[:, -1, 2:] = False
    history_valid = torch.ones(b, length, K, dtype=torch.bool)
    history_valid[:, 0, :-1] = False
    history_valid[:, 1, 0] = False
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


# -- The backbone -----------------------------------------------------------------------------


def test_attention_rules_are_octos_block_structure():
    # order: task, obs t0, obs t1, readout 0, readout 1 (row: query, column: key)
    expected = torch.tensor(
        [
            [1, 0, 0, 0, 0],  # task: itself
            [1, 1, 0, 0, 0],  # obs t0: task, obs <= t0
            [1, 1, 1, 0, 0],  # obs t1: task, obs <= t1
            [1, 1, 1, 1, 1],  # readouts: task, every obs, the readouts
            [1, 1, 1, 1, 1],
        ],
        dtype=torch.bool,
    )
    assert torch.equal(OctoBackbone.attention_rules(2, 2), expected)


@pytest.mark.parametrize("name", HEADS)
def test_an_invalid_history_entry_does_not_change_the_output_and_a_valid_one_does(name):
    torch.manual_seed(0)
    model = build_policy(small(name), INFO).loss.model.eval()
    g = torch.Generator().manual_seed(1)
    history = torch.randn(6, K, D, generator=g)
    valid = torch.ones(6, K, dtype=torch.bool)
    valid[:, 0] = False  # the oldest entry is before the episode start
    task = torch.randint(0, 50, (6,), generator=g)
    base = model.backbone(history, valid, task)

    changed = history.clone()
    changed[:, 0] = torch.randn(6, D, generator=g) * 10  # the invalid entry
    assert torch.equal(model.backbone(changed, valid, task), base)
    changed = history.clone()
    changed[:, 1] += 1.0  # a valid entry
    assert not torch.allclose(model.backbone(changed, valid, task), base)
    # and the sampled chunks follow (same sampling noise: a fresh copy each time)
    chunk = copy.deepcopy(model).predict_chunk(history, valid, task)
    invalid_changed = history.clone()
    invalid_changed[:, 0] = -history[:, 0] * 3
    assert torch.equal(copy.deepcopy(model).predict_chunk(invalid_changed, valid, task), chunk)


def test_every_head_shares_the_identical_backbone():
    backbones = {}
    for name in HEADS:
        cfg = POLICIES[name].config()
        assert isinstance(cfg, OctoConfig)
        shared = {f: getattr(cfg, f) for f in OctoConfig.__dataclass_fields__ if f != "name"}
        assert shared == {f: getattr(OctoConfig(), f) for f in shared}  # the same defaults
        torch.manual_seed(0)
        model = build_policy(cfg, INFO).loss.model
        assert type(model.backbone) is OctoBackbone
        backbones[name] = model.backbone.state_dict()
    # built first under the same seed: the very same initial backbone, only the head differs
    ref = backbones["octo_linear"]
    for name in HEADS[1:]:
        assert list(backbones[name]) == list(ref)
        assert all(torch.equal(backbones[name][k], ref[k]) for k in ref), name


@pytest.mark.parametrize("name", HEADS)
def test_per_step_loss_is_per_chunk_element_and_never_reduced(name):
    torch.manual_seed(0)
    policy = build_policy(small(name), INFO)
    assert policy.event_valid == "action_chunk_valid" and policy.loss_key is None
    batch = segment_batch()
    out = policy.loss(batch)
    (key,) = [k for k in out.keys() if k.startswith("loss_")]
    assert out[key].shape == (3, 5, H, A)
    # through TARLoss: a scalar, finite, and gradients reach every parameter
    loss = tar_loss(policy.loss, "tar")
    loss.set_keys(event_valid=policy.event_valid)
    total = loss(batch)["loss_tar"]
    total.backward()
    assert torch.isfinite(total)
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in policy.actor.parameters())


@pytest.mark.parametrize("control", ["perturb_high", "perturb_low"])
def test_perturbation_controls_corrupt_the_chunk_the_head_learns_from(control):
    torch.manual_seed(0)
    policy = build_policy(small("octo_linear"), INFO)
    loss = tar_loss(policy.loss, control, perturb_fraction=0.5, perturb_scale=0.3)
    loss.set_keys(event_valid=policy.event_valid)
    assert loss.tensor_keys.action == "action_chunk"
    batch = segment_batch()
    seen = []
    step_loss = policy.loss.model.step_loss

    def spy(history, history_valid, task_id, chunk):
        seen.append(chunk.clone())
        return step_loss(history, history_valid, task_id, chunk)

    policy.loss.model.step_loss = spy
    out = loss(batch)
    # the clean pass (which steps to corrupt), then the pass on the corrupted copy
    clean = batch["action_chunk"].clone()
    clean[:, -1, 2:] = clean[:, -1, 1:2]  # padded entries hold the last valid action (segment_batch)
    assert torch.equal(seen[0], clean)
    changed = (seen[-1] != clean).flatten(-2).any(-1)  # [B, L]
    assert changed.any() and float(out["perturbed_fraction"]) > 0
    assert torch.equal(seen[-1][~changed], clean[~changed])
    assert ((seen[-1] != clean).flatten(-2).sum(-1)[changed] >= 2 * A).all()  # whole valid chunks corrupted


def test_padded_chunk_entries_hold_the_last_valid_action_before_the_head_sees_them():
    torch.manual_seed(0)
    policy = build_policy(small("flow"), INFO)
    seen = []

    def flow_loss(history, history_valid, task_id, chunk):  # the flow head's loss and times (step_loss: the loss)
        seen.append(chunk)
        return torch.zeros(chunk.shape), torch.zeros(chunk.shape[:-2])

    policy.loss.model.flow_loss = flow_loss
    batch = segment_batch()
    valid = batch["action_chunk_valid"]
    valid[0, 0, 1:] = False
    valid[1, 2, :] = False  # no valid entry: the first one is held
    policy.loss(batch)
    expected = batch["action_chunk"].clone()
    expected[:, -1, 2:] = expected[:, -1, 1:2]
    expected[0, 0, 1:] = expected[0, 0, 0]
    expected[1, 2, 1:] = expected[1, 2, 0]
    assert torch.equal(seen[0], expected)


def test_octo_linear_loss_is_the_squared_error_of_its_chunk():
    torch.manual_seed(0)
    policy = build_policy(small("octo_linear"), INFO)
    batch = segment_batch()
    pred = policy.loss.model(batch["observation_history"], batch["observation_history_valid"], batch["task_id"])
    target = batch["action_chunk"].clone()
    target[:, -1, 2:] = target[:, -1, 1:2]  # padded entries hold the last valid action
    torch.testing.assert_close(policy.loss(batch)["loss_octo_linear"], (pred - target) ** 2)


# -- Diffusion -------------------------------------------------------------------------------


@pytest.mark.parametrize("T", [5, 20])
def test_cosine_schedule_matches_the_hand_formula(T):
    torch.testing.assert_close(cosine_alpha_bar(T), torch.tensor(hand_alpha_bar(T), dtype=torch.float64))
    model = OctoDiffusion(OctoDiffusionConfig(**SMALL, train_steps=T, sample_steps=T), INFO)
    torch.testing.assert_close(model.alpha_bar, torch.tensor(hand_alpha_bar(T), dtype=torch.float32))


def test_forward_process_mixes_chunk_and_noise_by_alpha_bar(monkeypatch):
    torch.manual_seed(0)
    T = 20
    model = OctoDiffusion(OctoDiffusionConfig(**SMALL, train_steps=T), INFO)
    seen = {}
    c = 50.0  # a constant prediction: loss = (c - eps) ** 2, so eps = c - sqrt(loss)

    def fake_eps(noisy, t, features):
        seen["noisy"], seen["t"] = noisy.detach().clone(), t.clone()
        return torch.full_like(noisy, c)

    monkeypatch.setattr(model, "eps", fake_eps)
    batch = segment_batch(b=8, length=16)
    chunk = batch["action_chunk"]
    loss = model.step_loss(batch["observation_history"], batch["observation_history_valid"], batch["task_id"], chunk)
    eps = c - loss.sqrt()
    t = seen["t"]
    assert t.shape == (8, 16) and int(t.min()) >= 0 and int(t.max()) <= T - 1 and len(t.unique()) > 5
    ab = torch.tensor(hand_alpha_bar(T), dtype=torch.float32)[t][..., None, None]
    torch.testing.assert_close(seen["noisy"], ab.sqrt() * chunk + (1 - ab).sqrt() * eps, rtol=1e-4, atol=1e-4)
    assert abs(float(eps.mean())) < 0.1 and abs(float(eps.std()) - 1) < 0.1  # standard normal noise


@pytest.mark.parametrize(("T", "S"), [(20, 20), (20, 5), (20, 1), (50, 7)])
def test_ddim_with_the_true_noise_recovers_the_clean_chunk(T, S):
    g = torch.Generator().manual_seed(0)
    x0 = (torch.rand(16, H, A, generator=g, dtype=torch.float64) * 2 - 1) * 0.9
    eps = torch.randn(16, H, A, generator=g, dtype=torch.float64)
    ab = torch.tensor(hand_alpha_bar(T), dtype=torch.float64)
    steps = sampling_timesteps(T, S)
    assert steps[0] == T - 1 and len(steps) == S and (S == 1 or steps[-1] == 0)
    x_start = ab[T - 1].sqrt() * x0 + (1 - ab[T - 1]).sqrt() * eps
    out = ddim_sample(lambda x, t: eps, x_start, ab, steps, eta=0.0)
    torch.testing.assert_close(out, x0, rtol=0, atol=1e-9)


def test_ddpm_step_is_the_posterior_mean_plus_its_standard_deviation():
    T = 10
    ab = torch.tensor(hand_alpha_bar(T), dtype=torch.float64)
    g = torch.Generator().manual_seed(3)
    x = torch.randn(5, H, A, generator=g, dtype=torch.float64)
    eps = torch.randn(5, H, A, generator=g, dtype=torch.float64) * 0.5
    t = 6
    out = ddim_sample(
        lambda x_, t_: eps, x, ab, [t, t - 1], eta=1.0, generator=torch.Generator().manual_seed(9), clip=None
    )
    # by hand: DDPM's posterior (Ho et al. 2020, Eqs. 7 and 11) ...
    beta = 1 - ab[t] / ab[t - 1]
    mean = (x - beta / (1 - ab[t]).sqrt() * eps) / (1 - beta).sqrt()
    var = (1 - ab[t - 1]) / (1 - ab[t]) * beta
    z = torch.randn(1, H, A, generator=torch.Generator().manual_seed(9), dtype=torch.float64)  # shared by the rows
    x_prev = mean + var.sqrt() * z
    # ... then the last step (t - 1 -> 0 clean) returns its predicted clean chunk
    expected = (x_prev - (1 - ab[t - 1]).sqrt() * eps) / ab[t - 1].sqrt()
    torch.testing.assert_close(out, expected, rtol=1e-9, atol=1e-9)


# -- Flow matching ---------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["beta", "uniform"])
def test_flow_interpolation_and_velocity_target_by_hand(monkeypatch, kind):
    torch.manual_seed(0)
    model = FlowPolicy(FlowConfig(**SMALL, time_distribution=kind), INFO)
    seen = {}
    c = 50.0  # a constant prediction: loss = (c - u) ** 2, so the target u = c - sqrt(loss)

    def fake_velocity(x, tau, features):
        seen["x"], seen["tau"] = x.detach().clone(), tau.clone()
        return torch.full_like(x, c)

    monkeypatch.setattr(model, "velocity", fake_velocity)
    batch = segment_batch(b=16, length=16)
    chunk = batch["action_chunk"]
    loss = model.step_loss(batch["observation_history"], batch["observation_history_valid"], batch["task_id"], chunk)
    assert loss.shape == (16, 16, H, A)
    u = c - loss.sqrt()  # = noise - actions
    noise = u + chunk
    tau = seen["tau"].reshape(16, 16)[..., None, None]
    x_tau = seen["x"].reshape(16, 16, H, A)
    torch.testing.assert_close(x_tau, tau * noise + (1 - tau) * chunk, rtol=1e-4, atol=1e-4)
    assert abs(float(noise.mean())) < 0.1 and abs(float(noise.std()) - 1) < 0.1
    assert float(tau.min()) >= 0.001 and float(tau.max()) <= 1.0


def test_flow_time_distributions_by_hand():
    torch.manual_seed(0)
    n = 200_000
    beta = (sample_flow_time(n, "beta") - 0.001) / 0.999
    # Beta(1.5, 1): CDF x ** 1.5, mean 1.5 / 2.5
    assert float(beta.mean()) == pytest.approx(0.6, abs=0.005)
    for x in (0.1, 0.3, 0.5, 0.8):
        assert float((beta <= x).float().mean()) == pytest.approx(x**1.5, abs=0.005)
    uniform = (sample_flow_time(n, "uniform") - 0.001) / 0.999
    assert float(uniform.mean()) == pytest.approx(0.5, abs=0.005)
    with pytest.raises(ValueError, match=r"policy\.time_distribution"):
        sample_flow_time(3, "gamma")


def test_euler_integration_lands_where_hand_computation_says():
    x1 = torch.tensor([[0.5, -2.0]], dtype=torch.float64)
    c = torch.tensor([[0.3, 0.7]], dtype=torch.float64)
    # constant velocity: x_0 = x_1 - c whatever the number of steps
    for steps in (1, 4, 10):
        torch.testing.assert_close(euler_integrate(lambda x, tau: c.expand_as(x), x1, steps), x1 - c)
    # v = x: each step multiplies by (1 - 1 / S)
    torch.testing.assert_close(euler_integrate(lambda x, tau: x, x1, 5), x1 * (1 - 1 / 5) ** 5)
    # v = tau: taus 1, 1 - 1/S, ..., 1/S, so x_0 = x_1 - sum_i (1 - i / S) / S = x_1 - (S + 1) / (2 S)
    got = euler_integrate(lambda x, tau: tau[:, None].expand_as(x), x1, 4)
    torch.testing.assert_close(got, x1 - 5 / 8)


# -- Sampling at inference: seeded, picklable ------------------------------------------------


def _rollout(actor, steps: int = 3) -> torch.Tensor:
    g = torch.Generator().manual_seed(5)
    obs = torch.randn(steps, 4, D, generator=g)
    task = torch.tensor([0, 3, 3, 7])
    actions = []
    for i in range(steps):
        td = TensorDict({"observation": obs[i], "task_id": task, "is_init": torch.full((4, 1), i == 0)}, [4])
        actions.append(actor(td)["action"])
    return torch.stack(actions)


@pytest.mark.parametrize("name", ["octo_diffusion", "flow"])
@pytest.mark.parametrize("copier", ["pickle", "deepcopy", "state_dict"])
def test_sampling_is_deterministic_given_the_seed_and_a_copy_gives_the_same_actions(name, copier):
    torch.manual_seed(0)
    actor = build_policy(small(name), INFO).actor.eval()

    def clone(m):
        if copier == "pickle":
            return pickle.loads(pickle.dumps(m))
        if copier == "deepcopy":
            return copy.deepcopy(m)
        torch.manual_seed(1)
        other = build_policy(small(name), INFO).actor.eval()  # other weights, then the saved ones
        other.load_state_dict(m.state_dict())
        return other

    fresh = clone(actor)  # before any sampling
    first = _rollout(actor)
    assert torch.isfinite(first).all() and first.abs().max() <= 1
    assert torch.equal(_rollout(fresh), first)
    assert torch.equal(_rollout(clone(actor)), first)  # a copy made after sampling
    assert torch.equal(_rollout(actor), first)  # no sampling state: the same again
    torch.manual_seed(123)  # the global RNG plays no part at inference
    assert torch.equal(_rollout(clone(fresh)), first)
    torch.manual_seed(0)
    other = build_policy(small(name, seed=1), INFO).actor.eval()
    assert not torch.equal(_rollout(other), first)  # another seed, other noise (same weights)


@pytest.mark.parametrize("name", ["octo_diffusion", "flow"])
def test_a_rows_chunk_depends_on_its_own_inputs_only(name):
    """Not on its slot in the batch or the batch size (a sharded evaluation acts like one process)."""
    torch.manual_seed(0)
    model = build_policy(small(name), INFO).loss.model.eval()
    g = torch.Generator().manual_seed(2)
    history = torch.randn(6, K, D, generator=g)
    valid = torch.ones(6, K, dtype=torch.bool)
    valid[2, 0] = False
    task = torch.tensor([1, 2, 3, 4, 5, 6])
    batch = model.predict_chunk(history, valid, task)
    for i in (0, 2, 5):
        alone = model.predict_chunk(history[i : i + 1], valid[i : i + 1], task[i : i + 1])
        torch.testing.assert_close(alone[0], batch[i], rtol=1e-5, atol=1e-6)
    flipped = model.predict_chunk(history.flip(0), valid.flip(0), task.flip(0))
    torch.testing.assert_close(flipped.flip(0), batch, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("sampler", ["ddim", "ddpm"])
def test_diffusion_samplers_give_bounded_chunks(sampler):
    torch.manual_seed(0)
    model = OctoDiffusion(OctoDiffusionConfig(**SMALL, sampler=sampler, train_steps=8, sample_steps=4), INFO).eval()
    history = torch.randn(5, K, D)
    chunk = model.predict_chunk(history, torch.ones(5, K, dtype=torch.bool), torch.zeros(5, dtype=torch.long))
    assert chunk.shape == (5, H, A) and torch.isfinite(chunk).all() and chunk.abs().max() <= 1


# -- Settings --------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("name", "setting", "value", "named"),
    [
        ("octo_linear", "dim", 10, "policy.dim"),
        ("octo_linear", "layers", 0, "policy.layers"),
        ("octo_linear", "readouts", 0, "policy.readouts"),
        ("octo_linear", "dropout", 1.5, "policy.dropout"),
        ("octo_linear", "task_conditioning", "onehot", "policy.task_conditioning"),
        ("octo_linear", "execution", "replan", "policy.execution"),
        ("octo_linear", "execute_steps", 9, "policy.execute_steps"),
        ("octo_diffusion", "sampler", "euler", "policy.sampler"),
        ("octo_diffusion", "sample_steps", 21, "policy.sample_steps"),
        ("octo_diffusion", "train_steps", 0, "policy.train_steps"),
        ("flow", "sample_steps", 0, "policy.sample_steps"),
        ("flow", "time_distribution", "logit_normal", "policy.time_distribution"),
        ("flow", "expert_dim", 5, "policy.expert_dim"),
    ],
)
def test_bad_settings_are_refused_naming_the_setting(name, setting, value, named):
    cfg = POLICIES[name].config()
    if setting == "execute_steps":
        cfg.execution = "open_loop"
    setattr(cfg, setting, value)
    with pytest.raises(ValueError, match=named.replace(".", r"\.")):
        build_policy(cfg, INFO)


def test_a_history_or_chunk_of_another_size_is_refused():
    model = OctoLinear(OctoLinearConfig(**SMALL), INFO)
    with pytest.raises(ValueError, match=r"data\.history"):
        model.backbone(torch.randn(2, K + 1, D), torch.ones(2, K + 1, dtype=torch.bool), torch.zeros(2).long())
    batch = segment_batch()
    with pytest.raises(ValueError, match=r"data\.chunk_horizon"):
        model.step_loss(
            batch["observation_history"],
            batch["observation_history_valid"],
            batch["task_id"],
            batch["action_chunk"][..., :2, :],
        )


def test_instruction_conditioning_trains():
    torch.manual_seed(0)
    policy = build_policy(small("octo_linear", task_conditioning="instruction"), INFO)
    policy.loss(segment_batch())["loss_octo_linear"].mean().backward()
    assert all(p.grad is not None for p in policy.actor.parameters())


# -- Precision and distribution --------------------------------------------------------------


@pytest.mark.parametrize("name", HEADS)
def test_bf16_autocast_forward_and_backward_on_cpu(name):
    torch.manual_seed(0)
    policy = build_policy(small(name), INFO)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        loss = policy.loss(segment_batch())
    (key,) = [k for k in loss.keys() if k.startswith("loss_")]
    assert loss[key].dtype == torch.float32 and torch.isfinite(loss[key]).all()
    loss[key].mean().backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in policy.actor.parameters())


@pytest.mark.gpu
@pytest.mark.parametrize("name", HEADS)
def test_cuda_bf16_autocast_training_step_and_sampling(name):
    torch.manual_seed(0)
    policy = build_policy(small(name), INFO)
    objective = tar_loss(policy.loss, "tar").cuda()
    objective.set_keys(event_valid=policy.event_valid)
    with torch.autocast("cuda", dtype=torch.bfloat16):
        out = objective(segment_batch().cuda())
    out["loss_tar"].backward()
    assert torch.isfinite(out["loss_tar"])
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in policy.actor.parameters())
    actions = _rollout_cuda(policy.actor.eval())
    assert actions.device.type == "cuda" and torch.isfinite(actions).all() and actions.abs().max() <= 1
    cpu = copy.deepcopy(policy.actor).cpu()  # what the evaluator runs: a CPU copy
    assert _rollout(cpu).shape == actions.shape


def _rollout_cuda(actor) -> torch.Tensor:
    td = TensorDict(
        {
            "observation": torch.randn(4, D),
            "task_id": torch.tensor([0, 3, 3, 7]),
            "is_init": torch.ones(4, 1, dtype=torch.bool),
        },
        [4],
    ).cuda()
    return torch.stack([actor(td.clone())["action"] for _ in range(3)])


@pytest.mark.parametrize("name", HEADS)
def test_ddp_without_unused_parameters_trains_two_steps(tmp_path, name):
    """One rank, ``find_unused_parameters=False``: DDP raises on the 2nd step if a parameter got no gradient."""
    import torch.distributed as dist
    from torch.nn.parallel import DistributedDataParallel

    from tar_rl.distributed import close_group

    store = dist.FileStore(str(tmp_path / "store"), 1)
    dist.init_process_group("gloo", store=store, rank=0, world_size=1, timeout=timedelta(seconds=60))
    try:
        torch.manual_seed(0)
        policy = build_policy(small(name), INFO)
        objective = tar_loss(policy.loss, "tar")
        objective.set_keys(event_valid=policy.event_valid)
        model = DistributedDataParallel(objective, find_unused_parameters=False)
        optimizer = torch.optim.AdamW(objective.parameters(), lr=1e-3)
        batch = segment_batch()
        for _ in range(3):
            loss = model(batch)["loss_tar"]
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
        assert torch.isfinite(loss)
        del model
        close_group()
    finally:
        if dist.is_initialized():
            dist.destroy_process_group()


# -- Through the recipe ----------------------------------------------------------------------


@pytest.fixture(scope="module")
def data_root(tmp_path_factory):
    return tmp_path_factory.mktemp("datasets")


@pytest.mark.parametrize("name", HEADS)
def test_a_tiny_training_job_runs_each_head(tmp_path, data_root, name):
    from hydra import compose, initialize

    from tar_rl.recipes import resolve_config, train
    from tar_rl.recipes.config import register_configs
    from tar_rl.runs import load_checkpoint

    overrides = [
        f"policy={name}",
        "data.tasks=[reach]",
        "data.n_demos=2",
        "data.workers=1",
        f"data.root={data_root}",
        "data.batch_segments=4",
        "data.slice_len=8",
        "data.chunk_horizon=4",
        *(f"policy.{k}={v}" for k, v in SMALL.items()),
        "optim.steps=20",
        "optim.warmup=2",
        "logging.every=10",
        "logging.checkpoint_every=20",
        "logging.progress=false",
        "logging.record_weights_at=[-1]",
        "eval.rollouts=1",
        "eval.horizon=10",
        "eval.workers=1",
        f"runs_root={tmp_path / 'runs'}",
    ]
    register_configs()
    with initialize(version_base="1.3", config_path=None):
        config = resolve_config(compose(config_name="train", overrides=overrides))
    run_dir = train(config)
    assert run_dir.name.startswith(f"tar-{name}-s0-")
    state = load_checkpoint(run_dir)
    assert state["step"] == 20 and state["finished"]
    assert all(torch.isfinite(v).all() for v in state["policy"].values() if v.is_floating_point())
    rollouts = pd.read_csv(run_dir / "eval_rollouts.csv")  # the final evaluation ran the ChunkedActor
    assert len(rollouts) == 1 and rollouts.steps.iloc[0] >= 1
