"""The ``flow`` head: flow matching with an action expert, the pi0 / SmolVLA family, on the Octo-style backbone.

The backbone is :class:`~tar_rl.policies.octo.OctoBackbone` with the same config fields as the
``octo_*`` heads. On top of it an action expert (a small transformer over the chunk, after pi0's
action expert, Black et al. 2024) predicts a velocity field:

* tokens: one context token (the backbone's features, projected) and ``H`` action tokens, each
  ``W [x_h, time features]`` plus a learned position embedding per chunk index (pi0 mixes the
  flow time into every action token the same way); full attention among them; the action tokens'
  outputs are mapped to ``A`` velocities.
* convention (openpi's): ``x_tau = tau * noise + (1 - tau) * actions``, so ``tau = 1`` is pure
  noise and ``tau = 0`` the chunk; the target velocity is ``u = noise - actions`` (``dx/dtau``).
  Training draws ``tau`` per step from ``time_distribution``: ``beta`` (pi0's: ``Beta(1.5, 1)``,
  density proportional to ``tau ** 0.5``, more weight on noisy times, drawn as ``U ** (2 / 3)``
  by inversion of its CDF ``tau ** 1.5``, then mapped to ``0.001 + 0.999 * tau`` as openpi does)
  or ``uniform`` (``U(0.001, 1)``). Per-step loss: the velocity regression squared error per chunk
  element ``[B, L, H, A]``. ``tau`` and the noise come from torch's global RNG.
* inference: start from ``x_1 ~ N(0, I)`` (drawn at every call from a generator seeded with
  ``seed`` and shared by the batch's rows, :class:`~tar_rl.policies.octo.SeededSampling`: the chunk is a
  deterministic function of the row's inputs and the seed) and take ``sample_steps`` Euler steps
  ``x <- x - v(x, tau) / sample_steps`` from ``tau = 1`` to 0; the result is clipped to ``[-1, 1]``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from .base import DataInfo, Policy, PolicySpec, register_policy
from .chunking import chunked_policy
from .octo import OctoConfig, SeededSampling, TransformerBlock, check_chunk_shape, sinusoidal_embedding

__all__ = ["TIME_DISTRIBUTIONS", "FlowConfig", "FlowPolicy", "euler_integrate", "sample_flow_time"]

TIME_DISTRIBUTIONS = ("beta", "uniform")


@dataclass
class FlowConfig(OctoConfig):
    """``flow``: flow matching with a transformer action expert on the Octo-style backbone.

    Attributes:
        sample_steps: Euler steps at inference (pi0: 10).
        seed: seeds the initial noise at inference.
        time_distribution: training times ``tau``: ``beta`` (pi0's Beta(1.5, 1)) or ``uniform``.
        expert_dim: token width of the action expert.
        expert_layers: transformer blocks of the action expert (heads: ``policy.heads``).
    """

    name: str = "flow"
    sample_steps: int = 10
    seed: int = 0
    time_distribution: str = "beta"
    expert_dim: int = 32
    expert_layers: int = 2


def sample_flow_time(shape, kind: str, device=None) -> torch.Tensor:
    """Training times ``tau`` in ``[0.001, 1]`` from torch's global RNG (module docstring)."""
    u = torch.rand(shape, device=device)
    if kind == "beta":
        u = u.pow(2.0 / 3.0)  # Beta(1.5, 1): CDF tau ** 1.5, inverted
    elif kind != "uniform":
        raise ValueError(f"policy.time_distribution must be one of {list(TIME_DISTRIBUTIONS)}, got {kind!r}")
    return 0.001 + 0.999 * u


def euler_integrate(velocity_fn, x: torch.Tensor, steps: int) -> torch.Tensor:
    """Integrate ``dx/dtau = v(x, tau)`` from ``tau = 1`` to 0 in ``steps`` Euler steps; returns ``x`` at 0.

    ``velocity_fn(x [N, ...], tau [N]) -> [N, ...]``; the step at ``tau_i = 1 - i / steps`` is
    ``x <- x - v(x, tau_i) / steps``.
    """
    dt = 1.0 / steps
    for i in range(steps):
        tau = torch.full((x.shape[0],), 1.0 - i * dt, dtype=x.dtype, device=x.device)
        x = x - dt * velocity_fn(x, tau).to(x.dtype)
    return x


class FlowPolicy(SeededSampling):
    """Backbone features + action expert -> velocity; flow-matching loss; Euler sampling (module docstring)."""

    T_EMBED = 32

    def __init__(self, cfg: FlowConfig, info: DataInfo):
        if cfg.sample_steps < 1:
            raise ValueError(f"policy.sample_steps must be >= 1, got {cfg.sample_steps}")
        if cfg.time_distribution not in TIME_DISTRIBUTIONS:
            raise ValueError(
                f"policy.time_distribution must be one of {list(TIME_DISTRIBUTIONS)}, got {cfg.time_distribution!r}"
            )
        if cfg.expert_dim < 1 or cfg.expert_layers < 1 or cfg.expert_dim % cfg.heads:
            raise ValueError(
                f"policy.expert_dim must be >= 1 and divisible by policy.heads ({cfg.heads}), and "
                f"policy.expert_layers >= 1; got {cfg.expert_dim} and {cfg.expert_layers}"
            )
        super().__init__(cfg, info)
        self.sample_steps, self.time_distribution = int(cfg.sample_steps), cfg.time_distribution
        e = int(cfg.expert_dim)
        self.context = nn.Linear(int(cfg.dim), e)
        self.action_in = nn.Linear(self.action_dim + self.T_EMBED, e)
        self.action_mlp = nn.Sequential(nn.GELU(), nn.Linear(e, e))
        self.chunk_pos = nn.Parameter(torch.randn(self.horizon, e) * 0.02)
        self.expert = nn.ModuleList(
            TransformerBlock(e, int(cfg.heads), cfg.dropout, bool(cfg.compile)) for _ in range(cfg.expert_layers)
        )
        self.out = nn.Sequential(nn.LayerNorm(e), nn.Linear(e, self.action_dim))

    def velocity(self, x: torch.Tensor, tau: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
        """``v [N, H, A]`` at the noisy chunk ``x [N, H, A]``, time ``tau [N]`` in [0, 1], features ``[N, dim]``."""
        n = x.shape[0]
        temb = sinusoidal_embedding(tau * 1000.0, self.T_EMBED)[:, None].expand(n, self.horizon, self.T_EMBED)
        dtype = features.dtype
        a = self.action_in(torch.cat([x.to(dtype), temb.to(dtype)], dim=-1))
        a = a + self.action_mlp(a) + self.chunk_pos
        h = torch.cat([self.context(features)[:, None], a.to(dtype)], dim=1)
        for i, block in enumerate(self.expert):
            # only the action tokens' outputs are read after the last block
            h = block(h, last=self.horizon if i == len(self.expert) - 1 else None)
        return self.out(h)

    def step_loss(self, history, history_valid, task_id, chunk, pixels=None) -> torch.Tensor:
        """``[B, L, H, A]``: ``(v_hat(x_tau, tau) - (noise - chunk)) ** 2`` per chunk element."""
        check_chunk_shape(chunk, self.horizon, self.action_dim)
        lead = chunk.shape[:-2]
        features = self.backbone(history, history_valid, task_id, pixels).reshape(-1, self.backbone.dim)
        actions = chunk.float().reshape(-1, self.horizon, self.action_dim)
        tau = sample_flow_time(actions.shape[0], self.time_distribution, device=actions.device)
        noise = torch.randn_like(actions)
        t = tau[:, None, None]
        x_tau = t * noise + (1 - t) * actions
        v = self.velocity(x_tau, tau, features).float()
        return (v - (noise - actions)).square().reshape(*lead, self.horizon, self.action_dim)

    def sample(self, noise: torch.Tensor, features: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        """The chunk ``[N, H, A]``: ``sample_steps`` Euler steps from ``noise`` at ``tau = 1`` to 0."""
        return euler_integrate(lambda x, tau: self.velocity(x, tau, features), noise, self.sample_steps)


def _build_flow(cfg: FlowConfig, info: DataInfo) -> Policy:
    return chunked_policy(FlowPolicy(cfg, info), cfg, info, "loss_flow", history=info.history)


register_policy(
    PolicySpec(
        "flow",
        FlowConfig,
        _build_flow,
        "flow matching (pi0-style action expert, Beta(1.5, 1) times, Euler sampling) on the Octo-style backbone",
    )
)
