"""``tar-rl report RUN_DIR... [--out DIR]``: print the runs and their comparison, write the CSV and figures."""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

import pandas as pd

from tar_rl.errors import one_line
from tar_rl.io import write_csv_atomic
from tar_rl.report.load import expand_run_dirs, load_run
from tar_rl.report.plots import plot_group_bars, plot_success_vs_neps, plot_weights
from tar_rl.report.stats import BASELINE, compare
from tar_rl.report.tables import display_comparison, display_pairs, runs_table

__all__ = ["main"]


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="tar-rl report",
        description="Compare training runs: a table per run, the comparison pooled over seeds, and figures.",
    )
    parser.add_argument(
        "runs", nargs="+", metavar="RUN_DIR", help="run directories, or folders holding run directories (a sweep)"
    )
    parser.add_argument("--out", metavar="DIR", help="folder for comparison.csv and the figures (default: ./report)")
    return parser


def _file_stem(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name) or "run"


def _print_frame(df: pd.DataFrame) -> None:
    print(df.to_string(index=False) if len(df) else "(none)")


def main(argv: list[str] | None = None) -> int:
    """``tar-rl report RUN_DIR... [--out DIR]``.

    Loads the runs (a folder holding run directories is expanded to them), prints one line per run
    (objective, policy, seed, overall success, 100 x Fast20, 100 x NEPS), notes on unfinished runs,
    the comparison pooled over seeds and the paired differences to ``uniform``; writes
    ``comparison.csv``, ``success_vs_neps.png``, ``group_success.png`` and ``weights_<run>.png`` for
    each run with ``weights.csv`` into ``--out``. With no finished run it prints the runs, writes
    only the weight figures and ends with a line saying so, returning 1.

    Args:
        argv: the arguments after ``report`` (default: ``sys.argv[1:]``).

    Returns:
        0, or 1 when no run is finished (nothing was compared).

    Raises:
        SystemExit: bad arguments, a bad run directory or runs that cannot be compared (the message says why).
    """
    args = _parser().parse_args(argv)
    out_dir = Path(args.out) if args.out else Path.cwd() / "report"
    try:
        runs = [load_run(p) for p in expand_run_dirs(args.runs)]
    except ValueError as err:
        raise SystemExit(one_line("tar-rl report", err)) from None

    print(f"{len(runs)} run(s):")
    _print_frame(runs_table(runs))
    for run in runs:
        for note in run.notes:
            if run.finished:  # the unfinished ones are noted by compare()
                print(f"note: {run.name}: {note}")
    written: list[Path] = []
    print()
    if any(r.finished for r in runs):
        try:
            table = compare(runs)
        except ValueError as err:
            raise SystemExit(one_line("tar-rl report", err)) from None
        print("\nComparison over seeds (mean ± std; success %, 100 x Fast20, 100 x NEPS; lower cost is better):")
        _print_frame(display_comparison(table))
        print(f"\nPaired differences to {BASELINE} over matched seeds (objective - {BASELINE}, overall):")
        _print_frame(display_pairs(table))
        written.append(write_csv_atomic(table, out_dir / "comparison.csv"))
        written.append(plot_success_vs_neps(table, out_dir / "success_vs_neps.png"))
        written.append(plot_group_bars(table, out_dir / "group_success.png"))
    else:
        for run in runs:
            print(f"note: {run.name} ({run.path}): {'; '.join(run.notes)}")
    used: set[str] = set()
    for run in runs:
        if run.weights is None:
            continue
        stem = _file_stem(run.name)
        while stem in used:
            stem += "_"
        used.add(stem)
        commit = (run.git_commit or "unknown")[:10]
        written.append(
            plot_weights(run.weights, out_dir / f"weights_{stem}.png", caption=f"run {run.name} | git: {commit}")
        )
    if written:
        print("\nwrote: " + ", ".join(str(p) for p in written))
    if not any(r.finished for r in runs):
        print(
            f"tar-rl report: no finished run among the {len(runs)} run(s) of {' '.join(args.runs)}: nothing to "
            "compare; let the runs finish (run a stopped run's tar-rl train command again to resume it)",
            file=sys.stderr,
        )
        return 1
    return 0
