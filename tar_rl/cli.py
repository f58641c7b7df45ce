"""The ``tar-rl`` command.

``tar-rl demo`` runs a short demonstration of the objective. Training, evaluation and report
commands arrive with the recipes.
"""

from __future__ import annotations

import argparse

from tar_rl.objectives import WEIGHTINGS


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="tar-rl", description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)
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
    args = _parser().parse_args(argv)
    if args.command == "demo":
        from tar_rl.demo import DemoConfig, run

        if args.steps < 10:
            raise SystemExit(f"tar-rl demo: --steps must be at least 10, got {args.steps}")
        run(DemoConfig(steps=args.steps, weightings=tuple(args.weightings), seed=args.seed))
    return 0
