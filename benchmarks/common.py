"""Helpers shared by the benchmark scripts: the commit measured and robust summaries of timings."""

from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent


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
