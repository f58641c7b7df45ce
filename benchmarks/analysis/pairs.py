"""The regime study's R3 runs paired by seed, with their recorded weights: what the diagnosis
(:mod:`.diagnosis`) and the per-dimension recording (:mod:`.dims`) read.

R3's runs are the runs whose config has R3's head, tasks, demonstrations and steps (the regime study's
declaration, :data:`benchmarks.studies.regimes.SIZES`); each seed must have one uniform and one tar run, finished,
with weights recorded at the step TAR reaches full strength and at the last step, trained at one commit on one
machine.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import yaml

from benchmarks.studies.compare import check_pairs
from benchmarks.studies.protocol import BASELINE, TREATMENT
from benchmarks.studies.regimes import SIZES
from tar_rl.report import Run, load_run

__all__ = ["DEFAULT_RUNS", "STEP_KEYS", "WINDOW", "Pairs", "load_pairs", "r3_settings"]

#: Steps on either side of a gripper switch that count as near it.
WINDOW = 2
#: The columns that name one recorded demonstration of a run's ``weights.csv``.
STEP_KEYS = ("step", "task", "episode")
#: The committed runs of the regime study.
DEFAULT_RUNS = Path(__file__).resolve().parent.parent / "results" / "regimes" / "runs"


def r3_settings() -> dict:
    """R3's defining settings (from the study's overrides in ``regimes.py``): head, tasks, demonstrations, steps
    (R4 and R5 share the last three with another head), and the training step at which TAR reaches full strength
    (the first recording step)."""
    overrides = dict(o.split("=", 1) for o in SIZES["cpu"].r3)
    return {
        "policy.name": overrides["policy"],
        "data.tasks": yaml.safe_load(overrides["data.tasks"]),
        "data.n_demos": int(overrides["data.n_demos"]),
        "optim.steps": int(overrides["optim.steps"]),
        "full_step": int(yaml.safe_load(overrides["logging.record_weights_at"])[0]),
    }


def _get(config: dict, dotted: str):
    node = config
    for key in dotted.split("."):
        node = node.get(key) if isinstance(node, dict) else None
    return node


@dataclass
class Pairs:
    """R3's runs paired by seed; ``steps`` maps the labels ``full`` and ``last`` to recording steps."""

    runs: dict[int, dict[str, Run]]
    steps: dict[str, int]


def load_pairs(runs_dir: Path) -> Pairs:
    """The R3 runs of ``runs_dir``, one uniform and one tar run per seed.

    Raises:
        SystemExit: no R3 runs, a seed without its two runs (or with more), an unfinished run, or a run
            without weights at both recording steps; the message names what is missing.
    """
    r3 = r3_settings()
    keys = ("policy.name", "data.tasks", "data.n_demos", "optim.steps")
    if not runs_dir.is_dir():
        raise SystemExit(f"diagnosis: {runs_dir} is not a folder")
    found = []
    for path in sorted(p for p in runs_dir.iterdir() if (p / "config.yaml").is_file()):
        config = yaml.safe_load((path / "config.yaml").read_text())
        if all(_get(config, k) == r3[k] for k in keys):
            found.append(load_run(path))
    if not found:
        wanted = ", ".join(f"{k} {r3[k]}" for k in keys)
        raise SystemExit(f"diagnosis: no R3 runs in {runs_dir} (runs whose config has {wanted})")
    steps = {"full": r3["full_step"], "last": r3["optim.steps"]}
    pairs: dict[int, dict[str, Run]] = {}
    for run in found:
        slot = pairs.setdefault(run.seed, {})
        if run.objective not in (BASELINE, TREATMENT) or run.objective in slot:
            raise SystemExit(f"diagnosis: unexpected R3 run {run.name} (seed {run.seed}, {run.objective})")
        slot[run.objective] = run
    for seed, slot in sorted(pairs.items()):
        for objective in (BASELINE, TREATMENT):
            if objective not in slot:
                have = ", ".join(r.name for r in slot.values())
                raise SystemExit(f"diagnosis: R3's pair of seed {seed} is incomplete: no {objective} run ({have})")
        _check_runs(slot, steps)
        check_pairs(list(slot.values()))
    return Pairs(dict(sorted(pairs.items())), steps)


def _check_runs(slot: dict[str, Run], steps: dict[str, int]) -> None:
    for run in slot.values():
        if not run.finished:
            raise SystemExit(f"diagnosis: {run.name} has not finished ({'; '.join(run.notes)})")
        recorded = set() if run.weights is None else set(run.weights["step"].astype(int))
        lacking = sorted(set(steps.values()) - recorded)
        if lacking:
            raise SystemExit(f"diagnosis: {run.name} has no recorded weights at training step(s) {lacking}")
    tasks = {run.eval_settings["tasks"] for run in slot.values()}
    if len(tasks) > 1:
        raise SystemExit(f"diagnosis: the runs {', '.join(r.name for r in slot.values())} evaluated other tasks")
