"""The ``act`` head: chunk L1 loss with padding, the KL term, inference at the prior mean, the recipe.

Expected values are computed by hand: the network's output layers are set to constants (zero
weights, chosen biases), so the predicted chunk and the posterior's mean and log-variance are
known numbers whatever the transformer layers compute.
"""

from __future__ import annotations

import json
import math
import pickle

import pandas as pd
import pytest
import torch
from objective_helpers import tar_loss
from recipe_helpers import tiny
from tensordict import TensorDict

from tar_rl.policies import POLICIES, ACTConfig, DataInfo, build_policy
from tar_rl.recipes import policy_from_checkpoint, train
from tar_rl.runs import load_checkpoint

INFO = DataInfo(obs_dim=3, action_dim=2, n_tasks=2, chunk_horizon=3, instructions=("Reach the goal.", "Push the puck."))
TINY = {"name": "act", "dim": 8, "heads": 2, "ffn_dim": 16, "latent_dim": 2, "dropout": 0.0}


def tiny_policy(**overrides):
    torch.manual_seed(0)
    return build_policy({**TINY, **overrides}, INFO)


def fix_outputs(policy, chunk_bias, mu, logvar):
    """Make the predicted chunk entries all ``chunk_bias`` and the posterior ``(mu, logvar)``, constant."""
    model = policy.actor.model
    with torch.no_grad():
        model.head.weight.zero_()
        model.head.bias.copy_(torch.tensor(chunk_bias))
        model.cvae_out.weight.zero_()
        model.cvae_out.bias.copy_(torch.tensor([*mu, *logvar]))


def batch_1x2():
    """One segment of two steps; the second step's chunk runs past the episode end at entry 2."""
    chunk = torch.tensor(
        [
            [[1.0, 0.0], [0.0, 0.0], [0.5, -0.25]],
            [[-1.0, 1.0], [0.5, 0.75], [9.0, 9.0]],  # the last entry is padding: ignored
        ]
    )[None]
    chunk_valid = torch.tensor([[True, True, True], [True, True, False]])[None]
    return TensorDict(
        {
            "observation": torch.tensor([[[0.1, 0.2, 0.3], [0.4, 0.5, 0.6]]]),
            "task_id": torch.tensor([[0, 1]]),
            "action_chunk": chunk,
            "action_chunk_valid": chunk_valid,
            ("collector", "mask"): torch.ones(1, 2, dtype=torch.bool),
        },
        [1, 2],
    )


def objective(policy, weighting="uniform"):
    loss = tar_loss(policy.loss, weighting, loss_key=policy.loss_key)
    loss.set_keys(event_valid=policy.event_valid)
    return loss


def kl_by_hand(mu, logvar):
    """KL(N(mu, sigma^2) || N(0, 1)) = log(1 / sigma) + (sigma^2 + mu^2) / 2 - 1/2, summed over dims."""
    total = 0.0
    for m, lv in zip(mu, logvar, strict=True):
        sigma = math.exp(lv / 2)
        total += math.log(1 / sigma) + (sigma**2 + m**2) / 2 - 0.5
    return total


# -- The loss -----------------------------------------------------------------------------------


def test_registered_with_the_per_step_loss_and_chunk_mask():
    assert "act" in POLICIES and POLICIES["act"].config is ACTConfig
    policy = tiny_policy()
    assert policy.loss_key == "loss_chunk" and policy.event_valid == "action_chunk_valid"
    assert {"observation", "task_id", "action_chunk", "action_chunk_valid"} <= set(policy.keys)
    # the perturbation controls corrupt the target the head learns from: the chunk
    assert tar_loss(policy.loss, "perturb_high", loss_key="loss_chunk").tensor_keys.action == "action_chunk"


def test_l1_per_step_loss_is_the_valid_horizon_average():
    policy = tiny_policy()
    fix_outputs(policy, [0.5, -0.25], mu=[0.0, 0.0], logvar=[0.0, 0.0])  # KL exactly 0
    out = policy.loss(batch_1x2())
    assert out["loss_chunk"].shape == (1, 2, 3, 2)
    # step 0: |0.5-1|, |-0.25-0|, 0.5, 0.25, 0, 0 -> 1.5 / 6; step 1: 1.5, 1.25, 0, 1.0 (3rd entry padding) -> 3.75 / 4
    expected_elements = torch.tensor([[[0.5, 0.25], [0.5, 0.25], [0.0, 0.0]], [[1.5, 1.25], [0.0, 1.0], [0.0, 0.0]]])[
        None
    ]
    torch.testing.assert_close(out["loss_chunk"], expected_elements)
    loss = objective(policy)
    torch.testing.assert_close(loss.step_losses(batch_1x2()), torch.tensor([[0.25, 0.9375]]))
    result = loss(batch_1x2())
    torch.testing.assert_close(result["loss_tar"], torch.tensor((0.25 + 0.9375) / 2))
    assert float(result["aux_loss_kl"]) == 0.0


