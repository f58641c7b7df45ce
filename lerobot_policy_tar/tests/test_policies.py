"""The TAR policies in process: their config (tar-rl's names and defaults, the errors), the loss against the base
policy's own, the segment's steps against the base policy run on each step, the schedule's step count."""

from __future__ import annotations

import inspect
import math

import pytest
import torch
from conftest import ACTION_DIM, ENV_DIM, EPISODE_LENGTHS, IMAGE_SIZE, STATE_DIM
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.policies.act.modeling_act import ACTPolicy
from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy
from lerobot_policy_tar.configuration_tar import PI0_FAST_REFUSAL, PI05TARConfig
from lerobot_policy_tar.modeling_tar import ACTTARPolicy, DiffusionTARPolicy
from lerobot_policy_tar.tar_source import MixSchedule, tar_weights

from lerobot_policy_tar import BASES, ACTTARConfig, DiffusionTARConfig, TARSettings, tar_config_class

FEATURES = {
    "observation.state": PolicyFeature(type=FeatureType.STATE, shape=(STATE_DIM,)),
    "observation.environment_state": PolicyFeature(type=FeatureType.ENV, shape=(ENV_DIM,)),
}
ACTION = {"action": PolicyFeature(type=FeatureType.ACTION, shape=(ACTION_DIM,))}
CHUNK = 4


def act_config(**tar) -> ACTTARConfig:
    return ACTTARConfig(
        device="cpu", input_features=dict(FEATURES), output_features=dict(ACTION), chunk_size=CHUNK,
        n_action_steps=CHUNK, dim_model=32, dim_feedforward=64, n_heads=2, n_encoder_layers=1, n_decoder_layers=1,
        latent_dim=8, pretrained_backbone_weights=None, tar=TARSettings(**tar),
    )  # fmt: skip


def act_image_config(**tar) -> ACTTARConfig:
    """ACT reading a camera and the state (its ResNet-18 backbone, untrained, on 32-pixel images)."""
    config = act_config(**tar)
    config.input_features = {
        "observation.state": FEATURES["observation.state"],
        "observation.images.cam": PolicyFeature(type=FeatureType.VISUAL, shape=(3, IMAGE_SIZE, IMAGE_SIZE)),
    }
    return config


def diffusion_config(**tar) -> DiffusionTARConfig:
    return DiffusionTARConfig(
        device="cpu", input_features=dict(FEATURES), output_features=dict(ACTION), n_obs_steps=2, horizon=8,
        n_action_steps=4, down_dims=(16, 32), diffusion_step_embed_dim=16, kernel_size=3, n_groups=4,
        num_train_timesteps=10, do_mask_loss_for_padding=True, tar=TARSettings(**tar),
    )  # fmt: skip


def _batch(config, size: int, seed: int = 0, pad_from: int | None = None) -> dict[str, torch.Tensor]:
    """A normalised batch of the config's delta indices: random features, ``action_is_pad`` from ``pad_from``."""
    generator = torch.Generator().manual_seed(seed)
    obs, act = config.observation_delta_indices, config.action_delta_indices
    frames = () if obs is None else (len(obs),)
    features = config.input_features
    batch = {key: torch.randn(size, *frames, *ft.shape, generator=generator) for key, ft in features.items()}
    batch["action"] = torch.randn(size, len(act), ACTION_DIM, generator=generator)
    batch["action_is_pad"] = torch.zeros(size, len(act), dtype=torch.bool)
    if pad_from is not None:
        batch["action_is_pad"][:, pad_from:] = True
    for key in features:
        if obs is not None:
            batch[f"{key}_is_pad"] = torch.zeros(size, len(obs), dtype=torch.bool)
    return batch


# -- Config ---------------------------------------------------------------------------------------


def test_tar_settings_have_the_names_and_defaults_of_tar_rls_objective():
    defaults = inspect.signature(tar_weights).parameters
    schedule = MixSchedule()
    settings = TARSettings()
    for name in ("gamma", "w_max", "eps", "cap"):
        assert getattr(settings, name) == defaults[name].default, name
    for name in ("start", "ramp", "shape"):
        assert getattr(settings, name) == getattr(schedule, name), name
    assert (settings.time_axis, settings.slice_len) == ("segment", 16)  # tar-rl's data.slice_len default
    assert sorted(BASES) == ["act", "diffusion", "pi0", "pi05", "smolvla"]
    for base, config_class in BASES.items():
        assert config_class(device="cpu").type == f"{base}_tar"


