"""The paired comparison of arms with a baseline, and the fit and weight statistics of runs.

Runs pair by seed; a pair trained at different commits, machines or devices is refused
(:func:`check_pairs`). :func:`paired` gives one arm's paired statistics at a metric and level (the mean paired
difference, its 95% CI, the paired t-test's p and the minimum detectable effect), :func:`holm_into` the Holm
correction over a family of them.
"""

from __future__ import annotations

import io
import math
from collections.abc import Sequence

import pandas as pd

__all__ = [
    "FINAL_SHARE",
    "check_pairs",
    "final_train_mean",
    "finite_mean",
    "fit_means",
    "fit_summary",
    "holm_into",
    "paired",
]

# The share of the last training steps over which a run's weight statistics are averaged (as the final train loss).
FINAL_SHARE = 0.05


def check_pairs(runs: Sequence) -> None:
    """Refuse a pair (same setting and seed) whose runs were trained at different commits, on different machines or
    on different devices (``summary.json``'s ``machine.device``: a lent GPU machine may share a CPU machine's
    hostname)."""
    by_seed: dict[int, list] = {}
    for run in runs:
        by_seed.setdefault(run.seed, []).append(run)
    for seed, pair in sorted(by_seed.items()):
        commits = {r.summary.get("git_commit") for r in pair}
        hosts = {(r.summary.get("machine") or {}).get("hostname") for r in pair}
        devices = {(r.summary.get("machine") or {}).get("device") for r in pair}
        if len(commits) > 1 or len(hosts) > 1 or len(devices) > 1:
            names = ", ".join(r.name for r in pair)
            what = "commits" if len(commits) > 1 else "machines" if len(hosts) > 1 else "devices"
            raise SystemExit(f"studies: the pair of seed {seed} ({names}) was trained at different {what}; re-run one")


def paired(runs: Sequence, objective: str, metric: str = "success", level: str = "overall") -> dict:
    """The paired statistics of ``objective``'s runs against the baseline's among ``runs`` at ``metric`` and
    ``level`` (a row of :func:`tar_rl.report.paired_table`) with ``mde``, the minimum detectable effect."""
    from tar_rl.report import min_detectable_effect, paired_table

    table = paired_table(runs, objectives=[objective], file=io.StringIO())
    rec = table[(table["metric"] == metric) & (table["level"] == level)].iloc[0].to_dict()
    rec["mde"] = min_detectable_effect(rec["delta_std"], int(rec["n_pairs"]))
    return rec


def holm_into(rows: Sequence[dict], p_key: str, out_key: str = "holm_p") -> None:
    """Write the Holm-adjusted ``p_key`` of ``rows`` (one family) into each row's ``out_key``."""
    from tar_rl.report import holm

    for row, p in zip(rows, holm([r[p_key] for r in rows])):
        row[out_key] = p


def finite_mean(values) -> float:
    """The mean of the finite values among ``values`` (``None`` left out); ``nan`` when there is none."""
    values = [float(v) for v in values if v is not None and math.isfinite(float(v))]
    return sum(values) / len(values) if values else math.nan


def fit_means(runs: Sequence) -> dict[str, float]:
    """Means over ``runs`` of their summaries' fit diagnostics: ``passes``, ``train_loss`` (the final uniform
    training loss), ``heldout_loss`` and ``alignment`` (its Spearman correlation); ``nan`` where none has it."""
    fits = [r.summary.get("fit") or {} for r in runs]
    return {
        "passes": finite_mean(f.get("passes") for f in fits),
        "train_loss": finite_mean(f.get("final_uniform_loss") for f in fits),
        "heldout_loss": finite_mean((f.get("heldout") or {}).get("loss") for f in fits),
        "alignment": finite_mean((f.get("alignment") or {}).get("spearman") for f in fits),
    }


def final_train_mean(run, name: str) -> float | None:
    """The mean of a run's logged training metric ``name`` over its last :data:`FINAL_SHARE` of steps (``None``
    when it logged none there)."""
    m = run.metrics
    if m.empty or run.steps is None:
        return None
    rows = m[(m["phase"] == "train") & (m["name"] == name) & (m["step"] > (1 - FINAL_SHARE) * run.steps)]
    return float(rows["value"].mean()) if len(rows) else None


def fit_summary(runs: Sequence) -> dict[str, float]:
    """Means over ``runs``: the fit diagnostics of each run's summary (the final uniform training loss
    ``train_loss``, the held-out per-step loss ``heldout_loss``, the ``alignment``) and, over the last
    :data:`FINAL_SHARE` of training steps, the largest weight in a segment ``weight_max`` and the weights'
    effective-sample-size fraction ``weight_ess`` (from ``metrics.csv``); ``nan`` where none has it."""
    fit = fit_means(runs)
    out = {name: fit[name] for name in ("train_loss", "heldout_loss", "alignment")}
    for name in ("weight_max", "weight_ess"):
        out[name] = finite_mean(final_train_mean(r, name) for r in runs)
    return out


def fit_frame(groups: dict[str, Sequence], key: str, counted: bool = False) -> pd.DataFrame:
    """One :func:`fit_summary` row per group of runs (``key`` names the group's column; ``counted`` adds the
    number of runs as ``runs``)."""
    rows = []
    for name, runs in groups.items():
        rows.append({key: name, **({"runs": len(runs)} if counted else {}), **fit_summary(runs)})
    return pd.DataFrame(rows)
