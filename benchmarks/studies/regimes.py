"""Where does TAR help? The pre-registered regime study (``results/regimes/PLAN.md``) as a study.

Stages (``python -m benchmarks.studies regimes run STAGE``; every run lands in ``<out>/runs/``, named by its
settings):

* ``r1``: post-training from a pretrained policy. Trains the source (uniform, the 42 MT50 tasks outside the
  default eight, 25 demonstrations each) if it is not there, then the pairs (uniform, tar) on the default eight
  tasks from it, for each demonstration budget (3: primary; 10: secondary; ``--budgets`` picks).
* ``r2-screen``: the screening run (uniform, MT50, evaluated on the tuning seed) and the list of the ten tasks
  with the lowest success (``<out>/screening.json``), refused once comparison runs started.
* ``r2``: the pairs on the screened tasks (``<out>/r2_started.json`` records the list they use).
* ``r3``: the pairs on MT50 with 50 demonstrations per task, about 20 passes over the data.
* ``r4``, ``r5``: the chunked-heads regimes, R3's data, schedule and evaluation with the ``act`` (R4) and
  ``flow`` (R5) heads, three arms per seed (:data:`.protocol.CHUNKED_ARMS`), seed by seed. The plan's digest is
  recorded when its first run starts (``<out>/chunked_started.json``); a changed plan is refused by these stages and
  by ``table``.

``table`` writes the decision table, the per-group rows and Fig. 3 per regime (:mod:`.regimes_table`); ``collect``
keeps the checkpoint of R1's source, which the R1 runs start from. The ``ci`` scale runs the same stages on two or
three tasks for a few steps (what the tests run).
"""

from __future__ import annotations

import argparse
import hashlib
import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from benchmarks.studies.cli import ints, with_seeds
from benchmarks.studies.core import Arm, Grid, Planner, Scale, Spec, seed_major
from benchmarks.studies.protocol import CHUNKED_ARMS, EIGHT_TASKS, PAIR, SOURCE_TASKS
from benchmarks.studies.records import check_started, provenance, read_json
from benchmarks.studies.regimes_table import Planned, write_tables
from benchmarks.studies.stages import Context, Digest, Gate, Record, Stage, Study, named, plan, stage_arms

__all__ = ["SIZES", "STAGES", "STUDY", "RegimeSizes", "chunked_base", "chunked_grid", "r3_grid"]

CHUNKED_STARTED_FILE = "chunked_started.json"
SCREENING_FILE, STARTED_FILE = "screening.json", "r2_started.json"


@dataclass(frozen=True)
class RegimeSizes:
    """The sizes of the study's runs at one scale (overrides are Hydra's ``key=value``).

    Attributes:
        scale: the shared overrides, seeds and time model.
        source: R1's pretraining run.
        r1: R1's post-training runs (without the budget, seed and objective).
        r1_budgets: demonstrations per task of R1 (the first is the primary budget).
        screen: R2's screening run.
        screen_keep: tasks R2 keeps.
        r2: R2's runs (without the tasks, seed and objective).
        r3: R3's runs (without seed and objective).
        chunked: the chunked-heads regimes' runs (R3's data, schedule and evaluation; without the head, seed and
            objective).
        chunked_heads: ``(regime, head, overrides of the head)`` for each chunked-heads regime (R4, R5).
    """

    scale: Scale
    source: tuple[str, ...]
    r1: tuple[str, ...]
    r1_budgets: tuple[int, ...]
    screen: tuple[str, ...]
    screen_keep: int
    r2: tuple[str, ...]
    r3: tuple[str, ...]
    chunked: tuple[str, ...] = ()
    chunked_heads: tuple[tuple[str, str, tuple[str, ...]], ...] = ()