@pytest.mark.parametrize(
    "field, value, message",
    [
        ("gamma", 0.0, "policy.tar: gamma must be a finite number > 0"),
        ("gamma", math.inf, "policy.tar: gamma must be a finite number > 0"),
        ("w_max", "3", "policy.tar: w_max must be a number >= 1"),
        ("eps", 0.0, "policy.tar: eps must be a finite number > 0"),
        ("cap", "soft", "policy.tar: cap must be one of"),
        ("w_max", 0.5, "policy.tar: w_max >= 1 is needed .*cap='paper' renormalises them above it"),
        ("start", -1, "policy.tar: schedule start must be an int >= 0"),
        ("ramp", 2.5, "policy.tar: schedule ramp must be an int >= 0"),
        ("shape", "step", "policy.tar: schedule shape must be one of"),
        ("time_axis", "episode", "policy.tar.time_axis must be one of"),
        ("slice_len", 0, "policy.tar.slice_len must be an int >= 1"),
    ],
)
def test_tar_fields_out_of_range_are_refused_with_their_name(field, value, message):
    with pytest.raises(ValueError, match=message):
        TARSettings(**{field: value}).validate()
    config = act_config(**{field: value})  # the command line's parser builds it; the dataset and the policy refuse it
    for read in (
        lambda: config.action_delta_indices,
        lambda: config.observation_delta_indices,
        config.validate_features,
    ):
        with pytest.raises(ValueError, match=message):
            read()


@pytest.mark.parametrize("cap", ["paper", "exact"])
@pytest.mark.parametrize("w_max", [0.5, 0.999, 1.0, 3.0, math.inf])
def test_w_max_follows_tar_rls_one_rule_with_either_cap(w_max, cap):
    """The plugin refuses what tar-rl's ``TARParams`` refuses, with its message: ``w_max`` below 1, either cap."""
    from tar_rl.objectives.tar import TARParams

    try:
        TARParams(w_max=w_max, cap=cap)
    except ValueError as error:
        assert w_max < 1
        with pytest.raises(ValueError) as ours:
            TARSettings(w_max=w_max, cap=cap).validate()
        assert str(ours.value) == f"policy.tar: {error}"
    else:
        assert w_max >= 1
        TARSettings(w_max=w_max, cap=cap).validate()


def test_unknown_base_policies_and_pi0_fast_are_refused_with_the_reason():
    with pytest.raises(ValueError, match=r"unknown base policy 'vqbet' for TAR; supported: \['act', 'diffusion'"):
        tar_config_class("vqbet")
    with pytest.raises(ValueError, match="pi0_fast is not supported by TAR: its loss is a cross-entropy over FAST"):
        tar_config_class("pi0_fast")
    from lerobot.configs.policies import PreTrainedConfig

    fast = PreTrainedConfig.get_choice_class("pi0_fast_tar")(device="cpu")
    for read in (lambda: fast.action_delta_indices, lambda: fast.observation_delta_indices, fast.validate_features):
        with pytest.raises(ValueError, match="pi0_fast is not supported by TAR"):
            read()
    assert PI0_FAST_REFUSAL.startswith("pi0_fast is not supported")
    with pytest.raises(ValueError, match=r"pi05_tar supports policy\.tar\.time_axis=chunk only"):
        PI05TARConfig(device="cpu", tar=TARSettings(time_axis="segment")).check_tar()
    assert PI05TARConfig(device="cpu").tar.time_axis == "chunk"


def test_segment_mode_extends_the_base_delta_indices_by_the_segment():
    act = act_config(slice_len=3)
    assert act.observation_delta_indices == [0, 1, 2]
    assert act_config(slice_len=1).observation_delta_indices == [0]  # a time axis even for one step
    assert act.action_delta_indices == list(range(CHUNK + 2))
    assert act_config(time_axis="chunk").observation_delta_indices is None
    diffusion = diffusion_config(slice_len=3)  # n_obs_steps 2, horizon 8: deltas -1..0 and -1..6
    assert diffusion.observation_delta_indices == [-1, 0, 1, 2]
    assert diffusion.action_delta_indices == list(range(-1, 9))


def test_a_segment_longer_than_every_episode_is_refused_before_training(state_dataset):
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata
    from lerobot.policies.factory import make_policy

    meta = LeRobotDatasetMetadata("local/tar_tiny", root=state_dataset)
    longest = max(EPISODE_LENGTHS)
    assert max(meta.episodes["length"]) == longest
    assert make_policy(act_config(slice_len=longest), ds_meta=meta).config.tar.slice_len == longest
    with pytest.raises(ValueError, match=f"policy.tar.slice_len={longest + 1} is longer than every episode"):
        make_policy(act_config(slice_len=longest + 1), ds_meta=meta)