def test_kl_term_matches_the_closed_form_and_is_added_once():
    mu, logvar = [0.5, -1.0], [0.0, math.log(2.0)]
    policy = tiny_policy(kl_weight=10.0)
    fix_outputs(policy, [0.5, -0.25], mu=mu, logvar=logvar)
    out = policy.loss(batch_1x2())
    kl = kl_by_hand(mu, logvar)  # 0.5 * (0.25 + 2 - ln 2)
    assert out["loss_kl"].shape == () and out["loss_kl"].requires_grad
    torch.testing.assert_close(out["loss_kl"], torch.tensor(10.0 * kl))
    torch.testing.assert_close(out["kl"], torch.tensor(kl))
    assert not out["kl"].requires_grad
    result = objective(policy)(batch_1x2())
    torch.testing.assert_close(result["aux_loss_kl"], torch.tensor(10.0 * kl))
    # the chunk loss of the previous test plus the KL term, once
    torch.testing.assert_close(result["loss_tar"], torch.tensor((0.25 + 0.9375) / 2 + 10.0 * kl))


def test_kl_is_averaged_over_valid_steps_only():
    policy = tiny_policy(kl_weight=1.0)
    policy.loss.eval()  # the posterior is deterministic; only z's sample is random, and the KL does not read it
    torch.manual_seed(1)
    data = TensorDict(
        {
            "observation": torch.randn(2, 3, 3),
            "task_id": torch.tensor([[0, 0, 0], [1, 1, 1]]),
            "action_chunk": torch.rand(2, 3, 3, 2) * 2 - 1,
            "action_chunk_valid": torch.ones(2, 3, 3, dtype=torch.bool),
            ("collector", "mask"): torch.tensor([[True, True, True], [True, False, False]]),
        },
        [2, 3],
    )
    data["observation"][1, 1:] = 50.0  # padding far from the data: a very different posterior
    with torch.no_grad():
        masked = policy.loss(data)["loss_kl"]
        valid = data[data["collector", "mask"]]  # the 4 real steps as a flat batch, all valid
        valid_only = policy.loss(valid.exclude(("collector", "mask")))["loss_kl"]
        everything = policy.loss(data.exclude(("collector", "mask")))["loss_kl"]
    torch.testing.assert_close(masked, valid_only)
    assert not torch.isclose(masked, everything)


def test_padded_chunk_entries_do_not_reach_the_posterior():
    policy = tiny_policy()
    policy.loss.eval()
    data = batch_1x2()
    changed = data.clone()
    changed["action_chunk"][0, 1, 2] = torch.tensor([-7.0, 3.0])  # a padded entry
    moved = data.clone()
    moved["action_chunk"][0, 1, 1] = torch.tensor([-7.0, 3.0])  # a real entry
    with torch.no_grad():
        kl = [policy.loss(d)["kl"] for d in (data, changed, moved)]
    torch.testing.assert_close(kl[0], kl[1])
    assert not torch.isclose(kl[0], kl[2])


def test_latent_is_sampled_in_training_and_the_posterior_mean_in_eval():
    policy = tiny_policy()
    with torch.no_grad():  # a posterior with unit variance: samples move the prediction
        policy.actor.model.cvae_out.bias[2:] = 0.0
    data = batch_1x2()
    with torch.no_grad():
        first, second = policy.loss(data)["loss_chunk"], policy.loss(data)["loss_chunk"]
        assert not torch.equal(first, second)
        policy.loss.eval()
        state = torch.get_rng_state()
        first, second = policy.loss(data)["loss_chunk"], policy.loss(data)["loss_chunk"]
        assert torch.equal(first, second)
        assert torch.equal(torch.get_rng_state(), state)  # no random numbers drawn


def test_loss_never_mutates_its_input():
    policy = tiny_policy()
    data = batch_1x2()
    before = data.clone()
    objective(policy, "perturb_high")(data)["loss_tar"].backward()
    policy.loss(data)
    assert set(data.keys(True, True)) == set(before.keys(True, True))
    for key in before.keys(True, True):
        torch.testing.assert_close(data[key], before[key], rtol=0, atol=0)


def test_every_parameter_gets_a_gradient_in_one_training_step():
    """DDP with find_unused_parameters=False needs every parameter in each training forward."""
    policy = tiny_policy(task_conditioning="instruction", enc_layers=2, dec_layers=2, cvae_layers=2)
    objective(policy, "tar")(batch_1x2())["loss_tar"].backward()
    missing = [n for n, p in policy.actor.named_parameters() if p.grad is None or not p.grad.abs().sum() > 0]
    assert not missing
    loss_params = {id(p) for p in policy.loss.parameters()}
    assert loss_params == {id(p) for p in policy.actor.parameters()}  # one set of weights, shared


