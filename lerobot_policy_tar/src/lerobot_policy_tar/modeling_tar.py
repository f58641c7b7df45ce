"""The policies: each LeRobot policy whose training forward reduces over time with TAR.

A TAR policy is its base policy (same network, processors, inference and checkpoints) with one training forward,
:meth:`TARPolicyMixin.forward`, shared by all five. What differs per base policy is only where its per-element loss
comes from, :meth:`element_losses`: the base's own loss up to the point where it reduces (LeRobot's
``policy.forward`` returns a scalar).

Diffusion, SmolVLA, pi0 and pi0.5 compute their loss at one random draw of a time (noise level) and a noise; their
element losses also carry, from the same draw, the error of the action chunk the prediction implies
(:func:`flow_action_error`, :func:`diffusion_action_error`) and the draw's quantile, which ``policy.tar.signal``
may rank the steps by instead of the loss (``action_error``, ``time_normalized``; the loss weighted is the
policy's own either way).

The forward's log (LeRobot prints every number of it at ``--log_freq``) holds the TAR-weighted loss and, for
comparison with the base policy's run, the uniform loss of the same batch, the base policy's own sub-losses (ACT's
``l1_loss`` and ``kld_loss``), the weights' ESS and largest value, and the epochs in the base policy's count of
frames. In evaluation mode (LeRobot's ``eval_loss``) the forward returns the uniform loss, the base policy's own.
"""

from __future__ import annotations

from typing import Any

import torch
import torch.nn.functional as F
from lerobot.policies.act.modeling_act import ACTPolicy
from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy
from lerobot.policies.pi0.modeling_pi0 import PI0Policy
from lerobot.policies.pi05.modeling_pi05 import PI05Policy
from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy
from lerobot.utils.constants import ACTION, OBS_IMAGES, OBS_LANGUAGE_ATTENTION_MASK, OBS_LANGUAGE_TOKENS, OBS_STATE
from torch import Tensor

from .configuration_tar import ACTTARConfig, DiffusionTARConfig, PI0TARConfig, PI05TARConfig, SmolVLATARConfig
from .tar_source import TimeNormalizer
from .time_axis import ElementLosses, effective_sample_size, fold_segments, reduce_over_time

__all__ = [
    "ACTTARPolicy",
    "DiffusionTARPolicy",
    "PI0TARPolicy",
    "PI05TARPolicy",
    "SmolVLATARPolicy",
    "TARPolicyMixin",
    "diffusion_action_error",
    "flow_action_error",
    "flow_quantile",
]

REDUCTIONS = ("mean", "none")


def check_segment_fits(config, dataset_meta) -> None:
    """Refuse a segment longer than every episode of the dataset (every segment would be padded)."""
    if config.tar.time_axis != "segment" or dataset_meta is None or dataset_meta.episodes is None:
        return
    longest = max(dataset_meta.episodes["length"])
    if config.tar.slice_len > longest:
        raise ValueError(
            f"policy.tar.slice_len={config.tar.slice_len} is longer than every episode of the dataset (the longest "
            f"has {longest} frames): set it to at most {longest}."
        )


def _entry_valid(batch: dict[str, Any], loss: Tensor) -> Tensor:
    """``[N, H]`` bool, ``True`` on the real chunk entries (``~action_is_pad``; all real without it)."""
    is_pad = batch.get("action_is_pad")
    return torch.ones(loss.shape[:2], dtype=torch.bool, device=loss.device) if is_pad is None else ~is_pad


def _fill_missing_tar_state(module, state_dict, prefix, *args) -> None:
    """A state dict without ``tar_step`` (a base policy's checkpoint: post-training starts from one) loads with the
    schedule at step 0 instead of LeRobot's warning about a missing key; without ``tar_normalizer``'s running
    means, with them empty."""
    state_dict.setdefault(prefix + "tar_step", torch.zeros((), dtype=torch.long))
    normalizer = getattr(module, "tar_normalizer", None)
    if normalizer is not None:
        for name, value in normalizer.state_dict().items():
            state_dict.setdefault(f"{prefix}tar_normalizer.{name}", torch.zeros_like(value))


