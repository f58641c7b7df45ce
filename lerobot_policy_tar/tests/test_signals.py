"""What TAR ranks the steps by (``policy.tar.signal``): the loss by default, bit-identical to the loss's weights;
for a sampled loss (diffusion, SmolVLA, pi0, pi0.5) the error of the action chunk the prediction implies at the same
draw, against hand formulas on the draw; the loss over a running mean at its draw; a signal a policy does not
offer refused before training; a non-finite signal refused as a non-finite loss is, naming the step."""

from __future__ import annotations

import pytest
import torch
from lerobot.policies.common.flow_matching import sample_time_beta
from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy
from lerobot_policy_tar.configuration_tar import SAMPLED_SIGNALS, PI05TARConfig
from lerobot_policy_tar.modeling_tar import (
    DiffusionTARPolicy,
    flow_action_error,
    flow_quantile,
)
from lerobot_policy_tar.tar_source import TimeNormalizer, tar_weights
from lerobot_policy_tar.time_axis import ElementLosses, reduce_over_time
from test_policies import _batch, act_config, diffusion_config

from lerobot_policy_tar import PI0TARConfig, SmolVLATARConfig, TARSettings

TAR = {"gamma": 1.0, "w_max": 3.0, "eps": 1e-8, "cap": "paper", "mix": 1.0}


def _segment_losses(seed: int = 0):
    """Element losses of B=2 segments of L=3 steps (H=4 entries, A=2 dims) with an action error beside them."""
    generator = torch.Generator().manual_seed(seed)
    loss = torch.rand(6, 4, 2, generator=generator, dtype=torch.float64)
    error = torch.rand(6, 4, 2, generator=generator, dtype=torch.float64)
    entry_valid = torch.ones(6, 4, dtype=torch.bool)
    entry_valid[2, 3] = False  # step 2's last chunk entry is padding
    segments = torch.tensor([[True, True, True], [True, True, False]])
    return loss, error, entry_valid, segments


# -- The config ----------------------------------------------------------------------------------


def test_the_default_signal_is_the_loss_and_the_sampled_policies_offer_two_more():
    assert TARSettings().signal == "loss"
    assert act_config().tar_signals == ("loss",)
    for config_class in (PI0TARConfig, PI05TARConfig, SmolVLATARConfig):
        assert config_class(device="cpu").tar_signals == SAMPLED_SIGNALS
    assert diffusion_config().tar_signals == SAMPLED_SIGNALS == ("loss", "action_error", "time_normalized")


@pytest.mark.parametrize(
    "config, message",
    [
        (lambda: act_config(signal="action_error"), "policy.tar.signal='action_error' is not offered by act_tar: it "
         "offers ['loss']."),
        (lambda: diffusion_config(signal="x0"), "policy.tar.signal='x0' is not offered by diffusion_tar: it offers "
         "['loss', 'action_error', 'time_normalized']."),
    ],
    ids=["act", "diffusion"],
)  # fmt: skip
def test_a_signal_the_policy_does_not_offer_is_refused_naming_the_policy_and_its_signals(config, message):
    config = config()  # the command line's parser builds it; the dataset and the policy refuse it
    for read in (lambda: config.action_delta_indices, config.validate_features):
        with pytest.raises(ValueError) as error:
            read()
        assert str(error.value) == message


def test_time_normalized_needs_pis_beta_time_of_beta_one():
    config = PI0TARConfig(device="cpu", tar=TARSettings(signal="time_normalized"))
    config.check_tar()
    config.time_sampling_beta_beta = 2.0
    with pytest.raises(ValueError, match=r"it needs policy\.time_sampling_beta_beta=1 \(the default\), got 2\.0"):
        config.check_tar()
    PI0TARConfig(device="cpu", tar=TARSettings(signal="action_error"), time_sampling_beta_beta=2.0).check_tar()


# -- The reduction: what the weights rank -----------------------------------------------------------