def test_bf16_autocast_keeps_float32_losses():
    policy = tiny_policy()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = objective(policy, "tar")(batch_1x2())
    assert out["loss_tar"].dtype == torch.float32 and torch.isfinite(out["loss_tar"])
    out["loss_tar"].backward()


# -- Inference ----------------------------------------------------------------------------------


def inference_batch():
    return TensorDict(
        {
            "observation": torch.tensor([[0.1, 0.2, 0.3], [0.4, 0.5, 0.6]]),
            "task_id": torch.tensor([0, 1]),
            "is_init": torch.ones(2, 1, dtype=torch.bool),
        },
        [2],
    )


def test_inference_uses_the_prior_mean():
    policy = tiny_policy()
    model = policy.actor.model
    # a posterior with mean 0 and (numerically) no variance: the training pass then decodes z = 0
    with torch.no_grad():
        model.cvae_out.weight.zero_()
        model.cvae_out.bias.copy_(torch.tensor([0.0, 0.0, -200.0, -200.0]))
    data = batch_1x2()
    obs = data["observation"][0]
    with torch.no_grad():
        trained_path, mu, _ = model(obs, data["task_id"][0], data["action_chunk"][0], data["action_chunk_valid"][0])
        inferred = model.predict_chunk(obs[:, None], torch.ones(2, 1, dtype=torch.bool), data["task_id"][0])
    assert (mu == 0).all()
    torch.testing.assert_close(inferred, trained_path)
    # the first action of a fresh rollout is the chunk's first entry (ensemble of one), clipped
    actor = policy.actor.eval()
    first = actor(TensorDict({**inference_batch().to_dict()}, [2]))["action"]
    torch.testing.assert_close(first, inferred[:, 0].clamp(-1, 1))


def test_inference_is_deterministic_and_picklable():
    policy = tiny_policy(dropout=0.1)
    actor = policy.actor.eval()
    a = actor(inference_batch())["action"]
    b = actor(inference_batch())["action"]
    assert a.shape == (2, 2) and torch.equal(a, b)
    assert (a.abs() <= 1).all()
    copy = pickle.loads(pickle.dumps(actor))
    assert torch.equal(copy(inference_batch())["action"], a)


@pytest.mark.parametrize(
    ("setting", "value"),
    [
        ("dim", 30),  # not divisible by heads=4
        ("heads", 0),
        ("enc_layers", 0),
        ("dec_layers", -1),
        ("cvae_layers", 0),
        ("latent_dim", 0),
        ("ffn_dim", 0),
        ("kl_weight", -1.0),
        ("dropout", 1.0),
        ("execution", "replay"),
        ("task_conditioning", "onehot"),
    ],
)
def test_bad_settings_name_the_setting(setting, value):
    cfg = {"name": "act", "dim": 32, "heads": 4, setting: value}
    with pytest.raises(ValueError, match=f"policy.{setting}"):
        build_policy(cfg, INFO)


# -- Through the recipe -------------------------------------------------------------------------


@pytest.mark.slow
def test_smoke_job_through_the_recipe(tmp_path, data_root):
    config = tiny(
        tmp_path,
        data_root,
        "policy=act",
        "policy.dim=16",
        "policy.ffn_dim=32",
        "data.chunk_horizon=4",
        "optim.steps=20",
        "logging.record_weights_at=[-1]",
        "eval.horizon=15",
    )
    run_dir = train(config)
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["finished"] and summary["steps"] == 20 and run_dir.name.startswith("tar-act-")
    assert math.isfinite(summary["final_train_loss"])
    assert len(pd.read_csv(run_dir / "weights.csv")) > 0  # the recording reads the head's per-step loss
    metrics = pd.read_csv(run_dir / "metrics.csv")
    kl = metrics[(metrics.phase == "train") & (metrics.name == "aux_loss_kl")]
    assert len(kl) == 4 and (kl.value >= 0).all()  # the KL term is logged every logging.every=5 steps
    state = load_checkpoint(run_dir)
    actor = policy_from_checkpoint(state)
    assert actor.horizon == 4
    obs = TensorDict(
        {
            "observation": torch.zeros(1, 39),
            "task_id": torch.zeros(1, dtype=torch.long),
            "is_init": torch.ones(1, 1, dtype=torch.bool),
        },
        [1],
    )
    action = actor(obs)["action"]
    assert action.shape == (1, 4) and torch.isfinite(action).all()