def flow_action_error(loss: Tensor, time: Tensor) -> Tensor:
    """``[N, H, A]``: the squared error of the chunk a flow-matching velocity implies, from its velocity loss
    ``loss`` ``[N, H, A]`` at the times ``time`` ``[N]``, detached.

    LeRobot's pi0, pi0.5 and SmolVLA follow openpi: ``x_t = t * noise + (1 - t) * A`` (``t = 1`` is noise) and the
    target velocity is ``u = noise - A``, so ``A = x_t - t * u``; the velocity ``v`` implies ``A_hat = x_t - t * v``
    and ``A_hat - A = t * (u - v)``: per element ``(A_hat - A) ** 2 = t ** 2 * (v - u) ** 2``.
    """
    return time.detach()[:, None, None].square() * loss.detach()


def flow_quantile(time: Tensor, alpha: float, scale: float, offset: float) -> Tensor:
    """``[N]``: the quantile of each time ``t = scale * b + offset`` with ``b ~ Beta(alpha, 1)`` (openpi's draw),
    ``((t - offset) / scale) ** alpha`` (the Beta's CDF), clamped to ``[0, 1]``."""
    return ((time.detach() - offset) / scale).clamp(0.0, 1.0).pow(alpha)


def diffusion_action_error(
    pred: Tensor,
    eps: Tensor,
    trajectory: Tensor,
    alpha_bar: Tensor,
    prediction_type: str,
    clip_range: float | None,
) -> Tensor:
    """``[N, H, A]``: the squared error of the clean chunk ``x0_hat`` a denoiser's prediction implies, detached.

    ``trajectory`` ``[N, H, A]`` is the clean chunk, noised as ``x_t = sqrt(a) * x0 + sqrt(1 - a) * eps`` with ``a``
    the cumulative ``alpha_bar`` ``[N]`` of each item's timestep (DDPM and DDIM alike). An ``epsilon`` prediction
    ``pred`` implies ``x0_hat = (x_t - sqrt(1 - a) * pred) / sqrt(a) = x0 - sqrt((1 - a) / a) * (pred - eps)``, so
    unclipped the error is ``(1 - a) / a`` times the noise loss; a ``sample`` prediction is ``x0_hat`` itself. With
    ``clip_range`` (the scheduler's ``clip_sample``), ``x0_hat`` is clipped to ``[-clip_range, clip_range]`` first,
    as the sampler's step clips it: at the noisiest timesteps ``(1 - a) / a`` reaches about ``4e6`` (LeRobot's
    default 100-step cosine schedule) and the unclipped error is mostly the noise loss magnified.
    """
    pred, eps, trajectory = pred.detach(), eps.detach(), trajectory.detach()
    if prediction_type == "epsilon":
        a = alpha_bar.detach().to(pred.dtype)[:, None, None]
        x0 = trajectory - ((1 - a) / a).sqrt() * (pred - eps)
    else:
        x0 = pred
    if clip_range is not None:
        x0 = x0.clamp(-clip_range, clip_range)
    return (x0 - trajectory).square()


def _world_size() -> int:
    distributed = torch.distributed.is_available() and torch.distributed.is_initialized()
    return torch.distributed.get_world_size() if distributed else 1


def _flow_losses(loss: Tensor, valid: Tensor, time: Tensor, alpha: float, scale: float, offset: float):
    """A flow-matching policy's element losses at the times ``time`` ``[N]`` drawn as ``Beta(alpha, 1) * scale +
    offset``, with their action errors and the times' quantiles."""
    quantile = flow_quantile(time, alpha, scale, offset)
    return ElementLosses(loss, valid, action_error=flow_action_error(loss, time), quantile=quantile)


def _pi_time_draw(config) -> tuple[float, float, float]:
    """pi0's and pi0.5's time draw as (alpha, scale, offset); its Beta's ``beta`` is 1 where a signal reads the
    quantile (``time_normalized``, checked by the config)."""
    return config.time_sampling_beta_alpha, config.time_sampling_scale, config.time_sampling_offset


