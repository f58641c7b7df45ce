"""The vision-language-action policies in process. pi0_tar and pi05_tar forward and backward at a tiny size: LeRobot
builds pi0 and pi0.5 only at their full size (PaliGemma 2B and a 300M expert, hard-coded), so the test shrinks the
Gemma variants and the SigLIP vision tower it reads. SmolVLA runs on the tiny local SmolVLM of ``conftest``. The TAR
loss is the base policy's own before TAR's start and one loss per item after it."""

from __future__ import annotations

import pytest
import torch
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.policies.pi0 import modeling_pi0
from lerobot.policies.pi0.modeling_pi0 import PI0Policy
from lerobot.policies.pi05 import modeling_pi05
from lerobot.policies.pi05.modeling_pi05 import PI05Policy
from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy
from lerobot.utils.constants import OBS_LANGUAGE_ATTENTION_MASK, OBS_LANGUAGE_TOKENS
from lerobot_policy_tar.modeling_tar import PI0TARPolicy, PI05TARPolicy, SmolVLATARPolicy

from lerobot_policy_tar import PI0TARConfig, PI05TARConfig, SmolVLATARConfig, TARSettings

WIDTH, IMAGE, CHUNK, STATE_DIM, ACTION_DIM, TOKENS = 32, 32, 4, 5, 3, 6


def tiny_vision(build):
    """pi0's PaliGemma builder with a one-layer SigLIP tower (the sizes it assigns are replaced before it builds)."""

    def tiny(config):
        vision = config.vision_config
        vision.hidden_size, vision.intermediate_size, vision.num_hidden_layers = 16, 32, 1
        vision.num_attention_heads, vision.patch_size = 2, 8
        vision.projection_dim = config.text_config.hidden_size
        return build(config=config)

    return tiny


@pytest.fixture
def tiny_pi(monkeypatch):
    """Both modules' Gemma variants at ``WIDTH`` wide and one layer deep, and a one-layer SigLIP tower."""
    for module in (modeling_pi0, modeling_pi05):
        tiny = module.GemmaConfig(
            width=WIDTH, depth=1, mlp_dim=64, num_heads=8, num_kv_heads=1, head_dim=4
        )  # 8: hard-coded
        monkeypatch.setattr(module, "get_gemma_config", lambda variant, tiny=tiny: tiny)
        build = module.PaliGemmaForConditionalGenerationWithPiGemma
        monkeypatch.setattr(module, "PaliGemmaForConditionalGenerationWithPiGemma", tiny_vision(build))


def pi_config(config_class, **tar):
    size = {"image_resolution": (IMAGE, IMAGE)} if config_class is not SmolVLATARConfig else {}
    return config_class(
        device="cpu", chunk_size=CHUNK, n_action_steps=CHUNK, max_state_dim=8, max_action_dim=8,
        tokenizer_max_length=TOKENS, tar=TARSettings(**tar), **size,
        input_features={
            "observation.state": PolicyFeature(type=FeatureType.STATE, shape=(STATE_DIM,)),
            "observation.images.cam": PolicyFeature(type=FeatureType.VISUAL, shape=(3, IMAGE, IMAGE)),
        },
        output_features={"action": PolicyFeature(type=FeatureType.ACTION, shape=(ACTION_DIM,))},
    )  # fmt: skip


def pi_batch(config, size: int, seed: int = 0, vocab: int = 1000, pad_from: int | None = None) -> dict:
    """A preprocessed batch: tokens as the tokenizer would leave them, images in [0, 1], normalised state/action."""
    generator = torch.Generator().manual_seed(seed)
    obs, act = config.observation_delta_indices, config.action_delta_indices
    frames = () if obs is None else (len(obs),)
    batch = {
        "observation.state": torch.randn(size, *frames, STATE_DIM, generator=generator),
        "observation.images.cam": torch.rand(size, *frames, 3, IMAGE, IMAGE, generator=generator),
        OBS_LANGUAGE_TOKENS: torch.randint(0, vocab, (size, TOKENS), generator=generator),
        OBS_LANGUAGE_ATTENTION_MASK: torch.ones(size, TOKENS, dtype=torch.bool),
        "action": torch.randn(size, len(act), ACTION_DIM, generator=generator),
        "action_is_pad": torch.zeros(size, len(act), dtype=torch.bool),
    }
    if pad_from is not None:
        batch["action_is_pad"][:, pad_from:] = True
    return batch