# -- The loss against the base policy's own ----------------------------------------------------------


@pytest.mark.parametrize(
    "make_config, tar_class, base_class",
    [
        (act_config, ACTTARPolicy, ACTPolicy),
        (act_image_config, ACTTARPolicy, ACTPolicy),
        (diffusion_config, DiffusionTARPolicy, DiffusionPolicy),
    ],
    ids=["act", "act-image", "diffusion"],
)
def test_with_the_schedule_off_the_loss_is_the_base_policys_own(make_config, tar_class, base_class):
    """Before ``start`` TAR's weights are uniform: the loss of one chunk (padding included) is the base policy's
    masked mean, drawn with the same random numbers."""
    config = make_config(time_axis="chunk", start=10)
    torch.manual_seed(0)
    policy = tar_class(config)
    base = base_class(config)
    base.load_state_dict({k: v for k, v in policy.state_dict().items() if k != "tar_step"})
    for pad_from in (None, 3):
        batch = _batch(config, 1, pad_from=pad_from)
        torch.manual_seed(1)
        ours, info = policy.forward(batch)
        torch.manual_seed(1)
        theirs, _ = base.forward(batch)
        torch.testing.assert_close(ours, theirs)
        assert info["tar_mix"] == 0.0


@pytest.mark.parametrize("slice_len", [1, 3])
def test_each_step_of_a_segment_is_the_base_policys_loss_on_that_step(slice_len):
    """ACT without its VAE and dropout is deterministic: step ``t``'s loss in a segment is ACT's own loss on the
    item of observation ``t`` and chunk ``t..t+H-1``, built here directly from the segment's tensors."""
    config = act_config(slice_len=slice_len, start=10)
    config.use_vae, config.dropout = False, 0.0
    torch.manual_seed(0)
    policy = ACTTARPolicy(config)
    base = ACTPolicy(config)
    base.load_state_dict({k: v for k, v in policy.state_dict().items() if k != "tar_step"})
    batch = _batch(config, 2, pad_from=5)  # L=3: steps 0..2 read actions t..t+3 of 6; step 2's last one is padding
    ours, _ = policy.forward(batch, reduction="none")
    for i in range(2):
        steps = []
        for t in range(slice_len):
            item = {key: batch[key][i : i + 1, t] for key in FEATURES}
            item["action"] = batch["action"][i : i + 1, t : t + CHUNK]
            item["action_is_pad"] = batch["action_is_pad"][i : i + 1, t : t + CHUNK]
            steps.append(base.forward(item)[0])
        torch.testing.assert_close(ours[i], torch.stack(steps).mean())  # uniform before start


def test_reduction_none_returns_one_loss_per_item_that_lerobots_sample_weights_multiply():
    config = act_config(slice_len=3)
    torch.manual_seed(0)
    policy = ACTTARPolicy(config)
    batch = _batch(config, 4)
    torch.manual_seed(1)
    per_item, _ = policy.forward(batch, reduction="none")
    torch.manual_seed(1)
    mean, _ = policy.forward(batch)
    assert per_item.shape == (4,)
    torch.testing.assert_close(per_item.mean(), mean)
    sample_weights = torch.tensor([1.0, 0.0, 2.0, 1.0])  # LeRobot's update_policy: sum(l * w) / sum(w)
    weighted = (per_item * sample_weights).sum() / sample_weights.sum()
    weighted.backward()
    assert all(p.grad is None or torch.isfinite(p.grad).all() for p in policy.parameters())
    with pytest.raises(ValueError, match="reduction must be one of"):
        policy.forward(batch, reduction="sum")


def test_the_schedule_counts_training_forwards_and_ramps_tar_in():
    config = act_config(slice_len=3, start=1, ramp=2)
    policy = ACTTARPolicy(config)
    batch = _batch(config, 2)
    policy.eval()
    assert policy.forward(batch)[1]["tar_mix"] == 0.0
    assert int(policy.tar_step) == 0  # evaluation does not advance the schedule
    policy.train()
    mixes = [policy.forward(batch)[1]["tar_mix"] for _ in range(4)]
    assert mixes == [0.0, 0.0, 0.5, 1.0]
    assert int(policy.tar_step) == 4
    assert "tar_step" in policy.state_dict()


# -- The log: comparable with the base policy's ----------------------------------------------------


