"""Policy heads, chosen by name from a small registry.

A head gives the recipe two things (:class:`Policy`):

* ``actor``: a ``TensorDictModule`` for inference, reading ``observation`` (``[..., 39]``) and
  ``task_id`` (int64, the index in ``tar_rl.collectors.tasks.TASKS``) and writing ``action``
  (``[..., 4]``). The evaluator collectors call it on ``[N]`` batches; it must be picklable.
* ``loss``: a TorchRL ``LossModule`` built with ``reduction="none"`` whose one ``loss_*`` output is
  the per-step loss ``[B, L]`` or ``[B, L, ...]`` on a ``[B, L]`` segment batch. Heads never
  average over the segment axis: ``tar_rl.TARLoss`` owns that reduction.

Every head is registered in :data:`POLICIES` with its config dataclass (the fields a recipe may
set, with defaults) and its builder ``build(config, info) -> Policy``. ``info``
(:class:`DataInfo`) carries what a head needs from the dataset: dimensions and normalisation
statistics. The statistics are stored as buffers of the network, so a checkpoint's state dict
restores them.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import torch
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.objectives import BCLoss, LossModule

from tar_rl.collectors.tasks import TASKS

__all__ = ["POLICIES", "DataInfo", "MLPConfig", "MLPPolicy", "Policy", "PolicySpec", "build_policy"]


@dataclass(frozen=True)
class DataInfo:
    """What a head needs to know about the data.

    Attributes:
        obs_dim: observation size (39 for MetaWorld).
        action_dim: action size (4).
        n_tasks: number of task ids (``len(TASKS)``: ids are global, so a policy trained on a few
            tasks is evaluated with the same ids).
        obs_mean, obs_std: per-dimension observation statistics of the training data.
        chunk_horizon: the dataset's ``action_chunk`` horizon ``H``.
    """

    obs_dim: int = 39
    action_dim: int = 4
    n_tasks: int = len(TASKS)
    obs_mean: tuple[float, ...] | None = None
    obs_std: tuple[float, ...] | None = None
    chunk_horizon: int = 1

    @classmethod
    def from_metadata(cls, metadata: dict) -> DataInfo:
        """Read the dimensions and observation statistics from a dataset's ``metadata.json``."""
        stats = metadata["stats"]["observation"]
        return cls(
            obs_dim=len(stats["mean"]),
            action_dim=len(metadata["stats"]["action"]["mean"]),
            obs_mean=tuple(stats["mean"]),
            obs_std=tuple(stats["std"]),
            chunk_horizon=int(metadata["chunk_horizon"]),
        )

    def to_dict(self) -> dict:
        """A JSON-serialisable copy (lists for tuples)."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict) -> DataInfo:
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()})


@dataclass
class Policy:
    """A built head.

    Attributes:
        actor: inference module (``observation``, ``task_id`` -> ``action``).
        loss: per-step training loss, ``reduction="none"``.
        keys: the dataset entries the loss reads (the sampler draws only these, plus the mask);
            ``None``: all.
        event_valid: for losses with event dims that may be padding (a chunk running past the
            episode's end), the bool mask entry over them, passed to ``TARLoss.set_keys(event_valid=...)``.
    """

    actor: TensorDictModule
    loss: LossModule
    keys: tuple | None = None
    event_valid: str | None = None


class _ObsNorm(nn.Module):
    """``(x - mean) / std`` with statistics held as buffers (std floored at 1e-3: some MetaWorld
    observation dims are constant within a task)."""

    def __init__(self, dim: int, mean=None, std=None, min_std: float = 1e-3):
        super().__init__()
        mean = torch.zeros(dim) if mean is None else torch.as_tensor(mean, dtype=torch.float32)
        std = torch.ones(dim) if std is None else torch.as_tensor(std, dtype=torch.float32)
        if mean.shape != (dim,) or std.shape != (dim,):
            raise ValueError(
                f"observation statistics must have shape ({dim},), got {tuple(mean.shape)}, {tuple(std.shape)}"
            )
        self.register_buffer("mean", mean.clone())
        self.register_buffer("std", std.clamp_min(min_std))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.mean) / self.std


@dataclass
class MLPConfig:
    """The regression MLP head: normalised observation (+ task) -> action.

    Attributes:
        name: registry name.
        hidden: hidden layer widths.
        task_conditioning: ``embedding`` (learned, ``task_dim`` wide), ``onehot`` or ``none``.
        task_dim: width of the learned task embedding.
        normalize_obs: standardise observations with the training data's statistics.
    """

    name: str = "mlp"
    hidden: list[int] = field(default_factory=lambda: [256, 256, 256])
    task_conditioning: str = "embedding"
    task_dim: int = 32
    normalize_obs: bool = True


_TASK_CONDITIONING = ("embedding", "onehot", "none")


class MLPPolicy(nn.Module):
    """Plain tensor module: ``(observation [..., D], task_id [...]) -> action [..., A]``.

    Works on any leading shape (``[N]`` at inference, ``[B, L]`` in training), step by step:
    nothing mixes the time axis.
    """

    def __init__(self, cfg: MLPConfig, info: DataInfo):
        super().__init__()
        if cfg.task_conditioning not in _TASK_CONDITIONING:
            raise ValueError(
                f"policy.task_conditioning must be one of {list(_TASK_CONDITIONING)}, got {cfg.task_conditioning!r}"
            )
        if not cfg.hidden or any(int(h) < 1 for h in cfg.hidden):
            raise ValueError(f"policy.hidden must be a non-empty list of positive widths, got {list(cfg.hidden)}")
        if cfg.task_conditioning == "embedding" and cfg.task_dim < 1:
            raise ValueError(f"policy.task_dim must be >= 1, got {cfg.task_dim}")
        self.conditioning = cfg.task_conditioning
        self.n_tasks = info.n_tasks
        if cfg.normalize_obs:
            self.norm = _ObsNorm(info.obs_dim, info.obs_mean, info.obs_std)
        else:
            self.norm = nn.Identity()
        task_width = {"embedding": cfg.task_dim, "onehot": info.n_tasks, "none": 0}[self.conditioning]
        self.task_embedding = nn.Embedding(info.n_tasks, cfg.task_dim) if self.conditioning == "embedding" else None
        layers: list[nn.Module] = []
        width = info.obs_dim + task_width
        for h in cfg.hidden:
            layers += [nn.Linear(width, int(h)), nn.ReLU()]
            width = int(h)
        layers.append(nn.Linear(width, info.action_dim))
        self.net = nn.Sequential(*layers)

    def forward(self, observation: torch.Tensor, task_id: torch.Tensor) -> torch.Tensor:
        x = self.norm(observation)
        if self.conditioning == "embedding":
            x = torch.cat([x, self.task_embedding(task_id)], dim=-1)
        elif self.conditioning == "onehot":
            x = torch.cat([x, nn.functional.one_hot(task_id, self.n_tasks).to(x.dtype)], dim=-1)
        return self.net(x)


def _build_mlp(cfg: MLPConfig, info: DataInfo) -> Policy:
    actor = TensorDictModule(MLPPolicy(cfg, info), in_keys=["observation", "task_id"], out_keys=["action"])
    # BCLoss with reduction="none" keeps [B, L, A]; TARLoss averages the action dim per step.
    with warnings.catch_warnings():  # torchrl 0.14.1's BCLoss warns about its own annotations
        warnings.filterwarnings("ignore", "The name target_actor_network_params", UserWarning)
        loss = BCLoss(actor, loss_function="mse", reduction="none")
    return Policy(actor=actor, loss=loss, keys=("observation", "task_id", "action"))


@dataclass(frozen=True)
class PolicySpec:
    """A registered head: its config dataclass and its builder."""

    name: str
    config: type
    build: Callable[[object, DataInfo], Policy]
    description: str = ""


POLICIES: dict[str, PolicySpec] = {
    "mlp": PolicySpec("mlp", MLPConfig, _build_mlp, "regression MLP on the current observation and task, MSE"),
}


def build_policy(cfg, info: DataInfo) -> Policy:
    """Build the head named ``cfg.name`` (``cfg``: its config dataclass or a mapping with the same fields).

    Raises:
        ValueError: an unknown name (the valid ones are listed) or a bad setting.
    """
    is_mapping = isinstance(cfg, Mapping)
    name = cfg["name"] if is_mapping else cfg.name
    if name not in POLICIES:
        raise ValueError(f"unknown policy {name!r}; valid: {sorted(POLICIES)}")
    spec = POLICIES[name]
    if not isinstance(cfg, spec.config):
        values = dict(cfg) if is_mapping else dataclasses.asdict(cfg)
        known = {f.name for f in dataclasses.fields(spec.config)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ValueError(f"policy {name!r} has no setting(s) {unknown}; valid: {sorted(known)}")
        cfg = spec.config(**values)
    return spec.build(cfg, info)
