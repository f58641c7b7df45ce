"""The Octo-style transformer backbone, the parts every head on it shares, and the ``octo_linear`` head.

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

Three heads sit on it, the head being the only difference (the backbone class and its config
fields, :class:`OctoConfig`, are shared; :class:`OctoHead` is their common base):

* ``octo_linear`` (here): a linear map of the features to the chunk ``[H, A]`` (Octo's continuous
  head, without its tanh squashing: targets are clipped to ``[-1, 1]`` and the actor clips its
  output); per-step loss the squared error per chunk element ``[B, L, H, A]``;
* ``octo_diffusion`` (:mod:`tar_rl.policies.diffusion`): Octo's diffusion head;
* ``flow`` (:mod:`tar_rl.policies.flow`): flow matching with an action expert.

The generative heads sample at inference (:class:`SeededSampling`). Their training noise comes
from torch's global RNG (the recipe checkpoints it, so a resumed run draws the same numbers).
Sampling noise at inference is drawn, at every call, from a generator seeded with the config's
``seed`` and shared by the rows of the batch: the sampled chunk is a deterministic function of the
row's own inputs and the seed, whatever the batch size, the row's slot, the calls before or the
copy (pickled evaluation worker, reloaded state dict) that runs it. So a sharded evaluation
reproduces a single process's rollouts, and the policy acts as a fixed map from observation window
to chunk (one draw of the sampler's noise, not fresh noise at every step; change ``seed`` for
another draw). Nothing about sampling is held as state.

Training goes through :class:`~tar_rl.policies.chunking.ChunkLoss`, inference through
:class:`~tar_rl.policies.chunking.ChunkedActor` (ACT's temporal ensemble or open-loop chunks); the
models provide ``chunk_loss`` (:class:`OctoHead`) and ``predict_chunk``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from .attention import attend, broadcast_attention, compile_once, use_compiled
from .base import DataInfo, Policy, PolicySpec, register_policy
from .chunking import ChunkedHeadConfig, chunked_policy
from .common import PROPRIO_DIMS, ObsNorm, TaskEncoder, image_encoder

__all__ = [
    "OctoBackbone",
    "OctoConfig",
    "OctoHead",
    "OctoLinear",
    "OctoLinearConfig",
    "SeededSampling",
    "TransformerBlock",
    "check_chunk_shape",
    "hold_last_valid",
    "sinusoidal_embedding",
]


# -- Configs ------------------------------------------------------------------------------------


@dataclass
class OctoConfig(ChunkedHeadConfig):
    """Settings shared by every head on the Octo-style backbone (``octo_linear``, ``octo_diffusion``, ``flow``).

    Besides the chunked heads' settings (:class:`~tar_rl.policies.chunking.ChunkedHeadConfig`):

    Attributes:
        dim: token width of the backbone.
        heads: attention heads (``dim`` must be divisible by it).
        layers: transformer blocks.
        readouts: learned readout tokens (mean-pooled into the features).
        dropout: dropout rate in attention and in the blocks' residual branches.
    """

    name: str = "octo"
    dim: int = 64
    heads: int = 4
    layers: int = 2
    readouts: int = 2
    dropout: float = 0.0


@dataclass
class OctoLinearConfig(OctoConfig):
    """``octo_linear``: the backbone's features -> a linear map -> the chunk ``[H, A]``; MSE per element."""

    name: str = "octo_linear"


def check_backbone_config(cfg: OctoConfig) -> None:
    """Raise ``ValueError`` naming the setting for a bad backbone setting."""
    for field in ("dim", "heads", "layers", "readouts"):
        if int(getattr(cfg, field)) < 1:
            raise ValueError(f"policy.{field} must be >= 1, got {getattr(cfg, field)}")
    if cfg.dim % cfg.heads:
        raise ValueError(f"policy.dim ({cfg.dim}) must be divisible by policy.heads ({cfg.heads})")
    if not (math.isfinite(cfg.dropout) and 0.0 <= cfg.dropout < 1.0):
        raise ValueError(f"policy.dropout must lie in [0, 1), got {cfg.dropout}")


# -- The backbone ---------------------------------------------------------------------------------


