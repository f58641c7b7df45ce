"""The studies' command line::

    python -m benchmarks.studies STUDY plan | run STAGE | table | collect --from DIR
                                 [--scale NAME] [--out DIR] [--data-root DIR] [--jobs N] [--seeds 0,1,..]
                                 [--tables DIR] [--dry-run] [the study's own options]

* ``plan``: every stage's runs that can be planned now (a gated stage once its record exists), done or to do;
* ``run STAGE``: train the stage's unfinished runs (``--dry-run``: print them and the time estimate);
* ``table``: the study's tables and figures from its finished runs, into ``--out`` or ``--tables DIR``;
* ``collect --from DIR``: copy the finished runs of a runs folder (a sweep trained elsewhere) into ``<out>/runs``
  (:func:`benchmarks.studies.records.collect`).

A study is a :class:`.stages.Study`: its scales, its stages (declarations, :class:`.stages.Stage`) and its table,
declared in its own module (:data:`STUDIES`); :func:`.stages.run_stage` runs any stage.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

from benchmarks.studies.core import Planner
from benchmarks.studies.stages import Context, Study, plan, run_stage

__all__ = ["RESULTS", "STUDIES", "context", "main"]

#: The committed results folder of the studies.
RESULTS = Path(__file__).resolve().parent.parent / "results"
#: The studies by name: the module that declares each (its ``STUDY``).
STUDIES = {
    "paper": "benchmarks.studies.paper",
    "regimes": "benchmarks.studies.regimes",
    "tuning": "benchmarks.studies.tuning",
    "baselines": "benchmarks.studies.baselines",
    "why_act": "benchmarks.studies.why_act",
    "flow_signal": "benchmarks.studies.flow_signal",
}
COMMANDS = ("plan", "run", "table", "collect")


def ints(text: str) -> tuple[int, ...]:
    """Comma-separated integers of an option."""
    try:
        values = tuple(int(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None
    if not values:
        raise argparse.ArgumentTypeError("expected at least one integer")
    return values


def with_seeds(sizes: Any, args: argparse.Namespace) -> Any:
    """``sizes`` whose scale trains ``--seeds`` where given (the studies whose only option that is)."""
    if args.seeds is None:
        return sizes
    return replace(sizes, scale=replace(sizes.scale, seeds=args.seeds))


def names(text: str) -> tuple[str, ...]:
    """Comma-separated names of an option."""
    values = tuple(v.strip() for v in text.split(",") if v.strip())
    if not values:
        raise argparse.ArgumentTypeError("expected at least one name")
    return values


def load(name: str) -> Study:
    """The study called ``name``, refused naming the known ones."""
    if name not in STUDIES:
        raise SystemExit(f"studies: no study {name!r}; choose one of {', '.join(STUDIES)}")
    return importlib.import_module(STUDIES[name]).STUDY


def parser(study: Study) -> argparse.ArgumentParser:
    """The command line of ``study``: the options every study shares, then its own."""
    p = argparse.ArgumentParser(prog=f"python -m benchmarks.studies {study.name}", description=study.about)
    p.add_argument("command", choices=COMMANDS)
    p.add_argument("stage", nargs="?", default=None, help=f"run: one of {', '.join(study.stages)}")
    p.add_argument("--scale", default="cpu", help=f"one of {sorted(study.scales)} (default: cpu)")
    p.add_argument("--out", default=None, help="results folder (default: the study's folder in benchmarks/results)")
    p.add_argument("--data-root", default="datasets", help="dataset cache folder (default: ./datasets)")
    p.add_argument("--jobs", type=int, default=None, help="runs trained at once (default: the scale's)")
    p.add_argument("--seeds", type=ints, default=None, help="override the seeds (default: the scale's)")
    p.add_argument("--from", dest="source", default=None, help="collect: the runs folder to copy finished runs from")
    p.add_argument("--tables", default=None, help="table: write the tables here instead of into --out")
    p.add_argument("--dry-run", action="store_true", help="run: print the plan and the time estimate; run nothing")
    study.options(p)
    return p


def context(study: Study, argv: list[str]) -> Context:
    """The parsed and checked command line of ``study``."""
    args = parser(study).parse_args(argv)
    if args.scale not in study.scales:
        raise SystemExit(f"studies: --scale={args.scale!r} is not valid; choose one of {sorted(study.scales)}")
    sizes = study.with_options(study.scales[args.scale], args)
    scale = sizes.scale
    jobs = scale.jobs if args.jobs is None else args.jobs
    if jobs < 1:
        raise SystemExit(f"studies: --jobs must be >= 1, got {jobs}")
    default = study.results(args.scale)
    if args.out is None and default is None:
        raise SystemExit(f"studies: --out is required with --scale {args.scale} (the default folder holds the results)")
    out = Path(args.out) if args.out else RESULTS / default
    planner = Planner(scale, out, args.data_root, getattr(args, "set", ()))
    return Context(study, args, [study.name, *argv], sizes, scale, planner, out, jobs)


def print_plan(ctx: Context) -> None:
    """Every stage's planned runs, finished or to run."""
    for stage, specs in plan(ctx).items():
        done = sum(s.finished for s in specs)
        print(f"{stage}: {len(specs)} runs, {done} finished")
        for s in specs:
            print(f"  {'done' if s.finished else 'todo'} {s.run_dir.name}")


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point (module docstring). Returns 0, or 1 when a run failed (the others still ran)."""
    from benchmarks.studies.records import collect

    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0].startswith("-"):
        raise SystemExit(f"usage: python -m benchmarks.studies STUDY COMMAND ...; studies: {', '.join(STUDIES)}")
    study = load(argv[0])
    ctx = context(study, argv[1:])
    command, stage = ctx.args.command, ctx.args.stage
    if command != "run" and stage is not None:
        raise SystemExit(f"studies: {command} takes no stage (got {stage!r})")
    if command == "plan":
        print_plan(ctx)
    elif command == "collect":
        if not ctx.args.source:
            raise SystemExit(f"studies: {study.name} collect needs --from DIR (a runs folder)")
        copied = collect(
            Path(ctx.args.source),
            ctx.out,
            keep_checkpoint=study.keep_checkpoint(ctx),
            keep_weights=study.keep_weights(ctx),
        )
        print(f"copied {len(copied)} finished run(s) into {ctx.out / 'runs'}: " + ", ".join(copied))
    elif command == "table":
        study.table(ctx)
    else:
        if stage not in study.stages:
            raise SystemExit(f"studies: {study.name} run needs a stage, one of {', '.join(study.stages)}")
        failed = run_stage(ctx, study.stages[stage])
        if failed:
            print(f"\n{len(failed)} run(s) failed: " + ", ".join(s.run_dir.name for s in failed))
            return 1
    return 0
