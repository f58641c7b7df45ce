"""The ``mlp`` head: a regression MLP on the current observation and task, per-step MSE."""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import torch
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.objectives import BCLoss

from .base import DataInfo, Policy, PolicySpec, register_policy
from .common import PROPRIO_DIMS, ObsNorm, TaskEncoder, image_encoder

__all__ = ["MLPConfig", "MLPPolicy"]


@dataclass
class MLPConfig:
    """The regression MLP head: normalised observation (+ task) -> action.

    Attributes:
        name: registry name.
        hidden: hidden layer widths.
        task_conditioning: ``embedding`` (learned, ``task_dim`` wide), ``instruction`` (the task's
            instruction sentence as a learned bag of words, ``task_dim`` wide, see
            :mod:`tar_rl.policies.common`), ``onehot`` or ``none``.
        task_dim: width of the learned task embedding.
        normalize_obs: standardise observations with the training data's statistics.
        observation: ``state`` (the 39-d state vector) or ``image`` (the camera image through a
            conv encoder, plus the proprioceptive state: :mod:`tar_rl.policies.common`; needs a
            dataset with images, ``data.image_size > 0``).
        image_dim: width of the image features.
    """

    name: str = "mlp"
    hidden: list[int] = field(default_factory=lambda: [256, 256, 256])
    task_conditioning: str = "embedding"
    task_dim: int = 32
    normalize_obs: bool = True
    observation: str = "state"
    image_dim: int = 64


_TASK_CONDITIONING = ("embedding", "instruction", "onehot", "none")


class MLPPolicy(nn.Module):
    """Plain tensor module: ``(observation [..., D], task_id [...]) -> action [..., A]``.

    Works on any leading shape (``[N]`` at inference, ``[B, L]`` in training), step by step:
    nothing mixes the time axis. With ``observation="image"`` it also takes ``pixels [..., 3, S, S]``.
    """

    def __init__(self, cfg: MLPConfig, info: DataInfo):
        super().__init__()
        if cfg.task_conditioning not in _TASK_CONDITIONING:
            raise ValueError(
                f"policy.task_conditioning must be one of {list(_TASK_CONDITIONING)}, got {cfg.task_conditioning!r}"
            )
        if not cfg.hidden or any(int(h) < 1 for h in cfg.hidden):
            raise ValueError(f"policy.hidden must be a non-empty list of positive widths, got {list(cfg.hidden)}")
        if cfg.task_conditioning in ("embedding", "instruction") and cfg.task_dim < 1:
            raise ValueError(f"policy.task_dim must be >= 1, got {cfg.task_dim}")
        self.conditioning = cfg.task_conditioning
        self.n_tasks = info.n_tasks
        self.image = image_encoder(cfg.observation, info.image_size, cfg.image_dim)
        if cfg.normalize_obs:
            self.norm = ObsNorm(info.obs_dim, info.obs_mean, info.obs_std)
        else:
            self.norm = nn.Identity()
        task_width = {"embedding": cfg.task_dim, "instruction": cfg.task_dim, "onehot": info.n_tasks, "none": 0}
        task_width = task_width[self.conditioning]
        self.task_embedding = None
        if self.conditioning in ("embedding", "instruction"):
            self.task_embedding = TaskEncoder(self.conditioning, info.n_tasks, cfg.task_dim, info.instructions)
        layers: list[nn.Module] = []
        state_width = PROPRIO_DIMS + cfg.image_dim if self.image is not None else info.obs_dim
        width = state_width + task_width
        for h in cfg.hidden:
            layers += [nn.Linear(width, int(h)), nn.ReLU()]
            width = int(h)
        layers.append(nn.Linear(width, info.action_dim))
        self.net = nn.Sequential(*layers)

    def forward(self, observation: torch.Tensor, task_id: torch.Tensor, pixels: torch.Tensor | None = None):
        x = self.norm(observation)
        if self.image is not None:
            x = torch.cat([x[..., :PROPRIO_DIMS], self.image(pixels)], dim=-1)
        if self.task_embedding is not None:
            x = torch.cat([x, self.task_embedding(task_id)], dim=-1)
        elif self.conditioning == "onehot":
            x = torch.cat([x, nn.functional.one_hot(task_id, self.n_tasks).to(x.dtype)], dim=-1)
        return self.net(x)


def _build_mlp(cfg: MLPConfig, info: DataInfo) -> Policy:
    in_keys = ["observation", "task_id"] + (["pixels"] if cfg.observation == "image" else [])
    actor = TensorDictModule(MLPPolicy(cfg, info), in_keys=in_keys, out_keys=["action"])
    # BCLoss with reduction="none" keeps [B, L, A]; TARLoss averages the action dim per step.
    with warnings.catch_warnings():  # torchrl 0.14.1's BCLoss warns about its own annotations
        warnings.filterwarnings("ignore", "The name target_actor_network_params", UserWarning)
        loss = BCLoss(actor, loss_function="mse", reduction="none")
    return Policy(actor=actor, loss=loss, keys=(*in_keys, "action"))


register_policy(PolicySpec("mlp", MLPConfig, _build_mlp, "regression MLP on the current observation and task, MSE"))
