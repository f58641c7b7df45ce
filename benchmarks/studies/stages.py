"""A stage as a declaration, a study as its stages and its table, and the one function that plans and runs any stage.

A :class:`Stage` declares the runs it trains (grids of arms x seeds, :class:`.core.Grid`, from the records its gates
read), its gates (named preconditions: R2's screening list, R7's selection, R1's finished source), what it records
when its first run starts (its plan's digest, :class:`Digest`), and what it writes from its runs once they finished.
A stage that computes instead of training (a selection rule) or trains in rounds (a grid extended while its best
setting is at an edge) names that step as its ``action``. :func:`run_stage` runs any stage: the stages it needs
first, the gates, the plan, the record, the runs (resumable, ``--jobs`` at once, ``--tree``'s code), seed by seed;
it returns the runs that failed, and the command exits non-zero when there are any. :func:`plan` lists every stage's
runs that can be planned now.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from benchmarks.studies.core import Grid, Planner, Scale, Spec, seed_major
from benchmarks.studies.records import check_stage_plan
from benchmarks.studies.sweep import check_tree, execute

__all__ = [
    "Context",
    "Digest",
    "Gate",
    "Record",
    "Stage",
    "Study",
    "named",
    "plan",
    "run_stage",
    "stage_arms",
    "stage_grids",
    "stage_specs",
]


@dataclass
class Context:
    """One command of a study: the parsed command line, the study's sizes at the scale, the planner, the results
    folder and the runs trained at once."""

    study: Study
    args: argparse.Namespace
    argv: list[str]
    sizes: Any
    scale: Scale
    planner: Planner
    out: Path
    jobs: int

    @property
    def logs(self) -> Path:
        """Where the subprocesses of a parallel sweep write their output."""
        return self.out / "logs"

    @property
    def tables(self) -> Path:
        """Where ``table`` writes: ``--tables`` when given, else the results folder (created)."""
        dest = Path(self.args.tables) if getattr(self.args, "tables", None) else self.out
        dest.mkdir(parents=True, exist_ok=True)
        return dest

    @property
    def tree(self) -> Path | None:
        """The checkout whose code trains the runs (``--tree``, where the study has the option), checked."""
        return check_tree(getattr(self.args, "tree", None), self.study.name)


@dataclass(frozen=True)
class Gate:
    """A named precondition of a stage: a record the stage is planned from.

    Attributes:
        name: what the stage needs, in words ("the screening record").
        read: the record (read from the study's folder), or None while there is none.
        missing: the message naming what to run first.
        stop: a missing record ends the stage with the message (the command succeeds) instead of refusing it.
    """

    name: str
    read: Callable[[Context], Any]
    missing: Callable[[Context], str]
    stop: bool = False


class Record:
    """What a stage records when its first run starts, and refuses to see change after (:class:`Digest`, or R2's
    screened task list)."""

    #: The grid whose plan is recorded, where it is not the stage's (``ctx -> Grid``).
    of: Callable[[Context], Grid] | None = None

    def check(self, ctx: Context, key: str, arms: dict[str, list[Spec]], records: Sequence[Any], record: bool) -> None:
        """Refuse ``arms`` (the runs per arm of the grid named ``key``; ``records``: the stage's gates') where they
        differ from what was recorded; with ``record``, record them (the stage's first run starts)."""
        raise NotImplementedError


@dataclass(frozen=True)
class Digest(Record):
    """What a stage records when its first run starts: its plan's digest (:func:`.core.plan_digest`) under its
    grid's name in ``file`` beside the runs. A plan that changed since is refused by ``run`` and the table.

    Attributes:
        file: the record's file name in the study's folder.
        of: the grid whose plan is recorded, where it is not the stage's (a grid that grows as it trains records the
            one it started as).
    """

    file: str
    of: Callable[[Context], Grid] | None = None

    def check(self, ctx: Context, key: str, arms: dict[str, list[Spec]], records: Sequence[Any], record: bool) -> None:
        """:meth:`Record.check` of the plan's digest."""
        check_stage_plan(ctx.out / self.file, ctx.study.name, key, arms, record)


@dataclass(frozen=True)
class Stage:
    """A stage of a study as a declaration (module docstring).

    Attributes:
        name: the stage's name on the command line (``run NAME``).
        about: one line on what it does.
        grids: the grids it trains, from the context and its gates' records (in their order); ``None`` for a stage
            that trains nothing itself.
        gates: the records it needs, checked in order before it is planned.
        records: what it records when its first run starts (:class:`Record`).
        first: the stages run before this one's gates are checked (a run the gates read, or the stages ``all``
            runs).
        jobs: runs trained at once where the stage fixes it (a single run trained alone); else ``--jobs``.
        trains: the grids ``run`` trains instead of those planned (``ctx``, the grids, the gates' records): an
            option of the command picking some.
        then: after the runs, what the stage writes from them (``ctx``, the runs trained).
        action: what the stage does instead of training its grids (``ctx``; returns the runs that failed): a rule
            applied to finished runs, or a grid trained in rounds.
        planned: ``plan`` lists its runs.
    """

    name: str
    about: str
    grids: Callable[..., Sequence[Grid]] | None = None
    gates: tuple[Gate, ...] = ()
    records: Record | None = None
    first: tuple[Stage, ...] = ()
    jobs: int | None = None
    trains: Callable[..., list[Grid]] | None = None
    then: Callable[[Context, list[Spec]], None] | None = None
    action: Callable[[Context], list[Spec]] | None = None
    planned: bool = True


def named(*stages: Stage) -> dict[str, Stage]:
    """Stages by name, in the order given (a study's ``stages``)."""
    return {s.name: s for s in stages}


@dataclass(frozen=True)
class Study:
    """A study: its sizes, its stages and its table.

    Attributes:
        name: its name on the command line.
        about: one line on what it is.
        scales: the study's sizes by scale name (each with its :class:`.core.Scale` as ``.scale``).
        stages: its stages by name (``run STAGE``; :func:`named`).
        table: writes the tables and figures.
        results: the default results folder at a scale (relative to ``benchmarks/results``); ``None`` where
            ``--out`` is required.
        options: adds the study's own options to the parser.
        with_options: the sizes with the command line's options applied (``--seeds`` and the study's own), refused
            where they do not apply.
        keep_checkpoint: run names whose checkpoint ``collect`` keeps.
        keep_weights: run names whose ``weights.csv`` ``collect`` keeps (the runs an analysis reads).
        announce: ``run`` prints each stage's name and the scale before its runs (a command that runs several).
    """

    name: str
    about: str
    scales: dict[str, Any]
    stages: Mapping[str, Stage]
    table: Callable[[Context], None]
    results: Callable[[str], str | None]
    options: Callable[[argparse.ArgumentParser], None] = lambda parser: None
    with_options: Callable[[Any, argparse.Namespace], Any] = lambda sizes, args: sizes
    keep_checkpoint: Callable[[Context], list[str]] = field(default=lambda ctx: [])
    keep_weights: Callable[[Context], list[str]] = field(default=lambda ctx: [])
    announce: bool = False


def _records(ctx: Context, stage: Stage) -> tuple[list[Any], Gate | None]:
    """The records of the stage's gates in order, and the first gate whose record is missing (else None)."""
    records = []
    for gate in stage.gates:
        record = gate.read(ctx)
        if record is None:
            return records, gate
        records.append(record)
    return records, None


def _planned(ctx: Context, stage: Stage) -> tuple[list[Grid], list[Any]] | None:
    """The stage's grids and its gates' records, or None where a gate's record is missing."""
    records, missing = _records(ctx, stage)
    if missing is not None or stage.grids is None:
        return None
    return list(stage.grids(ctx, *records)), records


def _in_order(ctx: Context, grids: Sequence[Grid]) -> list[Spec]:
    """The runs of ``grids`` in the order they train: each grid's seed by seed, grid after grid."""
    return [s for grid in grids for s in seed_major(grid.specs(ctx.planner))]


def stage_grids(ctx: Context, stage: Stage) -> list[Grid] | None:
    """The stage's grids, or None where a gate's record is missing."""
    planned = _planned(ctx, stage)
    return None if planned is None else planned[0]


def stage_specs(ctx: Context, stage: Stage, trained: bool = False) -> list[Spec] | None:
    """The stage's planned runs in the order they train, or None where a gate's record is missing; with
    ``trained``, the runs ``run`` trains (the stage's ``trains`` applied to its grids)."""
    planned = _planned(ctx, stage)
    if planned is None:
        return None
    grids, records = planned
    if trained and stage.trains is not None:
        grids = stage.trains(ctx, grids, *records)
    return _in_order(ctx, grids)


def stage_arms(ctx: Context, stage: Stage, check: bool = True) -> dict[str, list[Spec]] | None:
    """The runs per arm of a stage that trains one grid, or None where a gate's record is missing; with ``check``,
    a plan that differs from the one its runs started with is refused (the stage's record)."""
    planned = _planned(ctx, stage)
    if planned is None:
        return None
    (grid,), records = planned
    arms = grid.specs(ctx.planner)
    if check and stage.records is not None and stage.records.of is None:
        stage.records.check(ctx, grid.name, arms, records, record=False)
    return arms


def plan(ctx: Context) -> dict[str, list[Spec]]:
    """Every planned stage's runs that can be planned now (every gate's record there), by grid name, in the order
    they train."""
    out: dict[str, list[Spec]] = {}
    for stage in ctx.study.stages.values():
        planned = _planned(ctx, stage) if stage.planned else None
        for grid in planned[0] if planned else ():
            out.setdefault(grid.name, []).extend(_in_order(ctx, [grid]))
    return out


def run_stage(ctx: Context, stage: Stage) -> list[Spec]:
    """Run one stage: the stages it needs first, its gates (a missing record refuses the stage, or ends it where the
    gate says so), its plan, its record (``--dry-run``: checked, not written), then its action or its runs (finished
    ones skipped; ``--dry-run``: listed with the time estimate) and what it writes from them. Returns the runs that
    failed, the first stages' included."""
    tree = ctx.tree  # a bad --tree is refused before anything is planned or recorded
    failed = [spec for first in stage.first for spec in run_stage(ctx, first)]
    records, missing = _records(ctx, stage)
    if missing is not None:
        if missing.stop:
            print(missing.missing(ctx))
            return failed
        raise SystemExit(missing.missing(ctx))
    dry = ctx.args.dry_run
    grids = list(stage.grids(ctx, *records)) if stage.grids is not None else []
    if stage.records is not None:
        recorded = stage.records.of(ctx) if stage.records.of is not None else grids[0]
        stage.records.check(ctx, recorded.name, recorded.specs(ctx.planner), records, record=not dry)
    if stage.action is not None:
        return failed + stage.action(ctx)
    if not grids:
        return failed
    if ctx.study.announce:
        print(f"\n== {stage.name} (scale {ctx.scale.name}: {ctx.scale.about})")
    specs = _in_order(ctx, stage.trains(ctx, grids, *records) if stage.trains is not None else grids)
    failed += execute(ctx.scale, specs, stage.jobs or ctx.jobs, dry, ctx.logs, tree=tree)
    if stage.then is not None:
        stage.then(ctx, specs)
    return failed