_COMMON = ("logging=quiet", "logging.record_episodes=3", "threads=1")
_CPU = RegimeSizes(
    scale=Scale(
        name="cpu",
        about="the pre-registered regime study (results/regimes/PLAN.md) on 2 CPU cores",
        common=_COMMON,
        seeds=(0, 1, 2, 3, 4, 5, 6, 7),
        jobs=2,
    ),
    source=(
        "policy=mlp",
        "policy.task_conditioning=instruction",
        "objective=uniform",
        "seed=0",
        f"data.tasks=[{SOURCE_TASKS}]",
        "data.n_demos=25",
        "data.seed=3000",
        "optim.steps=40000",
        "eval.rollouts=10",
        "eval.seed=2000",
        "logging.record_episodes=1",
    ),
    r1=(
        "policy=mlp",
        "policy.task_conditioning=instruction",
        f"data.tasks={EIGHT_TASKS}",
        "data.seed=0",
        "optim.steps=8000",
        "eval.rollouts=50",
        "eval.seed=1000",
        "logging.record_weights_at=[4000,-1]",
    ),
    r1_budgets=(3, 10),
    screen=(
        "policy=mlp",
        "objective=uniform",
        "seed=0",
        "data.tasks=[mt50]",
        "data.n_demos=10",
        "data.seed=0",
        "optim.steps=8000",
        "eval.rollouts=20",
        "eval.seed=2000",
    ),
    screen_keep=10,
    r2=(
        "policy=mlp",
        "data.n_demos=10",
        "data.seed=0",
        "optim.steps=20000",
        "eval.rollouts=50",
        "eval.seed=1000",
        "logging.record_weights_at=[10000,-1]",
    ),
    r3=(
        "policy=mlp",
        "data.tasks=[mt50]",
        "data.n_demos=50",
        "data.seed=0",
        "optim.steps=3743",  # 20 x 191,624 demonstration steps / (64 x 16) (results/regimes/PLAN.md)
        "eval.rollouts=20",
        "eval.seed=1000",
        "logging.record_weights_at=[1872,-1]",
    ),
    chunked=(
        "data.tasks=[mt50]",
        "data.n_demos=50",
        "data.seed=0",
        "optim.steps=3743",  # R3's schedule
        "eval.rollouts=20",
        "eval.seed=1000",
        "logging.record_weights_at=[1872,-1]",
        "policy.compile=true",  # the compiled attention: the same model, faster steps (tar_rl.policies.attention)
    ),
    chunked_heads=(("R4", "act", ()), ("R5", "flow", ())),  # each head at its defaults
)
_TINY = (
    "data.n_demos=2",
    "data.batch_segments=4",
    "data.slice_len=8",
    "data.workers=1",
    "optim.steps=4",
    "optim.warmup=1",
    "eval.rollouts=1",
    "eval.horizon=20",
    "eval.workers=1",
    "logging.every=1",
    "logging.checkpoint_every=2",
    "logging.record_weights_at=[-1]",
    "diagnostics.heldout_demos=1",
    "diagnostics.train_episodes=1",
)
_CI = RegimeSizes(
    scale=Scale(
        name="ci",
        about="the regime study's commands on two or three tasks, a few steps (the tests' size; no meaningful numbers)",
        common=(*_COMMON, *_TINY),
        seeds=(0, 1),
        jobs=1,
    ),
    source=(
        "policy=mlp",
        "policy.hidden=[16,16]",
        "policy.task_conditioning=instruction",
        "objective=uniform",
        "seed=0",
        "data.tasks=[push,drawer-open]",
        "data.seed=3000",
        "eval.seed=2000",
    ),
    r1=(
        "policy=mlp",
        "policy.hidden=[16,16]",
        "policy.task_conditioning=instruction",
        "data.tasks=[reach,basketball]",
        "eval.seed=1000",
    ),
    r1_budgets=(1, 2),
    screen=(
        "policy=mlp",
        "policy.hidden=[16,16]",
        "objective=uniform",
        "seed=0",
        "data.tasks=[reach,basketball,push]",
        "eval.seed=2000",
        "eval.rollouts=2",
    ),
    screen_keep=2,
    r2=("policy=mlp", "policy.hidden=[16,16]", "eval.seed=1000"),
    r3=("policy=mlp", "policy.hidden=[16,16]", "data.tasks=[reach,push]", "eval.seed=1000"),
    chunked=("data.tasks=[reach,push]", "eval.seed=1000"),
    chunked_heads=(
        ("R4", "act", ("policy.dim=16", "policy.heads=2", "policy.ffn_dim=16", "policy.latent_dim=4")),
        ("R5", "flow", ("policy.dim=16", "policy.heads=2", "policy.layers=1", "policy.expert_dim=8")),
    ),
)
SIZES = {"cpu": _CPU, "ci": _CI}


# -- The grids -------------------------------------------------------------------------------------------


def r1_grid(sizes: RegimeSizes, source: Spec, budget: int) -> Grid:
    """R1's pairs at one budget from ``source`` (which must have finished: its checkpoint is read), listed as ``R1``
    at the primary budget and ``R1-10`` at the others."""
    base = (*sizes.r1, f"data.n_demos={budget}", f"init.from={source.run_dir}")
    label = "R1" if budget == sizes.r1_budgets[0] else "R1-10"
    return Grid(label, "post-training from the pretrained source", base, PAIR, sizes.scale.seeds)


def r2_grid(sizes: RegimeSizes, tasks: Sequence[str]) -> Grid:
    """R2's pairs on the screened tasks."""
    base = (*sizes.r2, f"data.tasks=[{','.join(tasks)}]")
    return Grid("R2", "the pairs on the screened tasks", base, PAIR, sizes.scale.seeds)