class TARPolicyMixin:
    """The training forward of every TAR policy (the first base of each; the second is the LeRobot policy).

    The policy counts its training forwards in the buffer ``tar_step`` (saved with the weights, so a resumed run
    continues TAR's schedule; a checkpoint without it, a base policy's, starts it at 0) and reads ``policy.tar``
    (:class:`~lerobot_policy_tar.configuration_tar.TARSettings`). With ``policy.tar.signal=time_normalized`` its
    running means per time bin are the submodule ``tar_normalizer``, saved and resumed the same way.
    """

    #: The base policy's name for the mean of its element losses over the real entries (ACT: ``l1_loss``), logged.
    element_loss_name: str | None = None

    def __init__(self, config, **kwargs):
        dataset_meta = kwargs.get("dataset_meta")
        check_segment_fits(config, dataset_meta)
        super().__init__(config, **kwargs)
        self.register_buffer("tar_step", torch.zeros((), dtype=torch.long))
        if config.tar.signal == "time_normalized":
            #: The running mean of the loss per time bin (tar-rl's): saved with the weights, as ``tar_step`` is.
            self.tar_normalizer = TimeNormalizer()
        self.register_load_state_dict_pre_hook(_fill_missing_tar_state)
        #: The dataset's frames, for ``tar_epochs`` (unknown without the dataset: at inference).
        self.tar_dataset_frames = None if dataset_meta is None else int(dataset_meta.total_frames)

    def element_losses(self, batch: dict[str, Any]) -> ElementLosses:
        """The base policy's per-element training loss on a batch of its own shapes."""
        raise NotImplementedError

    def forward(self, batch: dict[str, Any], reduction: str = "mean") -> tuple[Tensor, dict[str, float]]:
        """The loss: the mean over items (``reduction="mean"``) or one per item, ``[B]`` (``"none"``); TAR-weighted
        in training mode, uniform (the base policy's reduction) in evaluation mode."""
        if reduction not in REDUCTIONS:
            raise ValueError(f"reduction must be one of {REDUCTIONS}, got {reduction!r}.")
        tar, config = self.config.tar, self.config
        items = batch["action"].shape[0]
        segments = None
        if tar.time_axis == "segment":
            base_obs = config.base_observation_delta_indices
            base_action = config.base_action_delta_indices
            batch, segments = fold_segments(
                batch,
                slice_len=tar.slice_len,
                observation_keys=list(config.input_features),
                observation_window=None if base_obs is None else len(base_obs),
                action_window=len(base_action),
                action_offset=-min(base_action),
            )
        mix = tar.schedule(self.tar_step)
        element = self.element_losses(batch)
        out = reduce_over_time(
            element,
            segments=segments,
            gamma=tar.gamma,
            w_max=tar.w_max,
            eps=tar.eps,
            cap=tar.cap,
            mix=mix,
            signal=tar.signal,
            normalizer=getattr(self, "tar_normalizer", None),
            update=self.training,
        )
        if self.training:
            self.tar_step += 1
        per_item = out.per_item if self.training else out.uniform
        loss = per_item if reduction == "none" else per_item.mean()
        info = {
            "loss": per_item.mean().item(),
            "tar_uniform_loss": out.uniform.mean().item(),
            **self._base_terms(element, out.valid.reshape(-1) if segments is not None else out.valid.any(-1)),
            "tar_mix": float(mix),
            "tar_max_weight": out.weights.max().item(),
            "tar_ess": effective_sample_size(out.weights, out.valid).item(),
        }
        if self.tar_dataset_frames:
            # LeRobot counts epochs as steps x batch size / frames; an item of a segment holds slice_len frames.
            frames = items * (tar.slice_len if segments is not None else 1) * _world_size()
            info["tar_epochs"] = int(self.tar_step) * frames / self.tar_dataset_frames
        return loss, info

    def _base_terms(self, element: ElementLosses, real: Tensor) -> dict[str, float]:
        """The base policy's own logged terms, unweighted, over the ``real`` ``[N]`` items of its own batch (a
        segment's steps inside the episode): the mean of the element losses over their real entries
        (``element_loss_name``) and the mean of each of ``element.terms``."""
        terms = {}
        if self.element_loss_name is not None:
            entries = element.valid & real[:, None]
            count = entries.sum() * element.loss.shape[-1]
            total = torch.where(entries[..., None], element.loss, torch.zeros((), dtype=element.loss.dtype)).sum()
            terms[self.element_loss_name] = (total / count.clamp_min(1)).item()
        for name, value in element.terms.items():
            terms[name] = (value * real).sum().item() / max(int(real.sum()), 1)
        return terms