@pytest.mark.parametrize("segmented", [True, False], ids=["segment", "chunk"])
def test_the_loss_signal_leaves_the_weights_those_of_the_loss(segmented):
    loss, error, entry_valid, segments = _segment_losses()
    segments = segments if segmented else None
    element = ElementLosses(loss, entry_valid, action_error=error, quantile=torch.rand(6, dtype=torch.float64))
    plain = reduce_over_time(ElementLosses(loss, entry_valid), segments=segments, **TAR)
    out = reduce_over_time(element, segments=segments, signal="loss", **TAR)
    for name in ("per_item", "uniform", "losses", "valid", "weights"):
        assert torch.equal(getattr(out, name), getattr(plain, name)), name
    assert torch.equal(out.weights, tar_weights(out.losses, out.valid, **TAR))


def test_action_error_ranks_the_steps_by_their_mean_error_and_weights_the_loss():
    loss, error, entry_valid, segments = _segment_losses()
    element = ElementLosses(loss, entry_valid, action_error=error)
    out = reduce_over_time(element, segments=segments, signal="action_error", **TAR)
    ranked = reduce_over_time(ElementLosses(error, entry_valid), segments=segments, **TAR)
    assert torch.equal(out.losses, reduce_over_time(ElementLosses(loss, entry_valid), segments=segments, **TAR).losses)
    by_hand = torch.tensor([error[n][entry_valid[n]].mean().item() for n in range(6)], dtype=torch.float64)
    torch.testing.assert_close(ranked.losses, by_hand.reshape(2, 3))
    torch.testing.assert_close(out.weights, tar_weights(by_hand.reshape(2, 3), segments, **TAR))
    per_item = (out.weights * out.losses).sum(-1) / segments.sum(-1)
    torch.testing.assert_close(out.per_item, per_item)
    assert not torch.allclose(out.weights, tar_weights(out.losses, segments, **TAR))


def test_time_normalized_divides_each_step_by_its_bins_running_mean():
    """Two bins, decay 0.5: steps 1, 2 in bin 0 and 3, 4 in bin 1 give means 1.5 and 3.5 (bias-corrected)."""
    loss = torch.tensor([1.0, 2.0, 3.0, 4.0], dtype=torch.float64)[:, None, None]
    element = ElementLosses(loss, torch.ones(4, 1, dtype=torch.bool), quantile=torch.tensor([0.1, 0.4, 0.6, 0.9]))
    segments = torch.ones(1, 4, dtype=torch.bool)
    normalizer = TimeNormalizer(bins=2, decay=0.5)
    kw = {"segments": segments, "signal": "time_normalized", "normalizer": normalizer, **TAR}
    evaluated = reduce_over_time(element, update=False, **kw)
    assert torch.equal(normalizer.weight, torch.zeros(2, dtype=torch.float64))  # evaluation keeps nothing
    out = reduce_over_time(element, update=True, **kw)
    scores = torch.tensor([[1 / 1.5, 2 / 1.5, 3 / 3.5, 4 / 3.5]], dtype=torch.float64)
    torch.testing.assert_close(out.weights, tar_weights(scores, segments, **TAR))
    torch.testing.assert_close(evaluated.weights, out.weights)
    torch.testing.assert_close(normalizer.total, torch.tensor([0.75, 1.75], dtype=torch.float64))
    torch.testing.assert_close(normalizer.weight, torch.tensor([0.5, 0.5], dtype=torch.float64))


@pytest.mark.parametrize("signal", ["action_error", "time_normalized"])
def test_a_non_finite_signal_at_a_valid_step_is_refused_as_a_non_finite_loss_naming_the_step(signal):
    loss, error, entry_valid, segments = _segment_losses()
    quantile = torch.linspace(0.05, 0.95, 6, dtype=torch.float64)
    kw = {"segments": segments, "signal": signal, "normalizer": TimeNormalizer(), "update": True, **TAR}
    if signal == "action_error":
        error[4, 1, 0] = float("nan")  # item 4: segment 1, step 1
    else:
        loss[4, 1, 0] = float("inf")  # the normalised loss is inf
    with pytest.raises(ValueError) as raised:
        reduce_over_time(ElementLosses(loss, entry_valid, action_error=error, quantile=quantile), **kw)
    what = f"ranking signal '{signal}'" if signal == "action_error" else "loss"
    assert str(raised.value).startswith(f"non-finite per-step {what} at a valid step: the weights would be NaN.")
    assert "(first at index (1, 1)" in str(raised.value)
    with pytest.raises(ValueError, match=r"non-finite per-step loss at a valid step.*\(first at index \(1, 1\)"):
        reduce_over_time(ElementLosses(loss.where(error == error, torch.nan), entry_valid), segments=segments, **TAR)
    error[5], loss[5] = float("nan"), float("nan")  # segment 1's step 2 is padding: never counts
    error[4, 1, 0], loss[4, 1, 0] = 0.5, 0.5
    reduce_over_time(ElementLosses(loss, entry_valid, action_error=error, quantile=quantile), **kw)


