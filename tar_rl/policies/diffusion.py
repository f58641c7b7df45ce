"""The ``octo_diffusion`` head: Octo's diffusion head on the Octo-style backbone (:mod:`tar_rl.policies.octo`).

DDPM noise prediction (Ho et al. 2020) with a cosine beta schedule (Nichol and Dhariwal 2021) of
``train_steps`` steps (Octo: 20), a residual MLP denoiser on (noisy chunk, diffusion-step
embedding, features); per-step loss the noise-prediction squared error per chunk element
``[B, L, H, A]``. Inference samples ``sample_steps`` steps of DDIM (deterministic given the initial
noise, the default) or DDPM (ancestral, fresh noise each step), the predicted clean chunk clipped to
``[-1, 1]`` at every step.

Training noise and diffusion steps come from torch's global RNG; sampling noise at inference from a
generator seeded with ``seed`` (:class:`~tar_rl.policies.octo.SeededSampling`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

from .attention import compile_once, use_compiled
from .base import DataInfo, Policy, PolicySpec, register_policy
from .chunking import chunked_policy
from .octo import OctoConfig, SeededSampling, check_chunk_shape, sinusoidal_embedding

__all__ = [
    "SAMPLERS",
    "OctoDiffusion",
    "OctoDiffusionConfig",
    "ResidualMLP",
    "cosine_alpha_bar",
    "ddim_sample",
    "sampling_timesteps",
]

SAMPLERS = ("ddim", "ddpm")


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


# -- Sampling -------------------------------------------------------------------------------------


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


# -- The model ------------------------------------------------------------------------------------


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
        super().__init__(cfg, info)
        self.train_steps, self.sample_steps, self.sampler = int(cfg.train_steps), int(cfg.sample_steps), cfg.sampler
        self.compiled, self.dropout = bool(cfg.compile), float(cfg.dropout)
        hidden = int(cfg.denoiser_hidden)
        self.t_embed = nn.Sequential(nn.Linear(self.T_EMBED, hidden), nn.GELU(), nn.Linear(hidden, hidden))
        flat = self.horizon * self.action_dim
        self.denoiser = ResidualMLP(
            int(cfg.dim) + hidden + flat, hidden, int(cfg.denoiser_blocks), flat, dropout=cfg.dropout
        )
        self.register_buffer("alpha_bar", cosine_alpha_bar(self.train_steps).float(), persistent=False)

    def eps(self, noisy: torch.Tensor, t: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
        """Predicted noise ``[..., H, A]`` from the noisy chunk ``[..., H, A]``, step ``t [...]`` and features.

        With ``policy.compile``, a training step on the CPU runs it compiled (:mod:`tar_rl.policies.attention`).
        """
        if use_compiled(self.compiled, features, self.dropout if self.training else 0.0):
            return compile_once(_eps)(self, noisy, t, features)
        return _eps(self, noisy, t, features)

    def step_loss(self, history, history_valid, task_id, chunk, pixels=None) -> torch.Tensor:
        """``[B, L, H, A]``: ``(eps_hat - eps) ** 2`` , ``t ~ U{0..T-1}``, ``eps ~ N(0, I)`` per step (global RNG)."""
        check_chunk_shape(chunk, self.horizon, self.action_dim)
        features = self.backbone(history, history_valid, task_id, pixels)
        chunk = chunk.float()
        t = torch.randint(self.train_steps, chunk.shape[:-2], device=chunk.device)
        noise = torch.randn_like(chunk)
        ab = self.alpha_bar[t][..., None, None]
        noisy = ab.sqrt() * chunk + (1 - ab).sqrt() * noise
        return (self.eps(noisy, t, features).float() - noise).square()

    def sample(self, noise: torch.Tensor, features: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        """The chunk ``[N, H, A]`` by DDIM or DDPM from ``noise``, the predicted clean chunk clipped at every step."""
        steps = sampling_timesteps(self.train_steps, self.sample_steps)
        eta = 0.0 if self.sampler == "ddim" else 1.0
        return ddim_sample(
            lambda x, t: self.eps(x, t, features), noise, self.alpha_bar, steps, eta=eta, generator=generator
        )


def _eps(model: OctoDiffusion, noisy: torch.Tensor, t: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
    """The computation of :meth:`OctoDiffusion.eps`."""
    temb = model.t_embed(sinusoidal_embedding(t, model.T_EMBED).to(features.dtype))
    x = torch.cat([features, temb.to(features.dtype), noisy.flatten(-2).to(features.dtype)], dim=-1)
    return model.denoiser(x).unflatten(-1, (model.horizon, model.action_dim))


def _build_diffusion(cfg: OctoDiffusionConfig, info: DataInfo) -> Policy:
    return chunked_policy(OctoDiffusion(cfg, info), cfg, info, "loss_octo_diffusion", history=info.history)


register_policy(
    PolicySpec(
        "octo_diffusion",
        OctoDiffusionConfig,
        _build_diffusion,
        "Octo-style transformer with a DDPM diffusion head (cosine schedule, DDIM/DDPM sampling)",
    )
)