class ACTTARPolicy(TARPolicyMixin, ACTPolicy):
    """ACT with TAR: the L1 loss per chunk entry and action dim; the VAE's KL term (times ``kl_weight``) per item.
    Logs ACT's own ``l1_loss`` and ``kld_loss`` (the KL before ``kl_weight``), unweighted."""

    config_class = ACTTARConfig
    name = "act_tar"
    element_loss_name = "l1_loss"

    def element_losses(self, batch):
        if self.config.image_features:
            batch = dict(batch)
            batch[OBS_IMAGES] = [batch[key] for key in self.config.image_features]
        actions_hat, (mu, log_sigma_x2) = self.model(batch)
        loss = F.l1_loss(actions_hat, batch[ACTION], reduction="none")
        if self.config.use_vae and log_sigma_x2 is not None:
            kld = (-0.5 * (1 + log_sigma_x2 - mu.pow(2) - log_sigma_x2.exp())).sum(-1)
            return ElementLosses(loss, _entry_valid(batch, loss), kld * self.config.kl_weight, {"kld_loss": kld})
        return ElementLosses(loss, _entry_valid(batch, loss))


class DiffusionTARPolicy(TARPolicyMixin, DiffusionPolicy):
    """Diffusion Policy with TAR: the denoising MSE per horizon entry and action dim (``DiffusionModel.compute_loss``
    before its mean), padding always masked. Its draw: the timestep, uniform over the scheduler's
    ``num_train_timesteps``, and the noise; its action error is the clean chunk's (:func:`diffusion_action_error`)."""

    config_class = DiffusionTARConfig
    name = "diffusion_tar"

    def element_losses(self, batch):
        if self.config.image_features:
            batch = dict(batch)
            for key in self.config.image_features:
                if self.config.n_obs_steps == 1 and batch[key].ndim == 4:
                    batch[key] = batch[key].unsqueeze(1)
            batch[OBS_IMAGES] = torch.stack([batch[key] for key in self.config.image_features], dim=-4)
        model, trajectory = self.diffusion, batch[ACTION]
        global_cond = model._prepare_global_conditioning(batch)
        eps = torch.randn(trajectory.shape, device=trajectory.device)
        steps = model.noise_scheduler.config.num_train_timesteps
        timesteps = torch.randint(low=0, high=steps, size=(trajectory.shape[0],), device=trajectory.device).long()
        noisy = model.noise_scheduler.add_noise(trajectory, eps, timesteps)
        pred = model.unet(noisy, timesteps, global_cond=global_cond)
        if self.config.prediction_type not in ("epsilon", "sample"):
            raise ValueError(f"Unsupported prediction type {self.config.prediction_type}")
        target = eps if self.config.prediction_type == "epsilon" else trajectory
        loss = F.mse_loss(pred, target, reduction="none")
        alpha_bar = model.noise_scheduler.alphas_cumprod.to(trajectory.device)[timesteps]
        clip = self.config.clip_sample_range if self.config.clip_sample else None
        error = diffusion_action_error(pred, eps, trajectory, alpha_bar, self.config.prediction_type, clip)
        quantile = (timesteps.to(loss.dtype) + 0.5) / steps  # the middle of its timestep's 1 / steps of [0, 1]
        return ElementLosses(loss, _entry_valid(batch, loss), action_error=error, quantile=quantile)


