"""Octo-style heads on one shared transformer backbone: ``octo_linear`` and ``octo_diffusion``.

The backbone (:class:`OctoBackbone`, after Octo, Ghosh et al. 2024, at a size that trains on a
CPU) reads a window of ``K`` observations and the task and returns one feature vector:

* tokens: one task token (:class:`~tar_rl.policies.common.TaskEncoder`), ``K``
  observation tokens (the ``observation_history`` window, normalised with the training data's
  statistics, projected to ``dim``, plus a learned embedding per window position) and ``readouts``
  learned readout tokens;
* attention is block-structured as in Octo: the task token attends to itself; the observation
  token at window position ``k`` attends to the task and to the valid observation tokens at
  positions ``<= k``; the readout tokens attend to the task, to every valid observation token and
  to each other. Nothing attends to a readout token, so the readouts only read the observations,
  and invalid history entries (before the episode start, ``observation_history_valid`` False) are
  masked out of every attention: they cannot change the output;
* the readout tokens' outputs are mean-pooled and layer-normalised: ``[N, dim]`` features.
* with ``observation="image"`` (:mod:`tar_rl.policies.common`) the observation tokens carry the
  proprioceptive state only, and the current step's camera image enters as one more token, after
  the observation tokens (the conv encoder's features, ``dim`` wide): it attends to the task, the
  valid observation tokens and itself, and the readouts attend to it.

Two heads on it, the head being the only difference (the backbone class and its config fields
are shared):

* ``octo_linear``: a linear map of the features to the chunk ``[H, A]`` (Octo's continuous
  head, without its tanh squashing: targets are clipped to ``[-1, 1]`` and the actor clips its
  output); per-step loss the squared error per chunk element ``[B, L, H, A]``.
* ``octo_diffusion``: Octo's diffusion head: DDPM noise prediction (Ho et al. 2020) with a cosine
  beta schedule (Nichol and Dhariwal 2021) of ``train_steps`` steps (Octo: 20), a residual MLP
  denoiser on (noisy chunk, diffusion-step embedding, features); per-step loss the noise-prediction
  squared error per chunk element ``[B, L, H, A]``. Inference samples ``sample_steps`` steps of
  DDIM (deterministic given the initial noise, the default) or DDPM (ancestral, fresh noise each
  step), the predicted clean chunk clipped to ``[-1, 1]`` at every step.

Training noise and diffusion steps come from torch's global RNG (the recipe checkpoints it, so a
resumed run draws the same ones). Sampling noise at inference is drawn, at every call, from a
generator seeded with the config's ``seed`` and shared by the rows of the batch: the sampled chunk
is a deterministic function of the row's own inputs and the seed, whatever the batch size, the
row's slot, the calls before or the copy (pickled evaluation worker, reloaded state dict) that
runs it. So a sharded evaluation reproduces a single process's rollouts, and the policy acts as a
fixed map from observation window to chunk (one draw of the sampler's noise, not fresh noise at
every step; change ``seed`` for another draw). Nothing about sampling is held as state.

Inference goes through :class:`~tar_rl.policies.chunking.ChunkedActor` (ACT's temporal ensemble
or open-loop chunks); the models provide ``predict_chunk``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from tensordict import TensorDict, TensorDictBase
from torch import nn
from torchrl.objectives import LossModule

from . import DataInfo, Policy, PolicySpec, register_policy
from .chunking import EXECUTIONS, ChunkedActor
from .common import PROPRIO_DIMS, TASK_CONDITIONING, ObsNorm, TaskEncoder, image_encoder

__all__ = [
    "SAMPLERS",
    "ChunkLoss",
    "OctoBackbone",
    "OctoConfig",
    "OctoDiffusion",
    "OctoDiffusionConfig",
    "OctoLinear",
    "OctoLinearConfig",
    "TransformerBlock",
    "cosine_alpha_bar",
    "ddim_sample",
    "sinusoidal_embedding",
]

SAMPLERS = ("ddim", "ddpm")


# -- Configs ------------------------------------------------------------------------------------


@dataclass
class OctoConfig:
    """Settings shared by every head on the Octo-style backbone (``octo_linear``, ``octo_diffusion``, ``flow``).

    Attributes:
        name: registry name.
        dim: token width of the backbone.
        heads: attention heads (``dim`` must be divisible by it).
        layers: transformer blocks.
        readouts: learned readout tokens (mean-pooled into the features).
        dropout: dropout rate in attention and in the blocks' residual branches.
        task_conditioning: the task token: ``embedding`` (learned per task) or ``instruction``
            (bag of words of the task's instruction).
        normalize_obs: standardise observations with the training data's statistics.
        execution: inference: ``ensemble`` (ACT's temporal ensembling) or ``open_loop``.
        execute_steps: for ``open_loop``, actions executed per predicted chunk (``1..H``).
        ensemble_decay: ``m`` of the ensemble's weights ``exp(-m * i)`` (ACT: 0.01).
        observation: ``state`` (the state vectors of the window) or ``image`` (the current camera
            image as a token, plus the proprioceptive state of the window; needs a dataset with
            images, ``data.image_size > 0``).
    """

    name: str = "octo"
    dim: int = 64
    heads: int = 4
    layers: int = 2
    readouts: int = 2
    dropout: float = 0.0
    task_conditioning: str = "embedding"
    normalize_obs: bool = True
    execution: str = "ensemble"
    execute_steps: int = 1
    ensemble_decay: float = 0.01
    observation: str = "state"


@dataclass
class OctoLinearConfig(OctoConfig):
    """``octo_linear``: the backbone's features -> a linear map -> the chunk ``[H, A]``; MSE per element."""

    name: str = "octo_linear"


@dataclass
class OctoDiffusionConfig(OctoConfig):
    """``octo_diffusion``: DDPM noise prediction conditioned on the backbone's features.

    Attributes:
        train_steps: diffusion steps ``T`` of the cosine schedule (Octo: 20).
        sample_steps: denoising steps at inference, ``1..T`` (evenly spaced over the ``T`` steps).
        sampler: ``ddim`` (deterministic given the initial noise) or ``ddpm`` (ancestral).
        seed: seeds the sampling noise at inference.
        denoiser_hidden: width of the residual MLP denoiser (Octo: 256).
        denoiser_blocks: residual blocks of the denoiser (Octo: 3).
    """

    name: str = "octo_diffusion"
    train_steps: int = 20
    sample_steps: int = 10
    sampler: str = "ddim"
    seed: int = 0
    denoiser_hidden: int = 128
    denoiser_blocks: int = 3


def check_backbone_config(cfg: OctoConfig) -> None:
    """Raise ``ValueError`` naming the setting for a bad backbone or inference setting."""
    for field in ("dim", "heads", "layers", "readouts"):
        if int(getattr(cfg, field)) < 1:
            raise ValueError(f"policy.{field} must be >= 1, got {getattr(cfg, field)}")
    if cfg.dim % cfg.heads:
        raise ValueError(f"policy.dim ({cfg.dim}) must be divisible by policy.heads ({cfg.heads})")
    if not (math.isfinite(cfg.dropout) and 0.0 <= cfg.dropout < 1.0):
        raise ValueError(f"policy.dropout must lie in [0, 1), got {cfg.dropout}")
    if cfg.task_conditioning not in TASK_CONDITIONING:
        raise ValueError(
            f"policy.task_conditioning must be one of {list(TASK_CONDITIONING)}, got {cfg.task_conditioning!r}"
        )
    if cfg.execution not in EXECUTIONS:
        raise ValueError(f"policy.execution must be one of {list(EXECUTIONS)}, got {cfg.execution!r}")


# -- The backbone ---------------------------------------------------------------------------------


class TransformerBlock(nn.Module):
    """Pre-norm transformer block: masked multi-head self-attention and a GELU MLP (4x wide).

    ``forward(x [N, S, dim], mask [N, 1, S, S] or [S, S] bool (True: may attend)) -> [N, S, dim]``.
    """

    def __init__(self, dim: int, heads: int, dropout: float = 0.0):
        super().__init__()
        self.heads, self.dropout = heads, dropout
        self.norm1 = nn.LayerNorm(dim)
        self.qkv = nn.Linear(dim, 3 * dim)
        self.proj = nn.Linear(dim, dim)
        self.norm2 = nn.LayerNorm(dim)
        self.mlp = nn.Sequential(nn.Linear(dim, 4 * dim), nn.GELU(), nn.Linear(4 * dim, dim))
        self.drop = nn.Dropout(dropout)

    def forward(self, x: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        n, s, d = x.shape
        q, k, v = self.qkv(self.norm1(x)).view(n, s, 3, self.heads, d // self.heads).permute(2, 0, 3, 1, 4)
        p = self.dropout if self.training else 0.0
        if mask is not None and mask.dtype == torch.bool:
            # an additive bias: on CPU, SDPA with a float mask is about twice as fast as with a bool one here
            mask = torch.zeros(mask.shape, dtype=q.dtype, device=q.device).masked_fill_(~mask, float("-inf"))
        att = F.scaled_dot_product_attention(q, k, v, attn_mask=mask, dropout_p=p)
        x = x + self.drop(self.proj(att.transpose(1, 2).reshape(n, s, d)))
        return x + self.drop(self.mlp(self.norm2(x)))


class OctoBackbone(nn.Module):
    """Task token + ``K`` observation tokens + readout tokens -> pooled readout features (module docstring).

    ``forward(history [N, K, D], history_valid [N, K] bool (True: a real observation), task_id [N],
    pixels [N, 3, S, S] uint8 (image observations only)) -> [N, dim]``. Any leading shape:
    ``[B, L, K, D]`` gives ``[B, L, dim]``.
    """

    def __init__(self, cfg: OctoConfig, info: DataInfo):
        super().__init__()
        check_backbone_config(cfg)
        self.dim, self.history = int(cfg.dim), int(info.history)
        if self.history < 1:
            raise ValueError(f"data.history must be >= 1, got {info.history}")
        self.norm = ObsNorm(info.obs_dim, info.obs_mean, info.obs_std) if cfg.normalize_obs else nn.Identity()
        self.image = image_encoder(cfg.observation, info.image_size, self.dim)
        self.obs_width = PROPRIO_DIMS if self.image is not None else info.obs_dim
        self.obs_proj = nn.Linear(self.obs_width, self.dim)
        self.time_pos = nn.Parameter(torch.randn(self.history, self.dim) * 0.02)
        self.task = TaskEncoder(cfg.task_conditioning, info.n_tasks, self.dim, info.instructions)
        self.readout = nn.Parameter(torch.randn(int(cfg.readouts), self.dim) * 0.02)
        self.blocks = nn.ModuleList(TransformerBlock(self.dim, int(cfg.heads), cfg.dropout) for _ in range(cfg.layers))
        self.out_norm = nn.LayerNorm(self.dim)
        images = int(self.image is not None)
        self.register_buffer(
            "block_mask", self.attention_rules(self.history, int(cfg.readouts), images), persistent=False
        )

    @property
    def reads_pixels(self) -> bool:
        """True with image observations: ``forward`` needs ``pixels``."""
        return self.image is not None

    @staticmethod
    def attention_rules(k: int, r: int, images: int = 0) -> torch.Tensor:
        """The block structure ``[S, S]`` bool (row: query, column: key; True: may attend),
        ``S = 1 + k + images + r``.

        Token order: task, observations (oldest first), the current image (``images`` 1), readouts.
        """
        s = 1 + k + images + r
        rules = torch.zeros(s, s, dtype=torch.bool)
        obs, img, read = slice(1, 1 + k), slice(1 + k, 1 + k + images), slice(1 + k + images, s)
        rules[0, 0] = True  # the task token: itself
        rules[obs, 0] = True  # observations: the task ...
        rules[obs, obs] = torch.ones(k, k, dtype=torch.bool).tril()  # ... and observations up to their own time
        rules[img, : 1 + k + images] = True  # the image: task, every observation and itself
        rules[read, : 1 + k + images] = True  # readouts: task, every observation, the image ...
        rules[read, read] = True  # ... and the readouts; nothing else attends to a readout
        return rules

    def forward(
        self,
        history: torch.Tensor,
        history_valid: torch.Tensor,
        task_id: torch.Tensor,
        pixels: torch.Tensor | None = None,
    ) -> torch.Tensor:
        lead = history.shape[:-2]
        if history.shape[-2] != self.history:
            raise ValueError(
                f"the observation history has {history.shape[-2]} entries, the policy was built for "
                f"data.history = {self.history}"
            )
        history = history.reshape(-1, self.history, history.shape[-1])
        valid = history_valid.reshape(-1, self.history).bool()
        n = history.shape[0]
        # Invalid entries are zeroed as well as masked: nothing of them (not even a NaN) gets through.
        obs = torch.where(valid[..., None], self.norm(history), torch.zeros((), dtype=history.dtype))
        obs_tokens = self.obs_proj(obs[..., : self.obs_width]) + self.time_pos
        task_token = self.task(task_id.reshape(n))[:, None]
        readouts = self.readout.expand(n, -1, -1)
        tokens = [task_token.to(obs_tokens.dtype), obs_tokens]
        if self.image is not None:
            tokens.append(self.image(pixels).reshape(n, 1, -1).to(obs_tokens.dtype))
        x = torch.cat([*tokens, readouts.to(obs_tokens.dtype)], dim=1)
        r = self.readout.shape[0]
        keys = torch.cat([valid.new_ones(n, 1), valid, valid.new_ones(n, x.shape[1] - 1 - self.history)], dim=1)
        mask = (self.block_mask[None] & keys[:, None, :])[:, None]  # [N, 1, S, S]
        for block in self.blocks:
            x = block(x, mask)
        features = self.out_norm(x[:, -r:].mean(1))
        return features.reshape(*lead, self.dim)


# -- Diffusion helpers ---------------------------------------------------------------------------


def cosine_alpha_bar(steps: int, s: float = 0.008, max_beta: float = 0.999) -> torch.Tensor:
    """``alpha_bar_t`` for ``t = 0 .. steps - 1`` of the cosine schedule (Nichol and Dhariwal 2021), float64.

    ``f(u) = cos((u / T + s) / (1 + s) * pi / 2) ** 2``, ``beta_t = min(1 - f(t + 1) / f(t), max_beta)``,
    ``alpha_bar_t = prod_{i <= t} (1 - beta_i)``: ``f(t + 1) / f(0)`` wherever no beta was clipped
    (only the last one is, where ``f(T) = 0``).
    """
    u = torch.arange(steps + 1, dtype=torch.float64) / steps
    f = torch.cos((u + s) / (1 + s) * math.pi / 2) ** 2
    betas = (1 - f[1:] / f[:-1]).clamp(0.0, max_beta)
    return torch.cumprod(1 - betas, dim=0)


def sinusoidal_embedding(t: torch.Tensor, dim: int, max_period: float = 10_000.0) -> torch.Tensor:
    """``[..., dim]`` sine and cosine features of ``t`` (``[...]``, any real values), ``dim`` even."""
    half = dim // 2
    freqs = torch.exp(-math.log(max_period) * torch.arange(half, device=t.device, dtype=torch.float32) / half)
    angles = t.to(torch.float32)[..., None] * freqs
    return torch.cat([torch.sin(angles), torch.cos(angles)], dim=-1)


def sampling_timesteps(train_steps: int, sample_steps: int) -> list[int]:
    """The ``sample_steps`` diffusion steps visited at inference, from ``T - 1`` down to 0, evenly spaced."""
    return [round(x) for x in torch.linspace(train_steps - 1, 0, sample_steps, dtype=torch.float64).tolist()]


def ddim_sample(
    eps_fn,
    x: torch.Tensor,
    alpha_bar: torch.Tensor,
    timesteps: list[int],
    eta: float = 0.0,
    generator: torch.Generator | None = None,
    clip: float | None = 1.0,
) -> torch.Tensor:
    """Run the reverse process from ``x = x_{t_0}`` over ``timesteps`` (decreasing, ending at 0); returns ``x_0``.

    At each step ``t`` (next step ``t'``, ``alpha_bar_{-1} = 1`` after the last):
    ``x0 = (x - sqrt(1 - ab_t) eps) / sqrt(ab_t)`` (clipped to ``[-clip, clip]``),
    ``sigma = eta * sqrt((1 - ab_t') / (1 - ab_t) * (1 - ab_t / ab_t'))``,
    ``x <- sqrt(ab_t') x0 + sqrt(1 - ab_t' - sigma^2) eps + sigma z``, ``z ~ N(0, I)`` from
    ``generator``, one draw of ``x``'s trailing shape shared by the rows (so each row depends on its
    own inputs only).
    ``eta = 0`` is DDIM (Song et al. 2021); ``eta = 1`` is DDPM's ancestral step (with every step
    visited, ``sigma^2`` is DDPM's posterior variance ``(1 - ab_{t-1}) / (1 - ab_t) beta_t``).

    Args:
        eps_fn: ``(x [N, ...], t [N] int64) -> eps [N, ...]``, the noise prediction.
        x: the initial noise ``[N, ...]``.
        alpha_bar: ``[T]`` from :func:`cosine_alpha_bar`.
        timesteps: the steps to visit, e.g. :func:`sampling_timesteps`.
        eta: 0 (DDIM) .. 1 (DDPM).
        generator: for ``z`` (``eta > 0``).
        clip: bound of the predicted ``x0`` (``None``: no clipping).
    """
    ab = alpha_bar.to(device=x.device, dtype=torch.float64)
    for i, t in enumerate(timesteps):
        a_t = ab[t]
        a_next = ab[timesteps[i + 1]] if i + 1 < len(timesteps) else ab.new_ones(())
        eps = eps_fn(x, torch.full((x.shape[0],), t, dtype=torch.long, device=x.device)).to(x.dtype)
        x0 = (x - (1 - a_t).sqrt().to(x.dtype) * eps) / a_t.sqrt().to(x.dtype)
        if clip is not None:
            x0 = x0.clamp(-clip, clip)
        sigma = eta * ((1 - a_next) / (1 - a_t) * (1 - a_t / a_next)).clamp_min(0).sqrt()
        direction = (1 - a_next - sigma**2).clamp_min(0).sqrt()
        x = a_next.sqrt().to(x.dtype) * x0 + direction.to(x.dtype) * eps
        if eta > 0 and i + 1 < len(timesteps):
            z = torch.randn((1, *x.shape[1:]), generator=generator, device=x.device, dtype=x.dtype)
            x = x + sigma.to(x.dtype) * z
    return x


# -- The models ----------------------------------------------------------------------------------


class SeededSampling(nn.Module):
    """Base of the models that sample at inference: a fresh generator seeded with ``seed`` per call.

    No generator is kept on the module (a ``torch.Generator`` does not pickle, and a kept one would
    make the actions depend on the calls before): :meth:`sampling_generator` makes a new one each
    time, and :meth:`initial_noise` draws one ``[1, H, A]`` sample shared by the ``N`` rows.
    """

    def __init__(self, seed: int):
        super().__init__()
        self.seed = int(seed)

    def sampling_generator(self, device: torch.device) -> torch.Generator:
        return torch.Generator(device=device).manual_seed(self.seed)

    def initial_noise(self, n: int, shape: tuple[int, ...], generator: torch.Generator, device) -> torch.Tensor:
        """``[n, *shape]`` standard normal noise, the same for every row."""
        return torch.randn((1, *shape), generator=generator, device=device).expand(n, *shape)


def _chunk_shapes(chunk: torch.Tensor, horizon: int, action_dim: int) -> None:
    if chunk.shape[-2:] != (horizon, action_dim):
        raise ValueError(
            f"action_chunk has event shape {list(chunk.shape[-2:])}, the policy predicts [{horizon}, {action_dim}] "
            "(data.chunk_horizon must match the one the policy was built with)"
        )


class OctoLinear(nn.Module):
    """Backbone features -> a linear map -> the chunk ``[..., H, A]``; per-step loss the squared error per element."""

    def __init__(self, cfg: OctoConfig, info: DataInfo):
        super().__init__()
        self.horizon, self.action_dim = int(info.chunk_horizon), int(info.action_dim)
        self.backbone = OctoBackbone(cfg, info)
        self.head = nn.Linear(int(cfg.dim), self.horizon * self.action_dim)

    def forward(self, history, history_valid, task_id, pixels=None) -> torch.Tensor:
        features = self.backbone(history, history_valid, task_id, pixels)
        return self.head(features).unflatten(-1, (self.horizon, self.action_dim))

    def step_loss(self, history, history_valid, task_id, chunk, pixels=None) -> torch.Tensor:
        """``[B, L, H, A]`` squared errors of the predicted chunk."""
        _chunk_shapes(chunk, self.horizon, self.action_dim)
        return (self(history, history_valid, task_id, pixels).float() - chunk.float()).square()

    def predict_chunk(self, history, history_valid, task_id, pixels=None) -> torch.Tensor:
        return self(history, history_valid, task_id, pixels)


class ResidualMLP(nn.Module):
    """``in -> hidden``, ``blocks`` pre-norm residual blocks (LayerNorm, Linear, GELU, Linear), ``-> out``."""

    def __init__(self, d_in: int, hidden: int, blocks: int, d_out: int, dropout: float = 0.0):
        super().__init__()
        self.inp = nn.Linear(d_in, hidden)
        self.blocks = nn.ModuleList(
            nn.Sequential(
                nn.LayerNorm(hidden),
                nn.Linear(hidden, 4 * hidden),
                nn.GELU(),
                nn.Dropout(dropout),
                nn.Linear(4 * hidden, hidden),
            )
            for _ in range(blocks)
        )
        self.out = nn.Sequential(nn.LayerNorm(hidden), nn.GELU(), nn.Linear(hidden, d_out))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = self.inp(x)
        for block in self.blocks:
            h = h + block(h)
        return self.out(h)


class OctoDiffusion(SeededSampling):
    """DDPM noise prediction on the backbone's features (module docstring)."""

    T_EMBED = 32  # width of the sinusoidal diffusion-step features

    def __init__(self, cfg: OctoDiffusionConfig, info: DataInfo):
        super().__init__(cfg.seed)
        if cfg.train_steps < 1:
            raise ValueError(f"policy.train_steps must be >= 1, got {cfg.train_steps}")
        if not 1 <= cfg.sample_steps <= cfg.train_steps:
            raise ValueError(
                f"policy.sample_steps must lie in 1..{cfg.train_steps} (policy.train_steps), got {cfg.sample_steps}"
            )
        if cfg.sampler not in SAMPLERS:
            raise ValueError(f"policy.sampler must be one of {list(SAMPLERS)}, got {cfg.sampler!r}")
        if cfg.denoiser_hidden < 1 or cfg.denoiser_blocks < 0:
            raise ValueError(
                f"policy.denoiser_hidden must be >= 1 and policy.denoiser_blocks >= 0, "
                f"got {cfg.denoiser_hidden} and {cfg.denoiser_blocks}"
            )
        self.horizon, self.action_dim = int(info.chunk_horizon), int(info.action_dim)
        self.train_steps, self.sample_steps, self.sampler = int(cfg.train_steps), int(cfg.sample_steps), cfg.sampler
        self.backbone = OctoBackbone(cfg, info)
        hidden = int(cfg.denoiser_hidden)
        self.t_embed = nn.Sequential(nn.Linear(self.T_EMBED, hidden), nn.GELU(), nn.Linear(hidden, hidden))
        flat = self.horizon * self.action_dim
        self.denoiser = ResidualMLP(
            int(cfg.dim) + hidden + flat, hidden, int(cfg.denoiser_blocks), flat, dropout=cfg.dropout
        )
        self.register_buffer("alpha_bar", cosine_alpha_bar(self.train_steps).float(), persistent=False)

    def eps(self, noisy: torch.Tensor, t: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
        """Predicted noise ``[..., H, A]`` from the noisy chunk ``[..., H, A]``, step ``t [...]`` and features."""
        temb = self.t_embed(sinusoidal_embedding(t, self.T_EMBED).to(features.dtype))
        x = torch.cat([features, temb.to(features.dtype), noisy.flatten(-2).to(features.dtype)], dim=-1)
        return self.denoiser(x).unflatten(-1, (self.horizon, self.action_dim))

    def step_loss(self, history, history_valid, task_id, chunk, pixels=None) -> torch.Tensor:
        """``[B, L, H, A]``: ``(eps_hat - eps) ** 2`` , ``t ~ U{0..T-1}``, ``eps ~ N(0, I)`` per step (global RNG)."""
        _chunk_shapes(chunk, self.horizon, self.action_dim)
        features = self.backbone(history, history_valid, task_id, pixels)
        chunk = chunk.float()
        t = torch.randint(self.train_steps, chunk.shape[:-2], device=chunk.device)
        noise = torch.randn_like(chunk)
        ab = self.alpha_bar[t][..., None, None]
        noisy = ab.sqrt() * chunk + (1 - ab).sqrt() * noise
        return (self.eps(noisy, t, features).float() - noise).square()

    @torch.no_grad()
    def predict_chunk(self, history, history_valid, task_id, pixels=None) -> torch.Tensor:
        features = self.backbone(history, history_valid, task_id, pixels)
        n = features.shape[0]
        gen = self.sampling_generator(features.device)
        x = self.initial_noise(n, (self.horizon, self.action_dim), gen, features.device)
        steps = sampling_timesteps(self.train_steps, self.sample_steps)
        eta = 0.0 if self.sampler == "ddim" else 1.0
        x = ddim_sample(lambda x, t: self.eps(x, t, features), x, self.alpha_bar, steps, eta=eta, generator=gen)
        return x.clamp(-1.0, 1.0)


# -- The loss and the builders -------------------------------------------------------------------


def hold_last_valid(chunk: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """``chunk [..., H, A]`` with every entry past the last valid one (``valid [..., H]``, a prefix of
    True) replaced by the last valid action; a chunk with no valid entry keeps its first one throughout."""
    last = (valid.long().sum(-1, keepdim=True) - 1).clamp_min(0)  # [..., 1]
    held = chunk.gather(-2, last[..., None].expand(*last.shape, chunk.shape[-1]))  # [..., 1, A]
    return torch.where(valid[..., None].bool(), chunk, held)


class ChunkLoss(LossModule):
    """Per-step loss of a chunked head on ``[B, L]`` segments: ``[B, L, H, A]``, never reduced.

    Calls ``model.step_loss(observation_history, observation_history_valid, task_id, action_chunk)``
    (plus ``pixels=`` for a model with image observations, ``model.backbone.reads_pixels``)
    (the squared error of a regression head, the noise or velocity regression error of a generative
    one) and writes it as ``loss_name``. Padded chunk entries (``action_chunk_valid`` False) and
    padded steps are left in the output: ``TARLoss`` averages over the valid chunk entries
    (``set_keys(event_valid="action_chunk_valid")``) and weights the valid steps. Before the call,
    padded chunk entries are set to the chunk's last valid action (the dataset's own convention past
    an episode's end), so that whatever they hold cannot reach the valid entries' losses through
    heads that read the whole noisy chunk (the diffusion denoiser, the flow action expert).

    Args:
        model: a head with ``step_loss``.
        loss_name: the output entry, ``loss_<something>``.
    """

    @dataclass
    class _AcceptedKeys:
        """Input keys.

        Attributes:
            observation_history: ``[B, L, K, D]`` observation window, oldest first.
            observation_history_valid: ``[B, L, K]`` bool, True on real observations.
            task_id: ``[B, L]`` int64 task index.
            action: the regression target, by default ``action_chunk`` ``[B, L, H, A]`` (the next
                ``H`` expert actions). Named ``action`` so that ``TARLoss``'s ``perturb_*`` controls
                find it and corrupt the chunk the head learns from.
            action_valid: ``[B, L, H]`` bool, True on chunk entries that are real steps (a prefix);
                optional.
            pixels: ``[B, L, 3, S, S]`` uint8 camera images, read by models with image observations only.
        """

        observation_history: str = "observation_history"
        observation_history_valid: str = "observation_history_valid"
        task_id: str = "task_id"
        action: str = "action_chunk"
        action_valid: str = "action_chunk_valid"
        pixels: str = "pixels"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys

    def __init__(self, model: nn.Module, loss_name: str = "loss_chunk"):
        super().__init__()
        if not loss_name.startswith("loss_"):
            raise ValueError(f"the loss entry must start with 'loss_', got {loss_name!r}")
        self.model = model
        self.loss_name = loss_name
        self.reduction = "none"

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    @property
    def in_keys(self) -> list:
        k = self.tensor_keys
        keys = [k.observation_history, k.observation_history_valid, k.task_id, k.action, k.action_valid]
        return keys + ([k.pixels] if self.model.backbone.reads_pixels else [])

    @property
    def out_keys(self) -> list:
        return [self.loss_name]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        k = self.tensor_keys
        chunk = tensordict.get(k.action)
        valid = tensordict.get(k.action_valid, None)
        if valid is not None:
            chunk = hold_last_valid(chunk, valid)
        images = {"pixels": tensordict.get(k.pixels)} if self.model.backbone.reads_pixels else {}
        loss = self.model.step_loss(
            tensordict.get(k.observation_history),
            tensordict.get(k.observation_history_valid),
            tensordict.get(k.task_id),
            chunk,
            **images,
        )
        return TensorDict({self.loss_name: loss}, batch_size=[])


# "action" is not read by the loss: the recipe's weight recording plots its gripper dimension.
CHUNK_KEYS = (
    "observation_history",
    "observation_history_valid",
    "task_id",
    "action_chunk",
    "action_chunk_valid",
    "action",
)


def chunked_policy(model: nn.Module, cfg: OctoConfig, info: DataInfo, loss_name: str) -> Policy:
    """The :class:`Policy` of a chunked head: a ``ChunkedActor`` and a ``ChunkLoss`` sharing ``model``."""
    images = model.backbone.reads_pixels
    actor = ChunkedActor(
        model,
        horizon=info.chunk_horizon,
        history=info.history,
        execution=cfg.execution,
        execute_steps=cfg.execute_steps,
        ensemble_decay=cfg.ensemble_decay,
        images=images,
    )
    keys = CHUNK_KEYS + (("pixels",) if images else ())
    return Policy(actor=actor, loss=ChunkLoss(model, loss_name), keys=keys, event_valid="action_chunk_valid")


def _build_linear(cfg: OctoLinearConfig, info: DataInfo) -> Policy:
    return chunked_policy(OctoLinear(cfg, info), cfg, info, "loss_octo_linear")


def _build_diffusion(cfg: OctoDiffusionConfig, info: DataInfo) -> Policy:
    return chunked_policy(OctoDiffusion(cfg, info), cfg, info, "loss_octo_diffusion")


register_policy(
    PolicySpec(
        "octo_linear",
        OctoLinearConfig,
        _build_linear,
        "Octo-style transformer (task, observation window, readouts) with a linear chunk head, MSE",
    )
)
register_policy(
    PolicySpec(
        "octo_diffusion",
        OctoDiffusionConfig,
        _build_diffusion,
        "Octo-style transformer with a DDPM diffusion head (cosine schedule, DDIM/DDPM sampling)",
    )
)