def _folded_by_hand(batch, size: int, slice_len: int) -> dict[str, torch.Tensor]:
    """ACT's batch of single steps from a segment batch, item-major and step-minor (``n = i * L + t``), built here
    with loops: observation ``t``, actions ``t .. t + CHUNK - 1``."""
    steps = [(i, t) for i in range(size) for t in range(slice_len)]
    folded = {key: torch.stack([batch[key][i, t] for i, t in steps]) for key in FEATURES}
    for key in ("action", "action_is_pad"):
        folded[key] = torch.stack([batch[key][i, t : t + CHUNK] for i, t in steps])
    return folded


@pytest.mark.parametrize("start", [10, 0], ids=["tar-off", "tar-on"])
def test_the_logged_uniform_loss_and_acts_terms_are_acts_own(start):
    """On the same observation-chunk pairs and random draws, ``tar_uniform_loss`` is ACT's ``loss`` and ``l1_loss``,
    ``kld_loss`` are ACT's own terms, whether TAR weighs the loss or not; with TAR on the optimised loss differs."""
    slice_len, size = 3, 2
    config = act_config(slice_len=slice_len, start=start)
    torch.manual_seed(0)
    policy = ACTTARPolicy(config)
    base = ACTPolicy(config)
    base.load_state_dict({k: v for k, v in policy.state_dict().items() if k != "tar_step"})
    for pad_from in (None, 5):  # 5: step 2's last chunk entry is padding (its current action is real)
        batch = _batch(config, size, seed=3, pad_from=pad_from)
        torch.manual_seed(1)
        loss, info = policy.forward(batch)
        torch.manual_seed(1)
        theirs, terms = base.forward(_folded_by_hand(batch, size, slice_len))
        assert info["l1_loss"] == pytest.approx(terms["l1_loss"], rel=1e-6)
        assert info["kld_loss"] == pytest.approx(terms["kld_loss"], rel=1e-6)
        if pad_from is None:  # with padding the plugin averages per step first (docs/lerobot.md)
            assert info["tar_uniform_loss"] == pytest.approx(theirs.item(), rel=1e-6)
            if start == 0:
                assert abs(loss.item() - theirs.item()) > 1e-4  # the weighted loss is another number
            else:
                assert loss.item() == pytest.approx(theirs.item(), rel=1e-6)


def test_in_evaluation_mode_the_loss_is_the_base_policys_uniform_one():
    """LeRobot's ``eval_loss`` calls the forward in evaluation mode: the uniform loss, ACT's own, with TAR on."""
    config = act_config(slice_len=3, start=0)
    torch.manual_seed(0)
    policy = ACTTARPolicy(config).eval()
    base = ACTPolicy(config).eval()
    base.load_state_dict({k: v for k, v in policy.state_dict().items() if k != "tar_step"})
    batch = _batch(config, 2, seed=4)
    loss, info = policy.forward(batch)
    theirs, _ = base.forward(_folded_by_hand(batch, 2, 3))
    assert info["tar_mix"] == 1.0 and info["tar_max_weight"] > 1.0
    assert loss.item() == pytest.approx(theirs.item(), rel=1e-6)
    assert loss.item() == pytest.approx(info["tar_uniform_loss"], rel=1e-6)


def test_ess_and_the_largest_weight_are_one_before_tar_starts_and_not_after():
    config = act_config(slice_len=3, start=1)
    policy = ACTTARPolicy(config)
    batch = _batch(config, 4, seed=5)
    before = policy.forward(batch)[1]
    after = policy.forward(batch)[1]
    assert (before["tar_mix"], before["tar_ess"], before["tar_max_weight"]) == (0.0, 1.0, 1.0)
    assert after["tar_mix"] == 1.0 and after["tar_ess"] < 1.0 and after["tar_max_weight"] > 1.0


@pytest.mark.parametrize("time_axis, frames_per_item", [("segment", 3), ("chunk", 1)])
def test_tar_epochs_count_frames_as_the_base_policy_does(state_dataset, time_axis, frames_per_item):
    """LeRobot's epochs are steps x batch size / frames; an item of a segment holds slice_len frames."""
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

    meta = LeRobotDatasetMetadata("local/tar_tiny", root=state_dataset)
    frames = sum(EPISODE_LENGTHS)
    assert meta.total_frames == frames
    config = act_config(slice_len=3, time_axis=time_axis)
    policy = ACTTARPolicy(config, dataset_meta=meta)
    batch = _batch(config, 2)
    epochs = [policy.forward(batch)[1]["tar_epochs"] for _ in range(2)]
    assert epochs == pytest.approx([2 * frames_per_item / frames, 2 * 2 * frames_per_item / frames])
    assert "tar_epochs" not in ACTTARPolicy(config).forward(batch)[1]  # no dataset: at inference