class SmolVLATARPolicy(TARPolicyMixin, SmolVLAPolicy):
    """SmolVLA with TAR: the flow-matching MSE per chunk entry and (real) action dim. Its draw: the noise and the
    time from SmolVLA's own samplers, in the order its model draws them (time: ``Beta(1.5, 1) * 0.999 + 0.001``,
    fixed in SmolVLA's ``sample_time``)."""

    #: SmolVLA's ``sample_time``: ``Beta(alpha, 1) * scale + offset`` as (alpha, scale, offset).
    time_draw = (1.5, 0.999, 0.001)

    config_class = SmolVLATARConfig
    name = "smolvla_tar"

    def element_losses(self, batch):
        batch = dict(batch)
        if self.config.adapt_to_pi_aloha:
            batch[OBS_STATE] = self._pi_aloha_decode_state(batch[OBS_STATE])
            batch[ACTION] = self._pi_aloha_encode_actions_inv(batch[ACTION])
        images, img_masks = self.prepare_images(batch)
        state = self.prepare_state(batch)
        tokens, masks = batch[OBS_LANGUAGE_TOKENS], batch[OBS_LANGUAGE_ATTENTION_MASK]
        actions = self.prepare_action(batch)
        noise = self.model.sample_noise(actions.shape, actions.device)
        time = self.model.sample_time(actions.shape[0], actions.device)
        losses = self.model.forward(images, img_masks, tokens, masks, state, actions, noise, time)
        loss = losses[:, :, : self.config.action_feature.shape[0]]
        return _flow_losses(loss, _entry_valid(batch, loss), time, *self.time_draw)


class PI0TARPolicy(TARPolicyMixin, PI0Policy):
    """pi0 with TAR: the flow-matching MSE per chunk entry and (real) action dim; padded entries are masked. Its
    draw: the noise and the time from the model's own samplers (time:
    ``Beta(time_sampling_beta_alpha, time_sampling_beta_beta) * time_sampling_scale + time_sampling_offset``)."""

    config_class = PI0TARConfig
    name = "pi0_tar"

    def element_losses(self, batch):
        images, img_masks = self._preprocess_images(batch)
        tokens, masks = batch[OBS_LANGUAGE_TOKENS], batch[OBS_LANGUAGE_ATTENTION_MASK]
        state, actions = self.prepare_state(batch), self.prepare_action(batch)
        noise = self.model.sample_noise(actions.shape, actions.device)
        time = self.model.sample_time(actions.shape[0], actions.device)
        losses = self.model.forward(images, img_masks, tokens, masks, state, actions, noise, time)
        loss = losses[:, :, : self.config.output_features[ACTION].shape[0]]
        return _flow_losses(loss, _entry_valid(batch, loss), time, *_pi_time_draw(self.config))


class PI05TARPolicy(TARPolicyMixin, PI05Policy):
    """pi0.5 with TAR (``time_axis=chunk``): the flow-matching MSE per chunk entry and (real) action dim; padded
    entries are masked. Its draw: the noise and the time from the model's own samplers (time:
    ``Beta(time_sampling_beta_alpha, time_sampling_beta_beta) * time_sampling_scale + time_sampling_offset``)."""

    config_class = PI05TARConfig
    name = "pi05_tar"

    def element_losses(self, batch):
        images, img_masks = self._preprocess_images(batch)
        tokens, masks = batch[OBS_LANGUAGE_TOKENS], batch[OBS_LANGUAGE_ATTENTION_MASK]
        actions = self.prepare_action(batch)
        noise = self.model.sample_noise(actions.shape, actions.device)
        time = self.model.sample_time(actions.shape[0], actions.device)
        losses = self.model.forward(images, img_masks, tokens, masks, actions, noise, time)
        loss = losses[:, :, : self.config.output_features[ACTION].shape[0]]
        return _flow_losses(loss, _entry_valid(batch, loss), time, *_pi_time_draw(self.config))
