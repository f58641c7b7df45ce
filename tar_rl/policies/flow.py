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
  element ``[B, L, H, A]``. ``tau`` and the noise come from torch's global RNG. ``time_sampling``:
  ``step`` draws them for every step of a ``[B, L]`` batch apart (pi0's); ``segment`` draws one ``tau``
  and one noise chunk per segment, shared by its ``L`` steps, with the segments' times stratified
  (common random numbers: ``u_b = (u_0 + b / B) mod 1`` for segment ``b`` of ``B``, one ``u_0 ~ U(0, 1)``
  per batch, then the time distribution's inverse CDF), so that within a segment the steps' losses
  differ by the steps and not by the draw.
* ranking signals (what ``TARLoss`` may rank the steps by instead of the loss, :data:`FLOW_SIGNALS`):
  ``action_error``, the error of the chunk the velocity implies, and ``time_normalized``, the loss
  over a running estimate of the mean loss at its time (:class:`~tar_rl.objectives.signals.TimeNormalizer`).
  The implied chunk:
  from ``x_tau = tau * noise + (1 - tau) * A`` and ``u = noise - A``, ``A = x_tau - tau * u``, so the
  velocity ``v_hat`` implies ``A_hat = x_tau - tau * v_hat`` and ``A_hat - A = tau * (u - v_hat)``: per
  chunk element ``(A_hat - A) ** 2 = tau ** 2 * (v_hat - u) ** 2``, the step's action error is
  ``tau ** 2`` times its velocity loss (``tau ** 2`` in this convention, where ``tau = 1`` is noise; in
  the convention ``x_t = t * A + (1 - t) * noise`` it would be ``(1 - t) ** 2``). The same action
  error costs ``1 / tau ** 2`` times more velocity loss at a small ``tau``, which no other step of its
  segment shares when each step draws its own ``tau``.
* inference: start from ``x_1 ~ N(0, I)`` (drawn at every call from a generator seeded with
  ``seed`` and shared by the batch's rows, :class:`~tar_rl.policies.octo.SeededSampling`: the chunk is a
  deterministic function of the row's inputs and the seed) and take ``sample_steps`` Euler steps
  ``x <- x - v(x, tau) / sample_steps`` from ``tau = 1`` to 0; the result is clipped to ``[-1, 1]``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from tar_rl.objectives.signals import TimeNormalizer

from .base import DataInfo, Policy, PolicySpec, register_policy
from .chunking import TIME, chunked_policy
from .octo import OctoConfig, SeededSampling, TransformerBlock, check_chunk_shape, hold_last_valid, sinusoidal_embedding

__all__ = [
    "FLOW_SIGNALS",
    "TIME_DISTRIBUTIONS",
    "TIME_SAMPLINGS",
    "FlowConfig",
    "FlowPolicy",
    "euler_integrate",
    "flow_time",
    "flow_time_cdf",
    "sample_flow_time",
    "stratified_uniform",
]

TIME_DISTRIBUTIONS = ("beta", "uniform")
#: ``policy.time_sampling``: one training time and noise per step, or per segment (stratified across segments).
TIME_SAMPLINGS = ("step", "segment")
#: The ranking signals the head offers besides its loss (``objective.signal``; module docstring).
FLOW_SIGNALS = ("action_error", "time_normalized")


@dataclass
class FlowConfig(OctoConfig):
    """``flow``: flow matching with a transformer action expert on the Octo-style backbone.

    Attributes:
        sample_steps: Euler steps at inference (pi0: 10).
        seed: seeds the initial noise at inference.
        time_distribution: training times ``tau``: ``beta`` (pi0's Beta(1.5, 1)) or ``uniform``.
        time_sampling: ``step`` (a time and a noise chunk per step, pi0's) or ``segment`` (one per segment,
            shared by its steps, the segments' times stratified across the batch; see ``tar_rl.policies.flow``).
        expert_dim: token width of the action expert.
        expert_layers: transformer blocks of the action expert (heads: ``policy.heads``).
    """

    name: str = "flow"
    sample_steps: int = 10
    seed: int = 0
    time_distribution: str = "beta"
    time_sampling: str = "step"
    expert_dim: int = 32
    expert_layers: int = 2


def flow_time(u: torch.Tensor, kind: str) -> torch.Tensor:
    """Training times ``tau`` in ``[0.001, 1]`` from uniform ``u`` in ``[0, 1)``: the inverse CDF of the time
    distribution ``kind`` (module docstring)."""
    if kind == "beta":
        u = u.pow(2.0 / 3.0)  # Beta(1.5, 1): CDF tau ** 1.5, inverted
    elif kind != "uniform":
        raise ValueError(f"policy.time_distribution must be one of {list(TIME_DISTRIBUTIONS)}, got {kind!r}")
    return 0.001 + 0.999 * u


def flow_time_cdf(tau: torch.Tensor, kind: str) -> torch.Tensor:
    """The time distribution's CDF at ``tau``, in ``[0, 1]``: :func:`flow_time` inverted."""
    u = ((tau - 0.001) / 0.999).clamp(0.0, 1.0)
    return u.pow(1.5) if kind == "beta" else u


def sample_flow_time(shape, kind: str, device=None) -> torch.Tensor:
    """Training times ``tau`` in ``[0.001, 1]`` from torch's global RNG (module docstring)."""
    return flow_time(torch.rand(shape, device=device), kind)


def stratified_uniform(n: int, device=None) -> torch.Tensor:
    """``[n]`` uniforms, one in each of the ``n`` strata ``[b / n, (b + 1) / n)``: ``(u_0 + b / n) mod 1`` for
    ``b = 0 .. n-1`` with one ``u_0 ~ U(0, 1)`` from torch's global RNG."""
    return (torch.rand((), device=device) + torch.arange(n, device=device) / n) % 1.0


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
    signals = FLOW_SIGNALS

    def __init__(self, cfg: FlowConfig, info: DataInfo):
        if cfg.sample_steps < 1:
            raise ValueError(f"policy.sample_steps must be >= 1, got {cfg.sample_steps}")
        if cfg.time_distribution not in TIME_DISTRIBUTIONS:
            raise ValueError(
                f"policy.time_distribution must be one of {list(TIME_DISTRIBUTIONS)}, got {cfg.time_distribution!r}"
            )
        if cfg.time_sampling not in TIME_SAMPLINGS:
            raise ValueError(f"policy.time_sampling must be one of {list(TIME_SAMPLINGS)}, got {cfg.time_sampling!r}")
        if cfg.expert_dim < 1 or cfg.expert_layers < 1 or cfg.expert_dim % cfg.heads:
            raise ValueError(
                f"policy.expert_dim must be >= 1 and divisible by policy.heads ({cfg.heads}), and "
                f"policy.expert_layers >= 1; got {cfg.expert_dim} and {cfg.expert_layers}"
            )
        super().__init__(cfg, info)
        self.sample_steps, self.time_distribution = int(cfg.sample_steps), cfg.time_distribution
        self.time_sampling = cfg.time_sampling
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
        return self.flow_loss(history, history_valid, task_id, chunk, pixels)[0]

    def flow_loss(self, history, history_valid, task_id, chunk, pixels=None) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`step_loss` ``[*B, H, A]`` and the time ``tau`` ``[*B]`` each step's loss was drawn at."""
        check_chunk_shape(chunk, self.horizon, self.action_dim)
        lead = chunk.shape[:-2]
        features = self.backbone(history, history_valid, task_id, pixels).reshape(-1, self.backbone.dim)
        actions = chunk.float().reshape(-1, self.horizon, self.action_dim)
        tau, noise = self.draw(actions, lead)
        t = tau[:, None, None]
        x_tau = t * noise + (1 - t) * actions
        v = self.velocity(x_tau, tau, features).float()
        loss = (v - (noise - actions)).square().reshape(*lead, self.horizon, self.action_dim)
        return loss, tau.reshape(lead)

    def draw(self, actions: torch.Tensor, lead: torch.Size) -> tuple[torch.Tensor, torch.Tensor]:
        """The training times ``[N]`` and noise ``[N, H, A]`` of the ``N`` chunks ``actions`` (``lead`` their batch
        shape): per step, or with ``time_sampling="segment"`` per segment (the last axis of ``lead`` holds a
        segment's steps; a flat batch is one segment), stratified across segments (module docstring)."""
        if self.time_sampling == "step":
            tau = sample_flow_time(actions.shape[0], self.time_distribution, device=actions.device)
            return tau, torch.randn_like(actions)
        steps = lead[-1] if len(lead) else 1
        segments = actions.shape[0] // steps
        tau = flow_time(stratified_uniform(segments, actions.device), self.time_distribution)
        noise = torch.randn(segments, 1, *actions.shape[1:], device=actions.device, dtype=actions.dtype)
        return tau.repeat_interleave(steps), noise.expand(segments, steps, *actions.shape[1:]).reshape(actions.shape)

    def chunk_loss(
        self,
        observation_history: torch.Tensor,
        observation_history_valid: torch.Tensor,
        task_id: torch.Tensor,
        action_chunk: torch.Tensor,
        action_chunk_valid: torch.Tensor | None = None,
        pixels: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, dict]:
        """As :meth:`OctoHead.chunk_loss`, with each step's training time among the extras (``TIME``)."""
        if action_chunk_valid is not None:
            action_chunk = hold_last_valid(action_chunk, action_chunk_valid)
        images = {"pixels": pixels} if self.reads_pixels else {}
        loss, tau = self.flow_loss(observation_history, observation_history_valid, task_id, action_chunk, **images)
        return loss, {TIME: tau.detach()}

    def signal_state(self, name: str) -> nn.Module | None:
        """The state of the ranking signal ``name``: a :class:`TimeNormalizer` for ``time_normalized``."""
        return TimeNormalizer() if name == "time_normalized" else None

    def step_signal(self, name, step_loss, time, valid, state, update) -> torch.Tensor:
        """The ranking signal ``name`` ``[*B]`` of each step (module docstring): ``action_error``,
        ``tau ** 2 * step_loss``; ``time_normalized``, ``step_loss`` over ``state``'s estimate at ``tau``."""
        if name == "action_error":
            return time.square() * step_loss
        if name == "time_normalized":
            return state(step_loss, flow_time_cdf(time, self.time_distribution), valid, update)
        raise ValueError(f"the flow head offers the ranking signals {list(FLOW_SIGNALS)}, not {name!r}")

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
        signals=FLOW_SIGNALS,
    )
)