@pytest.mark.parametrize(
    "config_class, tar_class, base_class, time_axis",
    [
        (PI0TARConfig, PI0TARPolicy, PI0Policy, "chunk"),
        (PI0TARConfig, PI0TARPolicy, PI0Policy, "segment"),
        (PI05TARConfig, PI05TARPolicy, PI05Policy, "chunk"),
    ],
    ids=["pi0-chunk", "pi0-segment", "pi05-chunk"],
)
def test_pi_policies_forward_and_backward_at_a_tiny_size(tiny_pi, config_class, tar_class, base_class, time_axis):
    config = pi_config(config_class, time_axis=time_axis, slice_len=2, start=1)
    torch.manual_seed(0)
    policy = tar_class(config)
    assert (
        sum(p.numel() for p in policy.parameters()) < 30_000_000
    )  # 2B at full size; the 257,152-token vocabulary is most of it
    batch = pi_batch(config, 2)
    if time_axis == "chunk":  # before start: the base policy's own per-sample loss, with the same random draws
        base = base_class(config)
        base.load_state_dict({k: v for k, v in policy.state_dict().items() if k != "tar_step"})
        torch.manual_seed(1)
        ours, _ = policy.forward(batch, reduction="none")
        torch.manual_seed(1)
        theirs, _ = base.forward(batch, reduction="none")
        torch.testing.assert_close(ours, theirs)
    policy.forward(batch)  # the schedule's first step
    loss, info = policy.forward(batch, reduction="none")
    assert loss.shape == (2,) and info["tar_mix"] == 1.0
    loss.mean().backward()
    grads = [p.grad for p in policy.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(g).all() for g in grads)
    assert any(g.abs().sum() > 0 for g in grads)


def test_smolvla_tar_is_smolvlas_masked_loss_before_tar_starts_and_trains_after(smolvlm):
    """SmolVLA masks padded chunk entries itself: its per-sample loss with padding equals the plugin's before start."""
    config = pi_config(SmolVLATARConfig, time_axis="chunk", start=1)
    config.vlm_model_name, config.load_vlm_weights, config.num_vlm_layers = str(smolvlm), False, 2
    config.resize_imgs_with_padding = (IMAGE, IMAGE)
    torch.manual_seed(0)
    policy = SmolVLATARPolicy(config)
    base = SmolVLAPolicy(config)
    base.load_state_dict({k: v for k, v in policy.state_dict().items() if k != "tar_step"})
    batch = pi_batch(config, 2, vocab=9, pad_from=2)
    torch.manual_seed(1)
    ours, _ = policy.forward(batch, reduction="none")
    torch.manual_seed(1)
    theirs, _ = base.forward(dict(batch), reduction="none")
    torch.testing.assert_close(ours, theirs)
    loss, info = policy.forward(batch)
    assert info["tar_mix"] == 1.0
    loss.backward()
    assert all(torch.isfinite(p.grad).all() for p in policy.parameters() if p.grad is not None)


@pytest.mark.parametrize("kind", ["pi0", "pi05", "smolvla"])
def test_the_action_error_signal_is_the_error_of_the_chunk_the_velocity_implies(tiny_pi, smolvlm, kind):
    """On the draw LeRobot's model sees (its noisy chunk ``x_t``, its time ``t``, its velocity ``v``): the implied
    chunk is ``x_t - t * v`` (openpi's ``x_t = t * noise + (1 - t) * A``), its squared error the signal, and the time's
    quantile ``((t - 0.001) / 0.999) ** 1.5`` (Beta(1.5, 1)); TAR then trains on it."""
    config_class, policy_class = {
        "pi0": (PI0TARConfig, PI0TARPolicy),
        "pi05": (PI05TARConfig, PI05TARPolicy),
        "smolvla": (SmolVLATARConfig, SmolVLATARPolicy),
    }[kind]
    config = pi_config(config_class, time_axis="chunk", signal="action_error")
    if kind == "smolvla":
        config.vlm_model_name, config.load_vlm_weights, config.num_vlm_layers = str(smolvlm), False, 2
        config.resize_imgs_with_padding = (IMAGE, IMAGE)
    torch.manual_seed(0)
    policy = policy_class(config)
    model, seen = policy.model, {}
    embed_suffix, sample_time = model.embed_suffix, model.sample_time
    model.embed_suffix = lambda *args: (seen.update(x_t=args[-2].detach()), embed_suffix(*args))[1]
    model.sample_time = lambda *args: seen.setdefault("t", sample_time(*args))
    model.action_out_proj.register_forward_hook(lambda module, args, out: seen.update(v=out.detach()))
    batch = pi_batch(config, 3, vocab=9 if kind == "smolvla" else 1000, pad_from=3)
    element = policy.element_losses(batch)
    t = seen["t"][:, None, None]
    implied = seen["x_t"] - t * seen["v"]
    actions = policy.prepare_action(batch)
    expected = (implied - actions).square()[:, :, :ACTION_DIM]
    torch.testing.assert_close(element.action_error, expected, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(element.quantile, ((seen["t"] - 0.001) / 0.999).clamp(0, 1) ** 1.5)
    loss, info = policy.forward(batch)
    assert info["tar_mix"] == 1.0 and torch.isfinite(loss)
    loss.backward()