class TransformerBlock(nn.Module):
    """Pre-norm transformer block: masked multi-head self-attention and a GELU MLP (4x wide).

    ``forward(x [N, S, dim], bias, last=None) -> [N, S, dim]``: ``bias`` ``[N, 1, S, S]`` or ``[S, S]``
    float (0: may attend, ``-inf``: may not) or ``None``; ``last``: return the outputs of the last
    ``last`` tokens only, ``[N, last, dim]`` (every token still serves as a key and a value; a stack's
    last block computes only the outputs that are read). With ``compiled``, a training step on the
    CPU runs the whole block compiled (:mod:`tar_rl.policies.attention`).
    """

    def __init__(self, dim: int, heads: int, dropout: float = 0.0, compiled: bool = False):
        super().__init__()
        self.heads, self.dropout, self.compiled = heads, dropout, compiled
        self.norm1 = nn.LayerNorm(dim)
        self.qkv = nn.Linear(dim, 3 * dim)
        self.proj = nn.Linear(dim, dim)
        self.norm2 = nn.LayerNorm(dim)
        self.mlp = nn.Sequential(nn.Linear(dim, 4 * dim), nn.GELU(), nn.Linear(4 * dim, dim))
        self.drop = nn.Dropout(dropout)

    def forward(self, x: torch.Tensor, bias: torch.Tensor | None = None, last: int | None = None) -> torch.Tensor:
        p = self.dropout if self.training else 0.0
        if use_compiled(self.compiled, x, p):
            return compile_once(_block)(self, x, bias, last, broadcast_attention)
        return _block(self, x, bias, last, lambda q, k, v, b: attend(q, k, v, b, dropout=p))


