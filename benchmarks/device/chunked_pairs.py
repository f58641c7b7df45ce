"""Train whole seeds of a chunked-heads regime (R4, R5) on one machine, from the study's own code.

The regime study's runs are trained at one commit (the study's, recorded in ``PLAN.md``); this script drives
that commit's code, given as a folder (``--tree``), so that a lent machine with more cores and a GPU trains some
seeds of a regime while another machine trains others. A seed's three runs (``uniform``, ``tar``,
``tar_gentle``) are always trained here together, so every pair is trained on one machine, as the plan asks.

Usage (from the repository root, with the study's tree and its packages importable)::

    PYTHONPATH=STUDY_TREE python -P benchmarks/device/chunked_pairs.py --tree STUDY_TREE --regime r4 \
        --seeds 4,5,6,7 --out OUT --data-root DATA --jobs 6 [--scale cpu|ci]

A script run by its path with ``-P``, not a module of this checkout: ``python -m`` would put this checkout first
on the import path, and its ``tar_rl`` would shadow the tree's.

The plan's digest is checked against the one recorded when the regime's first run started (``--started``,
default the tree's ``benchmarks/results/regimes/chunked_started.json``) before anything is trained; a changed
plan is refused. Finished runs in ``OUT/runs`` are skipped, as by the study's own command.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path


def study_harness(tree: Path):
    """The study commit's regime study, its ``benchmarks/regimes.py`` loaded from its file as the module ``regimes``.

    That commit's harness is a folder of scripts that find each other beside themselves (``regimes.py`` imports
    ``paper_experiments.py``), and its ``tar_rl`` is the tree's, first on ``PYTHONPATH`` (the usage above); the
    module hands on what this driver uses (``Planner``, ``execute``, ``chunked_specs``, ``plan_digest``, ...).
    """
    import importlib.util

    spec = importlib.util.spec_from_file_location("regimes", tree / "benchmarks" / "regimes.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["regimes"] = module
    spec.loader.exec_module(module)
    return module


def seed_of(spec) -> int:
    """The training seed named in a run's overrides."""
    seeds = [int(o.split("=", 1)[1]) for o in spec.overrides if o.startswith("seed=")]
    if len(seeds) != 1:
        raise SystemExit(f"chunked_pairs: run {spec.run_dir.name} names {len(seeds)} seeds in its overrides")
    return seeds[0]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="chunked_pairs", description=__doc__.split("\n\n")[0])
    p.add_argument("--tree", required=True, help="the study commit's files (a checkout or an archive of it)")
    p.add_argument("--regime", required=True, choices=("r4", "r5"))
    p.add_argument("--seeds", required=True, help="comma-separated training seeds, each trained with all arms")
    p.add_argument("--out", required=True, help="results folder (runs in OUT/runs)")
    p.add_argument("--data-root", required=True, help="dataset cache folder")
    p.add_argument("--jobs", type=int, default=3, help="runs trained at once")
    p.add_argument("--scale", default="cpu", choices=("cpu", "ci"))
    p.add_argument(
        "--cores",
        type=int,
        default=None,
        help="cores shared by the runs' evaluation workers: each run evaluates with CORES // JOBS workers "
        "(default: this machine's cores; a setting outside the runs' identity)",
    )
    p.add_argument("--digest", action="store_true", help="print the plan's digest and exit")
    p.add_argument("--started", default=None, help="the plan record (default: the tree's chunked_started.json)")
    args = p.parse_args(argv)

    tree = Path(args.tree).resolve()
    if not (tree / "benchmarks" / "regimes.py").is_file():
        raise SystemExit(f"chunked_pairs: {tree} holds no benchmarks/regimes.py: not a checkout of the study")
    # The study commit's own harness, and its package for the training subprocesses (``python -m tar_rl``
    # imports from the working folder first, so they start in the tree, never in this checkout).
    out, data_root = Path(args.out).resolve(), Path(args.data_root).resolve()
    started_path = Path(args.started or tree / "benchmarks/results/regimes/chunked_started.json").resolve()
    os.chdir(tree)
    regimes = study_harness(tree)
    Planner, execute = regimes.Planner, regimes.execute

    study = regimes.STUDIES[args.scale]
    seeds = sorted({int(s) for s in args.seeds.split(",") if s.strip()})
    unknown = sorted(set(seeds) - set(study.scale.seeds))
    if not seeds or unknown:
        raise SystemExit(f"chunked_pairs: --seeds {args.seeds}: the plan's seeds are {list(study.scale.seeds)}")
    if args.jobs < 1:
        raise SystemExit(f"chunked_pairs: --jobs must be >= 1, got {args.jobs}")
    label = args.regime.upper()
    planner = Planner(study.scale, out, str(data_root))
    specs = regimes.chunked_specs(study, planner, label)
    recorded = json.loads(started_path.read_text()).get(label) if started_path.is_file() else None
    digest = regimes.plan_digest(specs)
    if args.digest:
        print(digest)
        return 0
    if recorded != digest:
        raise SystemExit(f"chunked_pairs: {label}'s plan digest is {digest}, the record {started_path} says {recorded}")
    todo = [s for s in regimes.seed_major(specs) if seed_of(s) in seeds]
    if args.cores is not None:
        if args.cores < 1:
            raise SystemExit(f"chunked_pairs: --cores must be >= 1, got {args.cores}")
        os.cpu_count = lambda: args.cores  # the study's execute() gives each run cpu_count() // jobs workers
    failed = execute(study.scale, todo, args.jobs, False, out / "logs")
    for spec in failed:
        print(f"FAILED {spec.run_dir.name}", flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
