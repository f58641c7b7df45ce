"""Helpers shared by the benchmark scripts: the commit measured and robust summaries of timings."""

from __future__ import annotations

import gc
import subprocess
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
# The columns of one timing summary in every benchmark CSV: median and IQR of the samples, their unit, the ratio
# of the median to the baseline variant's (side by side in one run), the baseline's name and the sample count.
SUMMARY_COLUMNS = ("median", "iqr", "unit", "ratio_to_baseline", "baseline", "n")


def git_commit() -> str:
    """The short hash of the checked-out commit, or ``"unknown"`` outside a git checkout."""
    try:
        out = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True, timeout=10, check=True
        )
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return out.stdout.strip() or "unknown"


def median_iqr(xs) -> tuple[float, float]:
    """Median and inter-quartile range of a sample."""
    q25, q50, q75 = np.percentile(np.asarray(xs, dtype=np.float64), [25, 50, 75])
    return float(q50), float(q75 - q25)


def interleaved(fns: dict, reps: int, seed: int, inner: int = 1, collect_every: int = 1) -> dict[object, np.ndarray]:
    """Per variant, ``reps`` samples of seconds per call; variants shuffled within each round.

    Each sample times ``inner`` consecutive calls and divides. The garbage collector is off while
    timing and runs every ``collect_every`` rounds, outside the timed region.
    """
    rng = np.random.default_rng(seed)
    names = list(fns)
    times = {name: np.empty(reps) for name in names}
    was_enabled = gc.isenabled()
    gc.disable()
    try:
        for r in range(reps):
            for i in rng.permutation(len(names)):
                name = names[i]
                fn = fns[name]
                start = time.perf_counter()
                for _ in range(inner):
                    fn()
                times[name][r] = (time.perf_counter() - start) / inner
            if r % collect_every == collect_every - 1:
                gc.collect()
    finally:
        if was_enabled:
            gc.enable()
    return times
