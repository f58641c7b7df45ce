"""A regime's runs paired by seed, with their recorded weights: what the diagnosis (:mod:`.diagnosis`) and the
per-dimension recording (:mod:`.dims`) read.

A regime's runs are the runs whose config has the regime's head, tasks, demonstrations and steps (the regime study's
declaration, :data:`benchmarks.studies.regimes.SIZES`: R3 the state MLP, R4 and R5 the chunked heads, :data:`REGIMES`);
each seed must have one run of each of the regime's arms (R3: uniform and tar; R4, R5: uniform, tar at tar-rl's
defaults and tar_gentle, the run whose objective has the ``tar_gentle`` preset's settings), finished and trained at one
commit on one machine. R3 needs the weights of every run, recorded at the step TAR reaches full strength and at the
last step; a chunked-heads regime keeps them for some seeds only (the study's results budget: seed 0) and needs them
for at least one seed, every arm (:attr:`Pairs.weighted`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import yaml

from benchmarks.studies.compare import check_pairs
from benchmarks.studies.protocol import BASELINE, CHUNKED_ARMS, TREATMENT, arm_of
from benchmarks.studies.regimes import SIZES
from tar_rl.report import Run, load_run

__all__ = [
    "DEFAULT_RUNS",
    "REGIMES",
    "STEP_KEYS",
    "WINDOW",
    "Pairs",
    "Regime",
    "load_pairs",
    "r3_settings",
    "regime",
]

#: Steps on either side of a gripper switch that count as near it.
WINDOW = 2
#: The columns that name one recorded demonstration of a run's ``weights.csv``.
STEP_KEYS = ("step", "task", "episode")
#: The committed runs of the regime study.
DEFAULT_RUNS = Path(__file__).resolve().parent.parent / "results" / "regimes" / "runs"
#: The settings that tell a regime's runs from the others'.
KEYS = ("policy.name", "data.tasks", "data.n_demos", "optim.steps")


def _settings(overrides: tuple[str, ...]) -> dict:
    """A regime's defining settings from its Hydra overrides: head, tasks, demonstrations, steps, and the training
    step at which TAR reaches full strength (the first recording step)."""
    values = dict(o.split("=", 1) for o in overrides)
    return {
        "policy.name": values["policy"],
        "data.tasks": yaml.safe_load(values["data.tasks"]),
        "data.n_demos": int(values["data.n_demos"]),
        "optim.steps": int(values["optim.steps"]),
        "full_step": int(yaml.safe_load(values["logging.record_weights_at"])[0]),
    }


def r3_settings() -> dict:
    """R3's defining settings (from the study's overrides in ``regimes.py``): head, tasks, demonstrations, steps
    (R4 and R5 share the last three with another head), and the training step at which TAR reaches full strength
    (the first recording step)."""
    return _settings(SIZES["cpu"].r3)


@dataclass(frozen=True)
class Regime:
    """What the diagnosis reads of one regime.

    Attributes:
        label: ``R3``, ``R4``, ``R5``.
        settings: :func:`r3_settings`'s keys for the regime.
        arms: the arms of a seed, the baseline first.
        weights_every_seed: every run must have its weights (R3); else at least one seed, every arm.
    """

    label: str
    settings: dict
    arms: tuple[str, ...]
    weights_every_seed: bool

    @property
    def treatments(self) -> tuple[str, ...]:
        return self.arms[1:]


def regime(label: str) -> Regime:
    """The regime ``label`` of the study at the cpu scale (:data:`REGIMES`).

    Raises:
        SystemExit: an unknown label (the known ones named).
    """
    sizes = SIZES["cpu"]
    if label == "R3":
        return Regime("R3", r3_settings(), (BASELINE, TREATMENT), True)
    for name, head, extra in sizes.chunked_heads:
        if name == label:
            return Regime(label, _settings((f"policy={head}", *extra, *sizes.chunked)), CHUNKED_ARMS, False)
    raise SystemExit(f"diagnosis: no regime {label!r}; the regimes are {', '.join(REGIMES)}")


#: The regimes the diagnosis reads: R3 and the chunked heads'.
REGIMES = ("R3", *(name for name, _, _ in SIZES["cpu"].chunked_heads))


def _get(config: dict, dotted: str):
    node = config
    for key in dotted.split("."):
        node = node.get(key) if isinstance(node, dict) else None
    return node


@dataclass
class Pairs:
    """A regime's runs paired by seed (``runs[seed][arm]``); ``steps`` maps the labels ``full`` and ``last`` to
    recording steps; ``weighted`` lists the seeds whose runs all recorded weights at both steps."""

    runs: dict[int, dict[str, Run]]
    steps: dict[str, int]
    regime: str = "R3"
    arms: tuple[str, ...] = (BASELINE, TREATMENT)
    weighted: tuple[int, ...] = field(default=())


def load_pairs(runs_dir: Path, label: str = "R3") -> Pairs:
    """The runs of regime ``label`` in ``runs_dir``, one run per arm and seed.

    Raises:
        SystemExit: an unknown regime, no runs of the regime, a seed without its arms (or with one twice), an
            unfinished run, runs of a seed trained at different commits or machines; R3: a run without weights at
            both recording steps; a chunked-heads regime: no seed whose runs all recorded them. The message names
            what is missing.
    """
    spec = regime(label)
    settings = spec.settings
    if not runs_dir.is_dir():
        raise SystemExit(f"diagnosis: {runs_dir} is not a folder")
    found = []
    for path in sorted(p for p in runs_dir.iterdir() if (p / "config.yaml").is_file()):
        config = yaml.safe_load((path / "config.yaml").read_text())
        if all(_get(config, k) == settings[k] for k in KEYS):
            found.append((arm_of(config), load_run(path)))
    if not found:
        wanted = ", ".join(f"{k} {settings[k]}" for k in KEYS)
        raise SystemExit(f"diagnosis: no {label} runs in {runs_dir} (runs whose config has {wanted})")
    steps = {"full": settings["full_step"], "last": settings["optim.steps"]}
    pairs: dict[int, dict[str, Run]] = {}
    for arm, run in found:
        slot = pairs.setdefault(run.seed, {})
        if arm not in spec.arms or arm in slot:
            raise SystemExit(f"diagnosis: unexpected {label} run {run.name} (seed {run.seed}, {arm})")
        slot[arm] = run
    weighted = []
    for seed, slot in sorted(pairs.items()):
        for arm in spec.arms:
            if arm not in slot:
                have = ", ".join(r.name for r in slot.values())
                raise SystemExit(f"diagnosis: {label}'s pair of seed {seed} is incomplete: no {arm} run ({have})")
        _check_runs(slot, steps, spec.weights_every_seed)
        check_pairs(list(slot.values()))
        if all(not _lacking(run, steps) for run in slot.values()):
            weighted.append(seed)
    if not weighted:
        raise SystemExit(
            f"diagnosis: no {label} seed has weights recorded by every arm at training steps "
            f"{sorted(steps.values())} ({len(pairs)} seeds in {runs_dir})"
        )
    return Pairs(dict(sorted(pairs.items())), steps, label, spec.arms, tuple(weighted))


def _lacking(run: Run, steps: dict[str, int]) -> list[int]:
    recorded = set() if run.weights is None else set(run.weights["step"].astype(int))
    return sorted(set(steps.values()) - recorded)


def _check_runs(slot: dict[str, Run], steps: dict[str, int], weights: bool) -> None:
    for run in slot.values():
        if not run.finished:
            raise SystemExit(f"diagnosis: {run.name} has not finished ({'; '.join(run.notes)})")
        lacking = _lacking(run, steps)
        if weights and lacking:
            raise SystemExit(f"diagnosis: {run.name} has no recorded weights at training step(s) {lacking}")
    tasks = {run.eval_settings["tasks"] for run in slot.values()}
    if len(tasks) > 1:
        raise SystemExit(f"diagnosis: the runs {', '.join(r.name for r in slot.values())} evaluated other tasks")
