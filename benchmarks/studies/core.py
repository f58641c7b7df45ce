"""What a study trains: a scale, arms, grids, run specs and the planner that composes them.

A *scale* holds the overrides every run of a study shares at one size (``cpu``, ``ci``, ...) and its time model.
An *arm* is a name and the overrides that make it (an objective, a TAR cell). A *grid* is arms x seeds over a base
of overrides; the planner turns each (arm, seed) into a :class:`Spec`: the composed, validated config of the
offline BC recipe and the run directory it names (``<out>/runs/<run name>``), so that running a grid again skips
its finished runs and resumes an interrupted one. A stage (:mod:`.stages`) trains one grid or several.
"""

from __future__ import annotations

import functools
import hashlib
import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

__all__ = ["Arm", "Grid", "Planner", "Scale", "Spec", "plan_digest", "seed_major"]


@dataclass(frozen=True)
class Scale:
    """A named size of a study.

    Attributes:
        name: the scale's name.
        about: one line on what it is for.
        common: Hydra overrides shared by every run of the study at this scale.
        seeds: the training seeds of the study's stages (a stage may name others).
        jobs: runs trained at once by default.
        step_seconds: the time model: seconds per training step of one run (one core).
        rollout_seconds: seconds per evaluation rollout (one core).
    """

    name: str
    about: str
    common: tuple[str, ...]
    seeds: tuple[int, ...]
    jobs: int = 1
    step_seconds: float = 0.025
    rollout_seconds: float = 0.9

    def value(self, key: str, default=None):
        """The value the scale's overrides give ``key`` (as text), else ``default``."""
        for item in reversed(self.common):
            k, _, v = item.partition("=")
            if k == key:
                return v
        return default


@dataclass
class Spec:
    """One training run: its Hydra overrides, resolved config and run directory."""

    overrides: tuple[str, ...]
    config: dict
    run_dir: Path

    @property
    def finished(self) -> bool:
        """The run directory holds a summary saying the run finished."""
        try:
            return bool(json.loads((self.run_dir / "summary.json").read_text()).get("finished"))
        except (OSError, ValueError):
            return False


@dataclass(frozen=True)
class Arm:
    """A setting compared in a stage: its name (a table's row) and the overrides that make it."""

    name: str
    overrides: tuple[str, ...]

    @classmethod
    def objective(cls, name: str) -> Arm:
        """The arm of a registered weighting at its defaults (``objective=<name>``)."""
        return cls(name, (f"objective={name}",))


@dataclass(frozen=True)
class Grid:
    """Arms x seeds over a base: the run of arm ``a`` and seed ``s`` has the overrides ``(*base, seed=s,
    *a.overrides)`` (with ``seed_last``: ``(*base, *a.overrides, seed=s)``; a seed ``None``: ``(*base,
    *a.overrides)``, the base naming the seed).

    Attributes:
        name: the label its runs are listed under by ``plan`` (grids of one stage may share it) and recorded under
            when its runs start (:class:`.stages.Digest`).
        about: one line on what it trains.
        base: the overrides every run of the grid shares (after the scale's).
        arms: the settings compared.
        seeds: the training seeds.
        seed_last: the seed's override after the arm's.
        reused: the ``(arm, seed)`` runs planned in another study's folder, ``reused_from`` (runs that study trained
            and this grid pairs with its own).
        reused_from: that folder (``<folder>/runs`` holds the runs).
    """

    name: str
    about: str
    base: tuple[str, ...]
    arms: tuple[Arm, ...]
    seeds: tuple[int | None, ...]
    seed_last: bool = False
    reused: frozenset[tuple[str, int]] = frozenset()
    reused_from: Path | None = None

    @classmethod
    def single(cls, name: str, overrides: tuple[str, ...]) -> Grid:
        """One run of exactly ``overrides`` (its seed among them)."""
        return cls(name, "one run", overrides, (Arm(name, ()),), (None,))

    def overrides(self, arm: Arm, seed: int | None) -> tuple[str, ...]:
        """The overrides of one run (after the scale's)."""
        if seed is None:
            return (*self.base, *arm.overrides)
        if self.seed_last:
            return (*self.base, *arm.overrides, f"seed={seed}")
        return (*self.base, f"seed={seed}", *arm.overrides)

    def specs(self, planner: Planner) -> dict[str, list[Spec]]:
        """The runs per arm, seeds in order."""
        elsewhere = planner
        if self.reused:
            elsewhere = Planner(planner.scale, self.reused_from, planner.data_root, planner.extra)
        return {
            arm.name: [
                (elsewhere if (arm.name, s) in self.reused else planner).spec(*self.overrides(arm, s))
                for s in self.seeds
            ]
            for arm in self.arms
        }


def seed_major(specs: dict[str, list[Spec]]) -> list[Spec]:
    """Seed by seed (every arm of the first seed, then the next), so a sweep cut short leaves whole seeds."""
    groups = list(specs.values())
    return [group[i] for i in range(max(map(len, groups), default=0)) for group in groups if i < len(group)]


def plan_digest(specs: dict[str, list[Spec]]) -> str:
    """A digest of what the runs of a plan train (their overrides, without the machine's folders)."""
    local = ("runs_root=", "data.root=")
    plan = {arm: [[o for o in s.overrides if not o.startswith(local)] for s in group] for arm, group in specs.items()}
    return hashlib.sha256(json.dumps(plan, sort_keys=True).encode()).hexdigest()[:16]


@functools.cache
def _register_configs() -> None:
    """Store the training job's configs in Hydra's ConfigStore, once per process (a third of a composition's time
    otherwise)."""
    from tar_rl.recipes.config import register_configs

    register_configs()


def compose(overrides: Sequence[str]) -> dict:
    """The resolved config of the training job with ``overrides`` (Hydra's composition, tar-rl's resolution)."""
    from hydra import compose as hydra_compose
    from hydra import initialize

    from tar_rl.recipes import resolve_config

    _register_configs()
    with initialize(version_base="1.3", config_path=None):
        return resolve_config(hydra_compose(config_name="train", overrides=list(overrides)))


class Planner:
    """Builds :class:`Spec` s for a scale, an output folder, a dataset cache and the user's extra overrides.

    A run's overrides are the scale's, ``runs_root=<out>/runs``, ``data.root=<data_root>``, the extra ones, then
    the run's own (the later wins).
    """

    def __init__(self, scale: Scale, out: Path, data_root: str, extra: Sequence[str] = ()):
        self.scale, self.out, self.data_root, self.extra = scale, out, data_root, tuple(extra)

    def overrides(self, *overrides: str) -> tuple[str, ...]:
        """Every override of the run whose own are ``overrides`` (class docstring), without composing it."""
        return (
            *self.scale.common,
            f"runs_root={self.out / 'runs'}",
            f"data.root={self.data_root}",
            *self.extra,
            *overrides,
        )

    def spec(self, *overrides: str) -> Spec:
        """The run of ``overrides``; bad settings are refused with the composition's or validation's message."""
        from tar_rl.recipes import ConfigError, run_name, validate
        from tar_rl.recipes.config import config_dict

        items = self.overrides(*overrides)
        try:
            config = compose(items)
            job = validate(config)
        except ConfigError as err:
            raise SystemExit(f"studies: {err}") from None
        except Exception as err:  # Hydra's composition errors name the bad override
            raise SystemExit(f"studies: bad settings {list(items)}: {err}") from None
        return Spec(items, config, Path(job.config.runs_root) / run_name(config_dict(job.config)))
