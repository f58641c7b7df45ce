"""The ``tar-rl`` command: train, evaluate and compare TAR policies.

Sub-commands:

* ``tar-rl train [overrides] [--cfg job] [-m]``: the offline BC recipe (``recipes/offline_bc.py``),
  configured with Hydra overrides such as ``objective=uniform`` or ``objective.gamma=2``.
* ``tar-rl eval CHECKPOINT``: evaluate a saved policy on its suite (MetaWorld, dm_control or LIBERO).
* ``tar-rl report RUN_DIR...``: compare finished runs (tables and figures).
* ``tar-rl data import robomimic FILE... --obs-keys a,b,c``: robomimic/LIBERO HDF5 demonstrations into a
  dataset folder; ``tar-rl data import lerobot FOLDER``: a LeRobot dataset on local disk;
  ``tar-rl data info PATH``: a dataset folder's episodes, steps, entries and tasks; ``tar-rl data seal PATH``:
  record the content digest of a dataset folder that has none.
* ``tar-rl demo``: a short demonstration of the objective on toy data.

An error the user can cause or meet ends in one line naming what happened, where and what to do;
``--debug`` anywhere on the command line (or ``HYDRA_FULL_ERROR=1``) shows the whole traceback instead.
"""

from __future__ import annotations

import argparse
import os
import sys

from tar_rl.errors import DEBUG_ENV, debug_mode, one_line
from tar_rl.objectives import WEIGHTINGS


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="tar-rl", description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)
    commands.add_parser("train", help="train a policy (Hydra overrides follow; `tar-rl train --help` lists them)")
    commands.add_parser("report", help="compare finished runs (`tar-rl report --help`)")
    ev = commands.add_parser("eval", help="evaluate a saved policy on its suite (MetaWorld, dm_control or LIBERO)")
    ev.add_argument("checkpoint", help="a checkpoint.pt or a run directory holding one")
    ev.add_argument("--tasks", nargs="+", help="tasks or groups (default: the run's evaluation tasks)")
    ev.add_argument("--rollouts", type=int, help="rollouts per task (default: the run's)")
    ev.add_argument("--seed", type=int, help="base seed of the evaluation variations (default: the run's)")
    ev.add_argument("--horizon", type=int, help="steps per rollout (default: the run's)")
    ev.add_argument("--workers", type=int, help="evaluation processes (default: every core)")
    ev.add_argument("--out", help="CSV of the rollouts (default: eval-<seed>.csv beside the checkpoint)")
    ev.add_argument("--no-progress", action="store_true", help="no progress bar")
    data = commands.add_parser("data", help="import demonstrations, describe or seal a dataset folder")
    data_commands = data.add_subparsers(dest="data_command", required=True)
    imp = data_commands.add_parser("import", help="import demonstrations from another format")
    formats = imp.add_subparsers(dest="format", required=True, metavar="FORMAT")
    from tar_rl.importers import IMPORTERS

    for importer in IMPORTERS.values():
        p = formats.add_parser(importer.name, help=importer.help)
        importer.add_arguments(p)
        # what every import takes
        p.add_argument("--out", default="data", help="folder holding datasets (default: data)")
        p.add_argument("--chunk-horizon", type=int, default=8, help="H of action_chunk (default 8)")
        p.add_argument("--history", type=int, default=2, help="K of observation_history (default 2)")
        p.add_argument("--clip", action="store_true", help="clip actions outside [-1, 1] instead of refusing them")
    info = data_commands.add_parser("info", help="episodes, steps, entries, action range and tasks of a dataset")
    info.add_argument("path", help="a dataset folder (holding metadata.json and buffer/)")
    info.add_argument("--json", action="store_true", help="print JSON instead of text")
    seal = data_commands.add_parser(
        "seal", help="record the content digest of a dataset folder that has none (one whose content you trust)"
    )
    seal.add_argument("path", help="a dataset folder without digest.json")
    demo = commands.add_parser("demo", help="train a small policy with uniform and TAR weighting on toy data")
    demo.add_argument("--steps", type=int, default=600, help="optimiser steps per weighting (default 600)")
    demo.add_argument(
        "--weightings",
        nargs="+",
        default=["uniform", "tar"],
        choices=sorted(WEIGHTINGS),
        metavar="NAME",
        help=f"weightings to compare, from: {', '.join(WEIGHTINGS)} (default: uniform tar)",
    )
    demo.add_argument("--seed", type=int, default=0)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if "--debug" in argv:
        argv = [a for a in argv if a != "--debug"]
        os.environ[DEBUG_ENV] = "1"  # Hydra's switch for whole tracebacks, read by every command here
    # train and report parse their own arguments (Hydra's overrides; the report's options).
    if argv and argv[0] == "train":
        from tar_rl.recipes import hydra_main

        return hydra_main(argv[1:])
    if argv and argv[0] == "report":
        from tar_rl.report import main as report_main

        return report_main(argv[1:])
    args = _parser().parse_args(argv)
    if args.command == "eval":
        from tar_rl.recipes import ConfigError, evaluate_checkpoint

        try:
            evaluate_checkpoint(
                args.checkpoint,
                tasks=args.tasks,
                rollouts=args.rollouts,
                seed=args.seed,
                horizon=args.horizon,
                workers=args.workers,
                out=args.out,
                progress=not args.no_progress,
            )
        except (ConfigError, FileNotFoundError, ValueError) as err:
            if debug_mode():
                raise
            raise SystemExit(one_line("tar-rl eval", err)) from None
        return 0
    if args.command == "data":
        return _data_command(args)
    if args.command == "demo":
        from tar_rl.demo import DemoConfig, run

        if args.steps < 10:
            raise SystemExit(f"tar-rl demo: --steps must be at least 10, got {args.steps}")
        run(DemoConfig(steps=args.steps, weightings=tuple(args.weightings), seed=args.seed))
    return 0


def _data_command(args: argparse.Namespace) -> int:
    if args.data_command == "import":
        from tar_rl.errors import DiskFullError
        from tar_rl.importers import IMPORTERS, DemoImportError

        common = {"out": args.out, "chunk_horizon": args.chunk_horizon, "history": args.history, "clip": args.clip}
        try:
            IMPORTERS.get(args.format).run(args, **common)
        except (DemoImportError, DiskFullError) as err:
            if debug_mode():
                raise
            raise SystemExit(one_line(f"tar-rl data import {args.format}", err)) from None
        return 0
    import json

    from tar_rl.data import DatasetError, seal_dataset
    from tar_rl.importers import dataset_info, format_info

    command = f"tar-rl data {args.data_command}"
    try:
        if args.data_command == "seal":
            dataset = seal_dataset(args.path)
            print(f"{dataset.path}: recorded its content digest; later loads check its files against it")
            return 0
        info = dataset_info(args.path)
    except DatasetError as err:
        if debug_mode():
            raise
        raise SystemExit(one_line(command, err)) from None
    print(json.dumps(info, indent=2) if args.json else format_info(info))
    return 0
