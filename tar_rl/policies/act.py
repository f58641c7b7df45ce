"""The ``act`` head: ACT-style action chunking with a CVAE (Zhao et al. 2023).

The model (:class:`ACTModel`) predicts the next ``H`` actions from the current (normalised)
observation and the task:

* **CVAE encoder** (training only): a transformer encoder over ``[CLS, obs, a_0 .. a_{H-1}]``
  (the expert chunk's padded entries, past the episode's end, are masked out of the attention)
  gives the mean and log-variance of a ``latent_dim`` style variable ``z`` from the CLS output;
  ``z`` is drawn with the reparameterisation trick.
* **Encoder-decoder**: a transformer encoder over three tokens ``[z, obs, task]`` (learned
  positions), then a transformer decoder whose ``H`` learned query embeddings cross-attend to
  the encoded tokens; a linear layer maps each query's output to an action: ``[H, A]``.
* **Image observations** (``observation="image"``, :mod:`tar_rl.policies.common`): the state
  tokens carry the proprioceptive state only and the encoder reads a fourth token, the current
  camera image through the conv encoder (ACT reads camera features as tokens too); the CVAE
  encoder sees the proprioceptive state and the actions, as in ACT, not the image.
* **Inference**: ``z`` is the prior mean, zero; the CVAE encoder is not run, so the chunk is a
  deterministic function of the observation and the task (in ``eval()`` mode, without dropout).

The loss (:meth:`ACTModel.chunk_loss`, through :class:`~tar_rl.policies.chunking.ChunkLoss`) returns

* ``loss_chunk``: the L1 error of every chunk element, ``[*B, H, A]``, zero where the chunk entry
  is padding (``action_chunk_valid`` False). With ``Policy.event_valid = "action_chunk_valid"``,
  ``TARLoss`` turns it into the per-step loss: the mean over the step's valid chunk entries and
  the action dims (paper Sec. II-D: a chunk's loss is one step's loss);
* ``loss_kl``: a scalar, ``kl_weight`` times the mean over the valid steps (``("collector",
  "mask")`` True) of ``KL(q(z | a, o) || N(0, I))`` summed over the latent dims; ``TARLoss`` adds
  it unweighted (``aux_loss_kl``); and ``kl``, the unweighted mean KL, detached (a diagnostic).

Written here rather than reusing ``torchrl.objectives.ACTLoss``: with ``reduction="none"`` torchrl's
loss averages each chunk over all its entries (padding past the episode's end included), returns
the per-sample KL inside the main loss entry and ignores the validity mask; TAR needs the chunk loss
per element with its padding left to ``TARLoss``'s ``event_valid`` average, and the KL term kept out
of the per-step weighting.

Inference goes through :class:`tar_rl.policies.chunking.ChunkedActor` (temporal ensembling by
default, or open-loop execution of the chunk's first ``execute_steps`` actions).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

from .attention import key_padding_bias, multihead
from .base import DataInfo, Policy, PolicySpec, register_policy
from .chunking import ChunkedHeadConfig, chunked_policy
from .common import PROPRIO_DIMS, ObsNorm, TaskEncoder, image_encoder

__all__ = ["ACTConfig", "ACTModel", "gaussian_kl"]


@dataclass
class ACTConfig(ChunkedHeadConfig):
    """The ACT head: a CVAE transformer predicting chunks of ``data.chunk_horizon`` actions.

    The defaults keep ACT's structure at a size that trains on CPU: a step on ``[64, 16]``
    segments runs every transformer over ``64 * 16 = 1024`` samples (``H + 2`` CVAE tokens, 3
    encoder tokens and ``H`` decoder queries each), so width and depth set the cost directly.
    ACT itself uses width 512, 8 heads, 4 CVAE and 4 encoder layers, 7 decoder layers of which
    its code uses only the first (LeRobot's ACT config, after tonyzhaozh/act issue 25), latent
    32, dropout 0.1, KL weight 10. Measured here (torch 2.13 CPU, one thread, shared 2-core
    machine): a step of the defaults on ``[64, 16]`` segments takes about 10 times the MLP head's.

    Besides the chunked heads' settings (:class:`~tar_rl.policies.chunking.ChunkedHeadConfig`):

    Attributes:
        dim: width of every token (transformer model dimension); divisible by ``heads``.
        heads: attention heads per layer.
        enc_layers: layers of the encoder over ``[z, obs, task]``.
        dec_layers: layers of the decoder over the ``H`` chunk queries.
        cvae_layers: layers of the CVAE encoder over ``[CLS, obs, action chunk]`` (training only).
        ffn_dim: width of each layer's feed-forward block (ACT: ``4 * dim``).
        latent_dim: size of the CVAE style latent ``z``.
        kl_weight: weight of the KL term (``loss_kl``), ACT's beta.
        dropout: dropout in the transformer layers (training only). ACT uses 0.1; the default
            is 0 because on CPU drawing the dropout masks took about 30% of a training step.
    """

    name: str = "act"
    dim: int = 64
    heads: int = 2
    enc_layers: int = 1
    dec_layers: int = 1
    cvae_layers: int = 1
    ffn_dim: int = 128
    latent_dim: int = 16
    kl_weight: float = 10.0
    dropout: float = 0.0


def _check_config(cfg: ACTConfig, info: DataInfo) -> None:
    for name in ("dim", "heads", "enc_layers", "dec_layers", "cvae_layers", "ffn_dim", "latent_dim"):
        value = getattr(cfg, name)
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ValueError(f"policy.{name} must be a positive integer, got {value!r}")
    if cfg.dim % cfg.heads:
        raise ValueError(f"policy.dim ({cfg.dim}) must be divisible by policy.heads ({cfg.heads})")
    if not (math.isfinite(cfg.kl_weight) and cfg.kl_weight >= 0):
        raise ValueError(f"policy.kl_weight must be a finite number >= 0, got {cfg.kl_weight!r}")
    if not 0 <= cfg.dropout < 1:
        raise ValueError(f"policy.dropout must lie in [0, 1), got {cfg.dropout!r}")
    if info.chunk_horizon < 1:
        raise ValueError(f"the chunk horizon (data.chunk_horizon) must be >= 1, got {info.chunk_horizon}")
    cfg.check_chunking(info.chunk_horizon)


def gaussian_kl(mu: torch.Tensor, logvar: torch.Tensor) -> torch.Tensor:
    """``KL(N(mu, exp(logvar)) || N(0, I))`` summed over the last dim: ``[..., Z] -> [...]``.

    Per dimension ``0.5 * (mu^2 + exp(logvar) - 1 - logvar)``.
    """
    return 0.5 * (mu.square() + logvar.exp() - 1.0 - logvar).sum(-1)


class ACTModel(nn.Module):
    """The ACT network (module docstring): plain tensors in and out.

    Args:
        cfg: the head's settings.
        info: the data's dimensions, chunk horizon ``H`` and observation statistics.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from tar_rl.policies import DataInfo
        >>> from tar_rl.policies.chunking import ChunkLoss
        >>> model = ACTModel(ACTConfig(dim=16, heads=2), DataInfo(obs_dim=5, action_dim=2, n_tasks=3, chunk_horizon=4))
        >>> data = TensorDict({"observation": torch.randn(2, 6, 5), "task_id": torch.zeros(2, 6, dtype=torch.long),
        ...     "action_chunk": torch.zeros(2, 6, 4, 2), "action_chunk_valid": torch.ones(2, 6, 4, dtype=torch.bool)},
        ...     [2, 6])
        >>> out = ChunkLoss(model)(data)
        >>> out["loss_chunk"].shape, out["loss_kl"].shape
        (torch.Size([2, 6, 4, 2]), torch.Size([]))
    """

    # what ChunkLoss passes to chunk_loss, and the scalars it returns besides the chunk loss
    loss_inputs = ("observation", "task_id", "action_chunk", "action_chunk_valid", "valid")
    loss_extras = ("loss_kl", "kl")

    def __init__(self, cfg: ACTConfig, info: DataInfo):
        super().__init__()
        _check_config(cfg, info)
        d, self.horizon, self.action_dim = cfg.dim, int(info.chunk_horizon), info.action_dim
        self.latent_dim = cfg.latent_dim
        self.kl_weight = float(cfg.kl_weight)
        self.compiled = bool(cfg.compile)
        self.norm = ObsNorm(info.obs_dim, info.obs_mean, info.obs_std) if cfg.normalize_obs else nn.Identity()
        self.image = image_encoder(cfg.observation, info.image_size, d)
        self.obs_width = PROPRIO_DIMS if self.image is not None else info.obs_dim

        def layers(kind: type, n: int) -> nn.Module:
            layer = kind(d, cfg.heads, cfg.ffn_dim, cfg.dropout, batch_first=True, norm_first=True)
            if kind is nn.TransformerEncoderLayer:
                return nn.TransformerEncoder(layer, n, norm=nn.LayerNorm(d), enable_nested_tensor=False)
            return nn.TransformerDecoder(layer, n, norm=nn.LayerNorm(d))

        # CVAE posterior q(z | obs, chunk)
        self.cvae_cls = nn.Parameter(torch.randn(d) * 0.02)
        self.cvae_obs = nn.Linear(self.obs_width, d)
        self.cvae_action = nn.Linear(info.action_dim, d)
        self.cvae_pos = nn.Parameter(torch.randn(2 + self.horizon, d) * 0.02)
        self.cvae_encoder = layers(nn.TransformerEncoderLayer, cfg.cvae_layers)
        self.cvae_out = nn.Linear(d, 2 * cfg.latent_dim)
        # Policy: [z, obs, task (, image)] -> encoder -> H queries -> decoder -> actions
        self.latent_in = nn.Linear(cfg.latent_dim, d)
        self.obs_in = nn.Linear(self.obs_width, d)
        self.task = TaskEncoder(cfg.task_conditioning, info.n_tasks, d, info.instructions)
        self.token_pos = nn.Parameter(torch.randn(3 + int(self.image is not None), d) * 0.02)
        self.encoder = layers(nn.TransformerEncoderLayer, cfg.enc_layers)
        self.queries = nn.Parameter(torch.randn(self.horizon, d) * 0.02)
        self.decoder = layers(nn.TransformerDecoderLayer, cfg.dec_layers)
        self.head = nn.Linear(d, info.action_dim)

    def posterior(
        self, obs: torch.Tensor, chunk: torch.Tensor, chunk_valid: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean and log-variance of ``q(z | obs, chunk)``.

        Args:
            obs: ``[N, D]`` normalised observations (the proprioceptive part with images).
            chunk: ``[N, H, A]`` expert action chunks.
            chunk_valid: ``[N, H]`` bool, True on real chunk entries (the others are not attended to).

        Returns:
            ``mu``, ``logvar``: ``[N, Z]`` each.
        """
        n = obs.shape[0]
        tokens = torch.cat(
            [self.cvae_cls.expand(n, 1, -1), self.cvae_obs(obs)[:, None], self.cvae_action(chunk)], dim=1
        )
        tokens = tokens + self.cvae_pos
        keep = torch.ones(n, 2, dtype=torch.bool, device=obs.device)
        ignore = ~torch.cat([keep, chunk_valid], dim=1)  # [N, 2 + H], True: not attended to
        out = self._encode(self.cvae_encoder, tokens, key_padding_bias(ignore, tokens.dtype))
        mu, logvar = self.cvae_out(out[:, 0]).chunk(2, dim=-1)
        return mu, logvar

    @property
    def reads_pixels(self) -> bool:
        """True with image observations: the model needs ``pixels``."""
        return self.image is not None

    def _state(self, observation: torch.Tensor) -> torch.Tensor:
        """Normalised observations ``[N, D]`` -> what the model reads of them (proprioception with images)."""
        return self.norm(observation)[..., : self.obs_width]

    def decode(
        self, obs: torch.Tensor, task_id: torch.Tensor, z: torch.Tensor, pixels: torch.Tensor | None = None
    ) -> torch.Tensor:
        """The chunk ``[N, H, A]`` from the state read ``[N, D']``, task ids ``[N]``, latents ``[N, Z]``
        and, with image observations, ``pixels [N, 3, S, S]``."""
        n = obs.shape[0]
        tokens = [self.latent_in(z), self.obs_in(obs), self.task(task_id)]
        if self.image is not None:
            tokens.append(self.image(pixels).reshape(n, -1))
        tokens = torch.stack(tokens, dim=1) + self.token_pos
        memory = self._encode(self.encoder, tokens)
        return self.head(self._decode(memory))

    # The transformer stacks are nn.TransformerEncoder / nn.TransformerDecoder modules (their
    # parameters, initialisation and state-dict names), run by the two methods below: the same
    # pre-norm computation as the modules' own forward, with the attention through
    # tar_rl.policies.attention, and the first decoder layer's self-attention over the learned
    # queries (the same for every sample) computed once and broadcast over the batch.

    def _encode(self, stack: nn.TransformerEncoder, x: torch.Tensor, bias: torch.Tensor | None = None) -> torch.Tensor:
        """``stack(x, src_key_padding_mask=...)`` for a pre-norm encoder, ``bias`` the additive key padding bias."""
        for layer in stack.layers:
            x = x + layer.dropout1(multihead(layer.self_attn, layer.norm1(x), bias=bias, compiled=self.compiled))
            x = x + _feed_forward(layer, layer.norm2(x))
        return stack.norm(x)

    def _decode(self, memory: torch.Tensor) -> torch.Tensor:
        """``decoder(queries.expand(N, -1, -1), memory)`` for the pre-norm decoder: ``[N, H, dim]``."""
        n = memory.shape[0]
        x = self.queries[None]
        for i, layer in enumerate(self.decoder.layers):
            if i == 0 and not (self.training and layer.dropout1.p > 0):
                # the queries are one tensor for every sample: their self-attention is too
                x = (x + multihead(layer.self_attn, layer.norm1(x), compiled=self.compiled)).expand(n, -1, -1)
            else:
                x = x.expand(n, -1, -1)
                x = x + layer.dropout1(multihead(layer.self_attn, layer.norm1(x), compiled=self.compiled))
            x = x + layer.dropout2(multihead(layer.multihead_attn, layer.norm2(x), memory, compiled=self.compiled))
            x = x + _feed_forward(layer, layer.norm3(x), third=True)
        return self.decoder.norm(x)

    def forward(
        self,
        observation: torch.Tensor,
        task_id: torch.Tensor,
        action_chunk: torch.Tensor,
        action_chunk_valid: torch.Tensor,
        pixels: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Training pass: posterior, a reparameterised sample of ``z``, the predicted chunk.

        In ``eval()`` mode ``z`` is the posterior mean instead of a sample, so that a loss computed
        for inspection (the recipe's per-step loss along demonstrations) is deterministic and draws
        no random numbers.

        Args:
            observation: ``[*B, D]`` raw observations.
            task_id: ``[*B]`` int64.
            action_chunk: ``[*B, H, A]`` expert chunks.
            action_chunk_valid: ``[*B, H]`` bool, True on real chunk entries.
            pixels: ``[*B, 3, S, S]`` uint8 camera images (image observations only).

        Returns:
            ``chunk`` ``[*B, H, A]``, ``mu`` and ``logvar`` ``[*B, Z]``.
        """
        batch = observation.shape[:-1]
        obs = self._state(observation.reshape(-1, observation.shape[-1]))
        chunk = action_chunk.reshape(-1, self.horizon, action_chunk.shape[-1])
        mu, logvar = self.posterior(obs, chunk, action_chunk_valid.reshape(-1, self.horizon))
        z = mu + torch.randn_like(mu) * (0.5 * logvar).exp() if self.training else mu
        pred = self.decode(obs, task_id.reshape(-1), z, pixels)
        return (
            pred.reshape(*batch, self.horizon, self.action_dim),
            mu.reshape(*batch, self.latent_dim),
            logvar.reshape(*batch, self.latent_dim),
        )

    def chunk_loss(
        self,
        observation: torch.Tensor,
        task_id: torch.Tensor,
        action_chunk: torch.Tensor,
        action_chunk_valid: torch.Tensor | None = None,
        valid: torch.Tensor | None = None,
        pixels: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """ACT's training loss, unreduced over the batch (module docstring).

        Args:
            observation, task_id, action_chunk, pixels: as in :meth:`forward`; the chunk is the
                target and the CVAE encoder's input.
            action_chunk_valid: ``[*B, H]`` bool, True on real chunk entries (``None``: all).
            valid: ``[*B]`` bool, True on real steps, the KL mean's mask (``None``: every step).

        Returns:
            ``|pred - target|`` ``[*B, H, A]`` (0 on padded chunk entries) and the scalars
            ``loss_kl`` (``kl_weight`` times the mean KL over valid steps) and ``kl`` (the
            unweighted mean KL, detached).
        """
        batch = action_chunk.shape[:-2]
        device = action_chunk.device
        if action_chunk_valid is None:
            action_chunk_valid = torch.ones(action_chunk.shape[:-1], dtype=torch.bool, device=device)
        valid = torch.ones(batch, dtype=torch.bool, device=device) if valid is None else valid.reshape(batch)
        pred, mu, logvar = self(observation, task_id, action_chunk, action_chunk_valid, pixels)
        error = (pred.float() - action_chunk.float()).abs()
        error = torch.where(
            action_chunk_valid[..., None], error, torch.zeros((), dtype=error.dtype, device=error.device)
        )
        kl = gaussian_kl(mu.float(), logvar.float())
        kl = torch.where(valid, kl, torch.zeros((), dtype=kl.dtype, device=kl.device)).sum() / valid.sum().clamp_min(1)
        return error, {"loss_kl": self.kl_weight * kl, "kl": kl.detach()}

    def predict_chunk(
        self,
        history: torch.Tensor,
        history_valid: torch.Tensor,
        task_id: torch.Tensor,
        pixels: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Inference: the chunk ``[N, H, A]`` at ``z = 0`` from the current observation ``history[:, -1]``.

        Args:
            history: ``[N, K, D]`` observation window, oldest first (only the last entry is read).
            history_valid: ``[N, K]`` bool (unused: the current observation is always real).
            task_id: ``[N]`` int64.
            pixels: ``[N, 3, S, S]`` uint8, the current images (image observations only).
        """
        obs = self._state(history[:, -1])
        z = obs.new_zeros(obs.shape[0], self.latent_dim)
        return self.decode(obs, task_id, z, pixels)


def _feed_forward(layer: nn.Module, x: torch.Tensor, third: bool = False) -> torch.Tensor:
    """A transformer layer's feed-forward branch ``linear2(dropout(activation(linear1(x))))`` and its output dropout."""
    out = layer.linear2(layer.dropout(layer.activation(layer.linear1(x))))
    return (layer.dropout3 if third else layer.dropout2)(out)


def _build_act(cfg: ACTConfig, info: DataInfo) -> Policy:
    # ACT reads the current observation only: a window of one
    return chunked_policy(ACTModel(cfg, info), cfg, info, "loss_chunk", history=1)


register_policy(
    PolicySpec(
        "act",
        ACTConfig,
        _build_act,
        "ACT: CVAE transformer predicting action chunks (L1 + KL), temporal ensembling at inference",
    )
)