def r3_grid(sizes: RegimeSizes) -> Grid:
    """R3's pairs: MT50, 50 demonstrations per task, about 20 passes."""
    return Grid("R3", "the pairs on MT50, 50 demonstrations per task", sizes.r3, PAIR, sizes.scale.seeds)


def chunked_base(sizes: RegimeSizes, label: str) -> tuple[str, ...]:
    """The overrides of the chunked-heads regime ``label``'s runs (``R4``, ``R5``) without seed and objective: the
    head at its settings, then R3's data, schedule and evaluation (what R6 and R7 repeat)."""
    for regime, head, extra in sizes.chunked_heads:
        if regime == label:
            return (f"policy={head}", *extra, *sizes.chunked)
    raise SystemExit(f"regimes: no chunked-heads regime {label!r} at this scale")


def chunked_grid(sizes: RegimeSizes, label: str) -> Grid:
    """The chunked-heads regime ``label`` (``R4``, ``R5``): R3's data with its head, the three
    :data:`.protocol.CHUNKED_ARMS`."""
    base = chunked_base(sizes, label)
    head = chunked_heads(sizes)[label]
    arms = tuple(Arm.objective(a) for a in CHUNKED_ARMS)
    return Grid(label, f"the chunked head {head}: {', '.join(CHUNKED_ARMS)}", base, arms, sizes.scale.seeds)


def chunked_heads(sizes: RegimeSizes) -> dict[str, str]:
    """The chunked-heads regimes' heads by regime."""
    return {regime: head for regime, head, _ in sizes.chunked_heads}


def source_spec(sizes: RegimeSizes, planner: Planner) -> Spec:
    """R1's pretraining run."""
    return planner.spec(*sizes.source)


def weights_read(sizes: RegimeSizes, planner: Planner) -> list[str]:
    """The runs whose ``weights.csv`` an analysis reads: R3's, every seed (``python -m benchmarks.analysis
    diagnosis``), and seed 0 of each arm of the chunked-heads regimes (R4, R5: the weights of each arm on one
    seed)."""
    names = [spec.run_dir.name for spec in seed_major(r3_grid(sizes).specs(planner))]
    for label in chunked_heads(sizes):
        specs = chunked_grid(sizes, label).specs(planner)
        names += [group[0].run_dir.name for group in specs.values() if group]
    return names


# -- The record of R2's screening ------------------------------------------------------------------------


def screening(out: Path) -> list[str] | None:
    """The committed R2 task list, or None before screening."""
    record = read_json(out / SCREENING_FILE)
    return None if record is None else record["tasks"]


def _digest(tasks: Sequence[str]) -> str:
    return hashlib.sha256(json.dumps(list(tasks)).encode()).hexdigest()[:16]


def pick_hardest(rollouts: pd.DataFrame, keep: int) -> list[str]:
    """The ``keep`` tasks with the lowest success rate; ties broken by task name (pre-registered)."""
    rates = rollouts.groupby("task")["success"].mean()
    order = sorted(rates.index, key=lambda t: (float(rates[t]), str(t)))
    return order[:keep]


def write_screening(sizes: RegimeSizes, spec: Spec, out: Path) -> list[str]:
    """Pick R2's tasks from the finished screening run and write ``screening.json``.

    Raises:
        SystemExit: comparison runs started with another list (``r2_started.json``).
    """
    from tar_rl import runs
    from tar_rl.io import write_json_atomic
    from tar_rl.report import load_run, run_file

    run = load_run(spec.run_dir)
    rollouts = pd.read_csv(run_file(spec.run_dir, runs.ROLLOUTS_FILE))
    tasks = pick_hardest(rollouts[rollouts["step"] == rollouts["step"].max()], sizes.screen_keep)
    started = out / STARTED_FILE
    if started.is_file() and json.loads(started.read_text())["tasks"] != tasks:
        raise SystemExit(
            f"regimes: R2's comparison runs started with the tasks in {started}; the screening now gives {tasks}. "
            "The list is fixed once comparison runs start: remove the R2 runs and that file to screen again."
        )
    rates = rollouts.groupby("task")["success"].mean()
    write_json_atomic(
        {
            "tasks": tasks,
            "digest": _digest(tasks),
            "rule": f"the {sizes.screen_keep} tasks with the lowest success of the screening run; ties by name",
            "screening_run": run.name,
            "success": {t: float(rates[t]) for t in sorted(rates.index)},
        },
        out / SCREENING_FILE,
    )
    return tasks


def check_r2_started(out: Path, tasks: Sequence[str]) -> None:
    """Record R2's task list when its comparison runs start; refuse a list that differs from the recorded one."""

    def refusal(key, recorded, now):
        return (
            f"regimes: {out / SCREENING_FILE} lists {list(tasks)} but R2's comparison runs started with "
            f"{recorded} ({out / STARTED_FILE}): a screening list may not change after comparison runs started"
        )

    check_started(out / STARTED_FILE, {"tasks": list(tasks), "digest": _digest(tasks)}, True, refusal)