# -- Flow matching (pi0, pi0.5, SmolVLA): openpi's time convention -----------------------------------


def test_flow_action_error_is_the_error_of_the_chunk_the_velocity_implies():
    """``x_t = t * noise + (1 - t) * A``, ``u = noise - A`` (LeRobot's pi0, pi0.5, SmolVLA): a velocity ``v`` implies
    ``A_hat = x_t - t * v``; its squared error is the signal, by hand here."""
    generator = torch.Generator().manual_seed(0)
    actions, noise, v = (torch.randn(3, 4, 2, generator=generator, dtype=torch.float64) for _ in range(3))
    time = torch.tensor([0.001, 0.5, 1.0], dtype=torch.float64)
    t = time[:, None, None]
    x_t = t * noise + (1 - t) * actions
    loss = (v - (noise - actions)).square()
    implied = x_t - t * v
    torch.testing.assert_close(flow_action_error(loss, time), (implied - actions).square())
    assert torch.equal(flow_action_error(loss, time)[2], loss[2])  # t = 1: pure noise, the velocity's own error


def test_in_chunk_mode_a_flow_signal_scales_a_chunk_by_one_factor_and_leaves_the_losss_weights():
    """A chunk's entries share their draw: ``t ** 2`` (or one bin's mean) rescales them all, and the z-scores do not
    move (up to ``eps`` over the scaled standard deviation: 1e-8 / 7e-4 at ``t = 0.05``); docs/lerobot.md says so."""
    generator = torch.Generator().manual_seed(2)
    loss = torch.rand(3, 5, 2, generator=generator, dtype=torch.float64)
    time = torch.tensor([0.05, 0.5, 0.95], dtype=torch.float64)
    valid = torch.ones(3, 5, dtype=torch.bool)
    element = ElementLosses(loss, valid, action_error=flow_action_error(loss, time), quantile=time)
    plain = reduce_over_time(element, segments=None, **TAR)
    for signal in ("action_error", "time_normalized"):
        out = reduce_over_time(element, segments=None, signal=signal, normalizer=TimeNormalizer(), **TAR)
        torch.testing.assert_close(out.weights, plain.weights, rtol=1e-4, atol=1e-4)


def test_flow_quantile_is_the_beta_draws_cdf():
    assert flow_quantile(torch.tensor([0.5005]), 1.5, 0.999, 0.001).item() == pytest.approx(0.5**1.5)
    assert flow_quantile(torch.tensor([0.0, 1.0]), 1.5, 0.999, 0.001).tolist() == [0.0, 1.0]
    torch.manual_seed(0)
    draws = sample_time_beta(20_000, "cpu", alpha=1.5, beta=1.0, scale=0.999, offset=0.001)  # LeRobot's sampler
    quantile = flow_quantile(draws, 1.5, 0.999, 0.001)
    for q in (0.1, 0.25, 0.5, 0.9):  # uniform: the bins of tar-rl's normaliser are equally likely
        assert (quantile < q).double().mean().item() == pytest.approx(q, abs=0.015)


# -- Diffusion -----------------------------------------------------------------------------------


def _recorded_draw(policy: DiffusionTARPolicy) -> dict:
    """Records the denoiser's input ``x_t``, timesteps and prediction at the policy's next forward."""
    seen = {}

    def hook(module, args, output):
        seen["x_t"], seen["t"], seen["pred"] = args[0].detach(), args[1].detach(), output.detach()

    policy.diffusion.unet.register_forward_hook(hook)
    return seen