def _block(block: TransformerBlock, x: torch.Tensor, bias, last: int | None, attention) -> torch.Tensor:
    """The computation of :class:`TransformerBlock`, ``attention(q, k, v, bias)`` computing the attention."""
    n, s, d = x.shape
    h, w, b = block.heads, block.qkv.weight, block.qkv.bias
    y = block.norm1(x)
    if last is None:
        q, k, v = F.linear(y, w, b).view(n, s, 3, h, d // h).permute(2, 0, 3, 1, 4)
    else:
        x, s = x[:, -last:], last
        q = F.linear(y[:, -last:], w[:d], b[:d]).view(n, s, h, d // h).transpose(1, 2)
        k, v = F.linear(y, w[d:], b[d:]).view(n, -1, 2, h, d // h).permute(2, 0, 3, 1, 4)
        bias = None if bias is None else bias[..., -last:, :]
    x = x + block.drop(block.proj(attention(q, k, v, bias).transpose(1, 2).reshape(n, s, d)))
    return x + block.drop(block.mlp(block.norm2(x)))


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
        self.blocks = nn.ModuleList(
            TransformerBlock(self.dim, int(cfg.heads), cfg.dropout, bool(cfg.compile)) for _ in range(cfg.layers)
        )
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
        allowed = self.block_mask[None] & keys[:, None, :]  # [N, S, S]
        # an additive bias: on CPU, attention with a float mask is about twice as fast as with a bool one here
        bias = torch.zeros(allowed.shape, dtype=x.dtype, device=x.device).masked_fill_(~allowed, float("-inf"))
        for i, block in enumerate(self.blocks):
            # only the readout tokens' outputs are read after the last block
            x = block(x, bias[:, None], last=r if i == len(self.blocks) - 1 else None)
        features = self.out_norm(x.mean(1))
        return features.reshape(*lead, self.dim)


# -- What the heads on the backbone share ---------------------------------------------------------


def check_chunk_shape(chunk: torch.Tensor, horizon: int, action_dim: int) -> None:
    """Raise ``ValueError`` unless ``chunk``'s event shape is ``[horizon, action_dim]``."""
    if chunk.shape[-2:] != (horizon, action_dim):
        raise ValueError(
            f"action_chunk has event shape {list(chunk.shape[-2:])}, the policy predicts [{horizon}, {action_dim}] "
            "(data.chunk_horizon must match the one the policy was built with)"
        )


def hold_last_valid(chunk: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """``chunk [..., H, A]`` with every entry past the last valid one (``valid [..., H]``, a prefix of
    True) replaced by the last valid action; a chunk with no valid entry keeps its first one throughout."""
    last = (valid.long().sum(-1, keepdim=True) - 1).clamp_min(0)  # [..., 1]
    held = chunk.gather(-2, last[..., None].expand(*last.shape, chunk.shape[-1]))  # [..., 1, A]
    return torch.where(valid[..., None].bool(), chunk, held)


class OctoHead(nn.Module):
    """Base of the heads on the backbone: ``horizon``, ``action_dim``, the ``backbone``, and the chunk loss's inputs.

    A head adds ``step_loss(history, history_valid, task_id, chunk, pixels=None) -> [*B, H, A]``
    and ``predict_chunk``. :meth:`chunk_loss` (what :class:`~tar_rl.policies.chunking.ChunkLoss`
    calls) sets padded chunk entries (``action_chunk_valid`` False) to the chunk's last valid action
    before ``step_loss`` sees the chunk (the dataset's own convention past an episode's end), so that
    whatever they hold cannot reach the valid entries' losses through heads that read the whole
    noisy chunk (the diffusion denoiser, the flow action expert). Their losses are left in the
    output: ``TARLoss`` averages over the valid chunk entries.
    """

    loss_inputs = (
        "observation_history",
        "observation_history_valid",
        "task_id",
        "action_chunk",
        "action_chunk_valid",
    )
    loss_extras: tuple[str, ...] = ()

    def __init__(self, cfg: OctoConfig, info: DataInfo):
        super().__init__()
        cfg.check_chunking(info.chunk_horizon)
        self.horizon, self.action_dim = int(info.chunk_horizon), int(info.action_dim)
        self.backbone = OctoBackbone(cfg, info)

    @property
    def reads_pixels(self) -> bool:
        """True with image observations: the model needs ``pixels``."""
        return self.backbone.reads_pixels

    def chunk_loss(
        self,
        observation_history: torch.Tensor,
        observation_history_valid: torch.Tensor,
        task_id: torch.Tensor,
        action_chunk: torch.Tensor,
        action_chunk_valid: torch.Tensor | None = None,
        pixels: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, dict]:
        """``step_loss`` on the chunk with its padded entries held at the last valid action; no extras."""
        if action_chunk_valid is not None:
            action_chunk = hold_last_valid(action_chunk, action_chunk_valid)
        images = {"pixels": pixels} if self.reads_pixels else {}
        loss = self.step_loss(observation_history, observation_history_valid, task_id, action_chunk, **images)
        return loss, {}


class SeededSampling(OctoHead):
    """Base of the heads that sample at inference: a fresh generator seeded with ``cfg.seed`` per call.

    No generator is kept on the module (a ``torch.Generator`` does not pickle, and a kept one would
    make the actions depend on the calls before): :meth:`predict_chunk` makes a new one each call,
    draws one ``[1, H, A]`` standard normal sample shared by the ``N`` rows, and hands both to the
    head's ``sample(noise [N, H, A], features [N, dim], generator) -> [N, H, A]``; the result is
    clipped to ``[-1, 1]``.
    """

    def __init__(self, cfg: OctoConfig, info: DataInfo):
        super().__init__(cfg, info)
        self.seed = int(cfg.seed)

    @torch.no_grad()
    def predict_chunk(self, history, history_valid, task_id, pixels=None) -> torch.Tensor:
        features = self.backbone(history, history_valid, task_id, pixels)
        n, shape = features.shape[0], (self.horizon, self.action_dim)
        generator = torch.Generator(device=features.device).manual_seed(self.seed)
        noise = torch.randn((1, *shape), generator=generator, device=features.device).expand(n, *shape)
        return self.sample(noise, features, generator).clamp(-1.0, 1.0)


def sinusoidal_embedding(t: torch.Tensor, dim: int, max_period: float = 10_000.0) -> torch.Tensor:
    """``[..., dim]`` sine and cosine features of ``t`` (``[...]``, any real values), ``dim`` even."""
    half = dim // 2
    freqs = torch.exp(-math.log(max_period) * torch.arange(half, device=t.device, dtype=torch.float32) / half)
    angles = t.to(torch.float32)[..., None] * freqs
    return torch.cat([torch.sin(angles), torch.cos(angles)], dim=-1)


# -- octo_linear ---------------------------------------------------------------------------------


class OctoLinear(OctoHead):
    """Backbone features -> a linear map -> the chunk ``[..., H, A]``; per-step loss the squared error per element."""

    def __init__(self, cfg: OctoConfig, info: DataInfo):
        super().__init__(cfg, info)
        self.head = nn.Linear(int(cfg.dim), self.horizon * self.action_dim)

    def forward(self, history, history_valid, task_id, pixels=None) -> torch.Tensor:
        features = self.backbone(history, history_valid, task_id, pixels)
        return self.head(features).unflatten(-1, (self.horizon, self.action_dim))

    def step_loss(self, history, history_valid, task_id, chunk, pixels=None) -> torch.Tensor:
        """``[B, L, H, A]`` squared errors of the predicted chunk."""
        check_chunk_shape(chunk, self.horizon, self.action_dim)
        return (self(history, history_valid, task_id, pixels).float() - chunk.float()).square()

    def predict_chunk(self, history, history_valid, task_id, pixels=None) -> torch.Tensor:
        return self(history, history_valid, task_id, pixels)


def _build_linear(cfg: OctoLinearConfig, info: DataInfo) -> Policy:
    return chunked_policy(OctoLinear(cfg, info), cfg, info, "loss_octo_linear", history=info.history)


register_policy(
    PolicySpec(
        "octo_linear",
        OctoLinearConfig,
        _build_linear,
        "Octo-style transformer (task, observation window, readouts) with a linear chunk head, MSE",
    )
)