# -- The study -------------------------------------------------------------------------------------------


class ScreenedTasks(Record):
    """R2's record when its comparison runs start: the screened task list (``r2_started.json``), which may not
    change after."""

    def check(self, ctx: Context, key: str, arms: dict, records: Sequence, record: bool) -> None:
        """Record the list the stage's gate read (``records[0]``) when its runs start; refuse one that differs."""
        if record:
            check_r2_started(ctx.out, records[0])


def _source(ctx: Context) -> Spec | None:
    spec = source_spec(ctx.sizes, ctx.planner)
    return spec if spec.finished else None


def _budgets(ctx: Context, grids: list[Grid], source: Spec) -> list[Grid]:
    """R1's grids at ``--budgets`` where given, in that order."""
    return [r1_grid(ctx.sizes, source, n) for n in ctx.args.budgets] if ctx.args.budgets else grids


def _screening_list(ctx: Context, specs: list[Spec]) -> None:
    (spec,) = specs
    if spec.finished:
        print(f"R2's tasks: {write_screening(ctx.sizes, spec, ctx.out)} ({ctx.out / SCREENING_FILE})")


SOURCE = Stage(
    "source",
    "R1's pretraining run, trained alone",
    grids=lambda ctx: [Grid.single("source", ctx.sizes.source)],
    jobs=1,
    planned=False,
)
SOURCE_FINISHED = Gate(
    "R1's finished source",
    read=_source,
    missing=lambda ctx: "R1's source has not finished: its post-training runs are planned once it has",
    stop=True,
)
SCREENED = Gate(
    "the screening record",
    read=lambda ctx: screening(ctx.out),
    missing=lambda ctx: f"regimes: no {ctx.out / SCREENING_FILE} yet; run `r2-screen` first",
)
STAGES = named(
    Stage(
        "r1",
        "post-training from the pretrained source, per demonstration budget",
        grids=lambda ctx, source: [r1_grid(ctx.sizes, source, n) for n in ctx.sizes.r1_budgets],
        gates=(SOURCE_FINISHED,),
        first=(SOURCE,),
        trains=_budgets,
    ),
    Stage(
        "r2-screen",
        "the screening run, trained alone, and the list of R2's tasks",
        grids=lambda ctx: [Grid.single("screen", ctx.sizes.screen)],
        jobs=1,
        then=_screening_list,
        planned=False,
    ),
    Stage(
        "r2",
        "the pairs on the screened tasks",
        grids=lambda ctx, tasks: [r2_grid(ctx.sizes, tasks)],
        gates=(SCREENED,),
        records=ScreenedTasks(),
    ),
    Stage("r3", "the pairs on MT50, 50 demonstrations per task", grids=lambda ctx: [r3_grid(ctx.sizes)]),
    *(
        Stage(
            label.lower(),
            f"the chunked-heads regime {label}",
            grids=lambda ctx, label=label: [chunked_grid(ctx.sizes, label)],
            records=Digest(CHUNKED_STARTED_FILE),
        )
        for label in ("R4", "R5")
    ),
)


def planned(ctx: Context) -> Planned:
    """The planned runs the tables read; a chunked-heads plan that changed after its runs started is refused."""
    heads = chunked_heads(ctx.sizes)
    chunked = {label: (head, stage_arms(ctx, STAGES[label.lower()])) for label, head in heads.items()}
    paired = {label: specs for label, specs in plan(ctx).items() if label not in heads}
    return Planned(paired, chunked, ctx.out / SCREENING_FILE, screening(ctx.out), ctx.out)


def table(ctx: Context) -> None:
    """The decision table, per-group rows and Fig. 3 (:func:`.regimes_table.write_tables`)."""
    prov = provenance(ctx.scale, ctx.study.name, ctx.argv[1:])
    print(write_tables(planned(ctx), prov, ctx.tables, complete=ctx.args.complete))


def _options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--budgets", type=ints, default=None, help="run r1: only these demonstration budgets")
    p.add_argument(
        "--complete", action="store_true", help="table: refuse a chunked-heads regime with a run of its plan missing"
    )


STUDY = Study(
    name="regimes",
    about="The pre-registered regime study: runs and tables.",
    scales=SIZES,
    stages=STAGES,
    table=table,
    results=lambda scale: "regimes" if scale == "cpu" else None,
    options=_options,
    with_options=with_seeds,
    keep_checkpoint=lambda ctx: [source_spec(ctx.sizes, ctx.planner).run_dir.name],
    keep_weights=lambda ctx: weights_read(ctx.sizes, ctx.planner),
)