@pytest.mark.parametrize("prediction_type", ["epsilon", "sample"])
@pytest.mark.parametrize("clip", [True, False], ids=["clipped", "unclipped"])
def test_diffusions_action_error_is_the_clean_chunk_its_prediction_implies(prediction_type, clip):
    """From the draw the denoiser saw, by DDPM's own formula: ``x0_hat = (x_t - sqrt(1 - a) * eps_hat) / sqrt(a)``
    (``epsilon``) or the prediction (``sample``), clipped as the sampler clips it; unclipped, ``epsilon``'s error is
    ``(1 - a) / a`` times the loss."""
    config = diffusion_config(time_axis="chunk")
    config.prediction_type, config.clip_sample, config.clip_sample_range = prediction_type, clip, 0.5
    torch.manual_seed(0)
    policy = DiffusionTARPolicy(config)
    seen = _recorded_draw(policy)
    batch = _batch(config, 8)
    torch.manual_seed(1)
    element = policy.element_losses(batch)
    a = policy.diffusion.noise_scheduler.alphas_cumprod[seen["t"]][:, None, None]
    actions = batch["action"]
    if prediction_type == "epsilon":
        x0 = (seen["x_t"] - (1 - a).sqrt() * seen["pred"]) / a.sqrt()
    else:
        x0 = seen["pred"]
    x0 = x0.clamp(-0.5, 0.5) if clip else x0
    torch.testing.assert_close(element.action_error, (x0 - actions).square(), rtol=1e-4, atol=1e-4)
    if not clip:
        ratio = (1 - a) / a if prediction_type == "epsilon" else torch.ones_like(a)
        torch.testing.assert_close(element.action_error, ratio * element.loss.detach())
    steps = config.num_train_timesteps
    torch.testing.assert_close(element.quantile, (seen["t"].float() + 0.5) / steps)


def test_diffusion_with_either_signal_trains_on_the_same_draw_and_loss():
    """Same seed, same draw: the signal changes the weights, never the loss they weight or the uniform loss."""
    outs = {}
    for signal in ("loss", "action_error", "time_normalized"):
        config = diffusion_config(slice_len=3, signal=signal)
        torch.manual_seed(0)
        policy = DiffusionTARPolicy(config)
        batch = _batch(config, 4, pad_from=9)
        torch.manual_seed(1)
        outs[signal] = policy.forward(batch)[1]
    assert outs["loss"]["tar_uniform_loss"] == outs["action_error"]["tar_uniform_loss"]
    assert outs["loss"]["tar_uniform_loss"] == outs["time_normalized"]["tar_uniform_loss"]
    assert outs["loss"]["tar_max_weight"] != outs["action_error"]["tar_max_weight"]


def test_time_normalizeds_running_means_are_saved_and_a_base_checkpoint_loads_without_them():
    config = diffusion_config(slice_len=3, signal="time_normalized")
    torch.manual_seed(0)
    policy = DiffusionTARPolicy(config)
    policy.forward(_batch(config, 4))
    state = policy.state_dict()
    assert state["tar_normalizer.weight"].sum() > 0
    resumed = DiffusionTARPolicy(config)
    resumed.load_state_dict(state)
    assert torch.equal(resumed.tar_normalizer.total, policy.tar_normalizer.total)
    base = DiffusionPolicy(diffusion_config()).state_dict()
    fresh = DiffusionTARPolicy(config)
    fresh.load_state_dict(base)  # strict: TAR's count and running means start empty
    assert fresh.tar_normalizer.weight.sum() == 0 and int(fresh.tar_step) == 0
    assert not any(key.startswith("tar_normalizer") for key in DiffusionTARPolicy(diffusion_config()).state_dict())


def test_to_base_drops_the_running_means_and_to_tar_starts_them_empty(tmp_path):
    from lerobot_policy_tar.checkpoints import to_base, to_tar

    config = diffusion_config(slice_len=3, signal="time_normalized")
    torch.manual_seed(0)
    policy = DiffusionTARPolicy(config)
    policy.forward(_batch(config, 4))
    policy.save_pretrained(tmp_path / "tar")
    base = DiffusionPolicy.from_pretrained(to_base(tmp_path / "tar", tmp_path / "base"))
    assert not any(key.startswith("tar_") for key in base.state_dict())
    back = to_tar(tmp_path / "base", tmp_path / "again", TARSettings(slice_len=3, signal="time_normalized"))
    again = DiffusionTARPolicy.from_pretrained(back)
    assert again.tar_normalizer.weight.sum() == 0 and int(again.tar_step) == 0
