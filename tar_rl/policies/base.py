"""What every head shares with the recipe: :class:`DataInfo` (what a head reads from the data), :class:`Policy`
(a built head), :class:`PolicySpec` (a registered head) and the registry :data:`POLICIES`.

The heads import this module and register themselves into :data:`POLICIES` (:func:`register_policy`);
``tar_rl.policies`` imports the heads, so a head is known once the package is imported.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

from tensordict.nn import TensorDictModule
from torchrl.objectives import LossModule

from tar_rl.objectives.registry import Registry

__all__ = ["POLICIES", "DataInfo", "Policy", "PolicySpec", "build_policy", "register_policy"]


@dataclass(frozen=True)
class DataInfo:
    """What a head needs to know about the data. The defaults are MetaWorld's sizes (39, 4, 50 task ids), for
    heads built without a dataset (tests, benchmarks).

    Attributes:
        obs_dim: observation size.
        action_dim: action size.
        n_tasks: number of task ids (the dataset's ``task_names``: a suite with a fixed task list numbers
            all of it, so a policy trained on a few tasks is evaluated with the same ids).
        obs_mean, obs_std: per-dimension observation statistics of the training data.
        chunk_horizon: the dataset's ``action_chunk`` horizon ``H``.
        history: the dataset's ``observation_history`` window ``K``.
        image_size: the side ``S`` of the dataset's ``pixels`` (0: a state-only dataset).
        instructions: the instruction text of each task id (``""`` where the dataset has none); ``None``:
            no texts at all (``task_conditioning=instruction`` is then refused).
    """

    obs_dim: int = 39
    action_dim: int = 4
    n_tasks: int = 50
    obs_mean: tuple[float, ...] | None = None
    obs_std: tuple[float, ...] | None = None
    chunk_horizon: int = 1
    history: int = 1
    image_size: int = 0
    instructions: tuple[str, ...] | None = None

    @classmethod
    def for_tasks(cls, names: Sequence[str], instructions: Mapping[str, str] | None, **fields) -> DataInfo:
        """The description of data whose task ids index ``names``, each with its instruction (``""`` where
        ``instructions`` has none); ``fields`` are the other attributes."""
        texts = instructions or {}
        return cls(n_tasks=len(names), instructions=tuple(texts.get(name) or "" for name in names), **fields)

    @classmethod
    def from_metadata(cls, metadata: dict) -> DataInfo:
        """Read the dimensions, observation statistics, task ids and instructions from a dataset's metadata."""
        stats = metadata["stats"]["observation"]
        return cls.for_tasks(
            metadata["task_names"],
            metadata.get("instructions"),
            obs_dim=len(stats["mean"]),
            action_dim=len(metadata["stats"]["action"]["mean"]),
            obs_mean=tuple(stats["mean"]),
            obs_std=tuple(stats["std"]),
            chunk_horizon=int(metadata["chunk_horizon"]),
            history=int(metadata.get("history", 1)),
            image_size=int(metadata.get("image_size", 0)),
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
        loss_key: the loss output holding the per-step loss when the loss returns several
            ``loss_*`` entries (the others must be scalars, added unweighted, e.g. ACT's KL term);
            ``None``: its only ``loss_*`` entry.
    """

    actor: TensorDictModule
    loss: LossModule
    keys: tuple | None = None
    event_valid: str | None = None
    loss_key: str | None = None


@dataclass(frozen=True)
class PolicySpec:
    """A registered head: its config dataclass and its builder.

    Attributes:
        signals: the ranking signals its loss offers besides the loss itself (``objective.signal``; the ``flow``
            head's ``action_error`` and ``time_normalized``), none for most heads.
    """

    name: str
    config: type
    build: Callable[[object, DataInfo], Policy]
    description: str = ""
    signals: tuple[str, ...] = ()


POLICIES: Registry[PolicySpec] = Registry("policy")


def register_policy(spec: PolicySpec) -> PolicySpec:
    """Add a head to :data:`POLICIES` (a name may be registered once)."""
    return POLICIES.register(spec.name, spec)


def build_policy(cfg, info: DataInfo) -> Policy:
    """Build the head named ``cfg.name`` (``cfg``: its config dataclass or a mapping with the same fields).

    Raises:
        ValueError: an unknown name (the valid ones are listed) or a bad setting.
    """
    is_mapping = isinstance(cfg, Mapping)
    name = cfg["name"] if is_mapping else cfg.name
    spec = POLICIES.get(name)
    if not isinstance(cfg, spec.config):
        values = dict(cfg) if is_mapping else dataclasses.asdict(cfg)
        known = {f.name for f in dataclasses.fields(spec.config)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ValueError(f"policy {name!r} has no setting(s) {unknown}; valid: {sorted(known)}")
        cfg = spec.config(**values)
    return spec.build(cfg, info)
