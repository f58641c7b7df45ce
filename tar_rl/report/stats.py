"""Statistics over loaded runs: pooling over seeds (:func:`compare`) and paired differences over matched seeds.

* :func:`compare` pools finished runs over seeds, one row per (policy, objective): mean and std of
  success, Fast20 and NEPS in percent (overall and per difficulty group), and the paired difference
  of each objective to :data:`BASELINE` over matched seeds.
* :func:`paired_table` gives, per policy, objective, metric and level, the paired differences to the
  baseline with :func:`paired_t`'s 95% CI and t-test; :func:`holm` adjusts a family of p-values and
  :func:`min_detectable_effect` sizes what a paired test can detect.
* :func:`run_percent` is one run's final metrics in ``100 x`` units.
"""

from __future__ import annotations

import math
import statistics
import sys
from collections.abc import Sequence
from typing import IO, Any

import pandas as pd

from tar_rl.metrics import DEFAULT_GROUP_ORDER, METRIC_COLUMNS, as_percent
from tar_rl.report.load import NOT_EVALUATED, Run

__all__ = [
    "BASELINE",
    "OBJECTIVE_ORDER",
    "PAIRED_COLUMNS",
    "compare",
    "holm",
    "min_detectable_effect",
    "objective_key",
    "paired_t",
    "paired_table",
    "run_percent",
    "table_levels",
]


#: Row order of the objectives in tables and legends; other objectives follow alphabetically.
OBJECTIVE_ORDER: tuple[str, ...] = ("uniform", "tar", "shuffle", "random", "invert", "perturb_high", "perturb_low")


#: The baseline of the paired differences.
BASELINE = "uniform"


#: Columns of :func:`paired_table`.
PAIRED_COLUMNS: tuple[str, ...] = (
    "policy",
    "baseline",
    "objective",
    "metric",
    "level",
    "n_pairs",
    "seeds",
    "baseline_mean",
    "baseline_std",
    "objective_mean",
    "objective_std",
    "delta_mean",
    "delta_std",
    "ci_low",
    "ci_high",
    "t",
    "p_value",
)


def objective_key(name: str) -> tuple[int, str]:
    return (OBJECTIVE_ORDER.index(name) if name in OBJECTIVE_ORDER else len(OBJECTIVE_ORDER), name)


def _mean(values: Sequence[float]) -> float:
    """Mean that handles ``inf`` without numpy warnings: ``nan`` if a value is nan or infs of both signs."""
    if not values or any(math.isnan(v) for v in values):
        return math.nan
    infs = {v for v in values if math.isinf(v)}
    if infs:
        return infs.pop() if len(infs) == 1 else math.nan
    return statistics.fmean(values)


def _std(values: Sequence[float]) -> float:
    """Sample standard deviation (ddof = 1); ``nan`` for one value or any non-finite value."""
    if len(values) < 2 or not all(math.isfinite(v) for v in values):
        return math.nan
    return statistics.stdev(values)


def _check_comparable(runs: Sequence[Run]) -> None:
    first = runs[0]
    for run in runs[1:]:
        for key, ref in first.eval_settings.items():
            value = run.eval_settings.get(key)
            if value == ref:
                continue
            if key == "tasks":
                only_first = sorted(set(ref) - set(value or ()))
                only_run = sorted(set(value or ()) - set(ref))
                raise ValueError(
                    f"runs evaluated on different task sets cannot be compared: {first.name} ({first.path}) has "
                    f"{len(ref)} tasks, {run.name} ({run.path}) has {len(value or ())}; only in the first: "
                    f"{only_first}, only in the second: {only_run}"
                )
            raise ValueError(
                f"runs evaluated with different settings cannot be compared: {key} is {ref!r} in {first.name} "
                f"({first.path}) but {value!r} in {run.name} ({run.path})"
            )


def _check_unique(runs: Sequence[Run]) -> None:
    seen: dict[tuple, Run] = {}
    for run in runs:
        key = (run.policy, run.objective, run.seed)
        if key in seen:
            other = seen[key]
            raise ValueError(
                f"two runs with policy {run.policy!r}, objective {run.objective!r} and seed {run.seed}: "
                f"{other.path} and {run.path}; they would be pooled as one seed. Report them separately."
            )
        seen[key] = run


def _levels(runs: Sequence[Run]) -> list[str]:
    groups = list(dict.fromkeys(n for r in runs for n in r.final.loc[r.final["level"] == "group", "name"]))
    ordered = [g for g in DEFAULT_GROUP_ORDER if g in groups] + [g for g in groups if g not in DEFAULT_GROUP_ORDER]
    return ["overall", *ordered]


def _percent_values(run: Run) -> dict[tuple[str, str], float]:
    """``(metric, level name) -> value`` in percent, for the overall and group rows of a run's final table."""
    table = as_percent(run.final[run.final["level"] != "task"])
    return {(m, rec["name"]): float(rec[m]) for rec in table.to_dict("records") for m in METRIC_COLUMNS}


def compare(runs: Sequence[Run], file: IO[str] | None = None) -> pd.DataFrame:
    """Pool finished runs over seeds: one row per (policy, objective), in percent.

    Unfinished runs are left out, each with a note printed to ``file`` (default: standard output) and
    listed in ``table.attrs["excluded"]``.

    Columns: ``policy``, ``objective``, ``n_seeds``, ``seeds`` (comma-separated), ``runs`` and
    ``git_commits`` (semicolon-separated, for provenance); for each level ``L`` in ``overall`` and the
    difficulty groups present (``easy``, ``medium``, ``hard``, ``very_hard``, then any other group) and
    each metric ``M`` in ``success``, ``fast20``, ``neps``: ``M_L_mean`` and ``M_L_std``, the mean and
    the sample standard deviation (ddof 1; ``nan`` with one seed or a non-finite value) over seeds of
    ``100 x`` the metric. Then the paired differences to ``uniform`` of the same policy over the seeds
    both have: ``n_pairs`` and ``delta_success``, ``delta_fast20``, ``delta_neps``, the mean over
    those seeds of (objective - uniform) of the overall metric, in percentage points (``nan`` and
    ``n_pairs = 0`` for ``uniform`` itself and where no seed is shared).

    Args:
        runs: loaded runs (:func:`~tar_rl.report.load_run`).
        file: where to print the notes on unfinished runs.

    Returns:
        The comparison table, sorted by policy and then objective (``uniform``, ``tar``, the controls).

    Raises:
        ValueError: no finished run; finished runs evaluated on different task sets or with a different
            evaluation seed, rollouts per task or horizon (the message names the setting and the runs);
            two finished runs with the same policy, objective and seed.
    """
    out = sys.stdout if file is None else file
    done = [r for r in runs if r.finished]
    excluded = [r for r in runs if not r.finished]
    for run in excluded:
        reason = "; ".join(n for n in run.notes if n.startswith(("unfinished", NOT_EVALUATED))) or "unfinished"
        print(f"note: {run.name} ({run.path}) is left out of the comparison: {reason}", file=out)
    if not done:
        raise ValueError("no finished run to compare" + (f" ({len(excluded)} unfinished)" if excluded else ""))
    _check_comparable(done)
    _check_unique(done)
    levels = _levels(done)
    values = {id(r): _percent_values(r) for r in done}

    by_key: dict[tuple[str, str], list[Run]] = {}
    for run in done:
        by_key.setdefault((run.policy, run.objective), []).append(run)
    keys = sorted(by_key, key=lambda k: (k[0], objective_key(k[1])))

    rows = []
    for policy, objective in keys:
        members = sorted(by_key[(policy, objective)], key=lambda r: r.seed)
        row: dict[str, Any] = {
            "policy": policy,
            "objective": objective,
            "n_seeds": len(members),
            "seeds": ",".join(str(r.seed) for r in members),
            "runs": ";".join(r.name for r in members),
            "git_commits": ";".join(dict.fromkeys(str(r.git_commit or "unknown") for r in members)),
        }
        for level in levels:
            for metric in METRIC_COLUMNS:
                vals = [values[id(r)][(metric, level)] for r in members if (metric, level) in values[id(r)]]
                row[f"{metric}_{level}_mean"] = _mean(vals)
                row[f"{metric}_{level}_std"] = _std(vals)
        baseline = {r.seed: r for r in by_key.get((policy, BASELINE), [])}
        pairs = [(r, baseline[r.seed]) for r in members if objective != BASELINE and r.seed in baseline]
        row["n_pairs"] = len(pairs)
        for metric in METRIC_COLUMNS:
            deltas = [values[id(a)][(metric, "overall")] - values[id(b)][(metric, "overall")] for a, b in pairs]
            row[f"delta_{metric}"] = _mean(deltas)
        rows.append(row)
    table = pd.DataFrame(rows)
    table.attrs["excluded"] = [r.name for r in excluded]
    return table


def table_levels(table: pd.DataFrame) -> list[str]:
    """The levels (``overall``, then groups) of a :func:`compare` table, from its ``success_<level>_mean`` columns."""
    prefix, suffix = "success_", "_mean"
    return [c[len(prefix) : -len(suffix)] for c in table.columns if c.startswith(prefix) and c.endswith(suffix)]


def run_percent(run: Run) -> dict[tuple[str, str], float]:
    """A finished run's final metrics in ``100 x`` units: ``(metric, level) -> value``, level ``overall`` or a group."""
    if run.final is None:
        raise ValueError(f"{run.name} ({run.path}) has no final evaluation")
    return _percent_values(run)


def paired_t(deltas: Sequence[float], confidence: float = 0.95) -> dict[str, float]:
    """Paired t statistics of per-seed differences (treatment - baseline).

    Args:
        deltas: one difference per matched seed, shape ``[n]``; all finite.
        confidence: level of the two-sided confidence interval of the mean difference.

    Returns:
        ``n``; ``mean``; ``std`` (sample, ddof 1); ``ci_low`` and ``ci_high``, the interval
        ``mean -+ t_{(1 + confidence) / 2, n - 1} * std / sqrt(n)``; ``t = mean / (std / sqrt(n))`` and
        the two-sided ``p_value`` of the paired t-test (H0: mean difference 0). With ``n < 2`` every
        entry but ``n`` and ``mean`` is ``nan``. With ``std = 0`` the interval is the point
        ``[mean, mean]``; ``t`` is ``+-inf`` and ``p = 0`` for a non-zero mean, ``t = nan`` and
        ``p = 1`` for a zero one.

    Raises:
        ValueError: a non-finite difference, or a confidence outside (0, 1).
    """
    from scipy import stats

    if not 0 < confidence < 1:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    values = [float(d) for d in deltas]
    if not all(math.isfinite(v) for v in values):
        raise ValueError(f"paired differences must be finite, got {values}")
    n = len(values)
    nan = math.nan
    out = {"n": n, "mean": statistics.fmean(values) if n else nan}
    out.update(std=nan, ci_low=nan, ci_high=nan, t=nan, p_value=nan)
    if n < 2:
        return out
    std = statistics.stdev(values)
    mean = out["mean"]
    out["std"] = std
    if std == 0:
        out.update(ci_low=mean, ci_high=mean, t=math.copysign(math.inf, mean) if mean else nan)
        out["p_value"] = 0.0 if mean else 1.0
        return out
    se = std / math.sqrt(n)
    q = float(stats.t.ppf((1 + confidence) / 2, n - 1))
    t = mean / se
    out.update(ci_low=mean - q * se, ci_high=mean + q * se, t=t, p_value=float(2 * stats.t.sf(abs(t), n - 1)))
    return out


def holm(p_values: Sequence[float]) -> list[float]:
    """Holm-Bonferroni adjusted p-values of a family of tests, in the order given.

    With the ``m`` p-values sorted ascending, ``p_(i)`` becomes ``max_{j <= i} min(1, (m - j + 1) p_(j))``
    (1-based ``j``). ``nan`` entries are left out of the family and stay ``nan``.
    """
    values = [float(p) for p in p_values]
    present = sorted((p, i) for i, p in enumerate(values) if not math.isnan(p))
    m = len(present)
    out = [math.nan] * len(values)
    running = 0.0
    for rank, (p, i) in enumerate(present):
        running = max(running, min(1.0, (m - rank) * p))
        out[i] = running
    return out


def min_detectable_effect(std: float, n: int, alpha: float = 0.05, power: float = 0.8) -> float:
    """The smallest true mean paired difference a two-sided paired t-test detects with ``power``.

    ``(t_{1 - alpha/2, n-1} + t_{power, n-1}) * std / sqrt(n)`` (the usual approximation with the
    observed spread ``std`` of the differences and ``n`` pairs); ``nan`` with fewer than 2 pairs.
    """
    from scipy import stats

    if not 0 < alpha < 1 or not 0 < power < 1:
        raise ValueError(f"alpha and power must lie in (0, 1), got {alpha}, {power}")
    if n < 2 or not math.isfinite(std):
        return math.nan
    q = float(stats.t.ppf(1 - alpha / 2, n - 1)) + float(stats.t.ppf(power, n - 1))
    return q * std / math.sqrt(n)


def paired_table(
    runs: Sequence[Run], baseline: str = BASELINE, objectives: Sequence[str] | None = None, file: IO[str] | None = None
) -> pd.DataFrame:
    """Paired comparison of objectives to a baseline over matched seeds, per policy, metric and level.

    For each policy, each objective other than ``baseline`` (or those in ``objectives``), each metric
    (``success``, ``fast20``, ``neps``, in ``100 x`` units) and each level (``overall`` and the
    difficulty groups), the seeds both runs have and where both values are finite are paired; the
    row gives the means and sample stds of both over those seeds, and :func:`paired_t` of the
    differences (objective - baseline). Unfinished runs are left out with a note (see :func:`compare`).

    Args:
        runs: loaded runs.
        baseline: the objective differences are taken to.
        objectives: the objectives to compare (default: every other one present).
        file: where notes on unfinished runs are printed.

    Returns:
        One row per (policy, objective, metric, level), columns :data:`PAIRED_COLUMNS`; ``seeds``
        lists the paired seeds (comma-separated). A cell without pairs has ``n_pairs = 0`` and ``nan``.

    Raises:
        ValueError: as :func:`compare` (no finished run, runs evaluated differently, duplicate seeds).
    """
    out = sys.stdout if file is None else file
    done = [r for r in runs if r.finished]
    for run in runs:
        if not run.finished:
            print(f"note: {run.name} ({run.path}) is left out: {'; '.join(run.notes) or 'unfinished'}", file=out)
    if not done:
        raise ValueError("no finished run to compare")
    _check_comparable(done)
    _check_unique(done)
    levels = _levels(done)
    values = {id(r): _percent_values(r) for r in done}
    rows = []
    for policy in sorted({r.policy for r in done}):
        mine = [r for r in done if r.policy == policy]
        base = {r.seed: r for r in mine if r.objective == baseline}
        present = sorted({r.objective for r in mine if r.objective != baseline}, key=objective_key)
        for objective in present if objectives is None else [o for o in objectives if o in present]:
            treat = {r.seed: r for r in mine if r.objective == objective}
            shared = sorted(set(base) & set(treat))
            for metric in METRIC_COLUMNS:
                for level in levels:
                    key = (metric, level)
                    pairs = [
                        (s, values[id(base[s])].get(key, math.nan), values[id(treat[s])].get(key, math.nan))
                        for s in shared
                    ]
                    pairs = [(s, b, t) for s, b, t in pairs if math.isfinite(b) and math.isfinite(t)]
                    stats_ = paired_t([t - b for _, b, t in pairs])
                    rows.append(
                        {
                            "policy": policy,
                            "baseline": baseline,
                            "objective": objective,
                            "metric": metric,
                            "level": level,
                            "n_pairs": len(pairs),
                            "seeds": ",".join(str(s) for s, _, _ in pairs),
                            "baseline_mean": _mean([b for _, b, _ in pairs]),
                            "baseline_std": _std([b for _, b, _ in pairs]),
                            "objective_mean": _mean([t for _, _, t in pairs]),
                            "objective_std": _std([t for _, _, t in pairs]),
                            "delta_mean": stats_["mean"],
                            "delta_std": stats_["std"],
                            "ci_low": stats_["ci_low"],
                            "ci_high": stats_["ci_high"],
                            "t": stats_["t"],
                            "p_value": stats_["p_value"],
                        }
                    )
    return pd.DataFrame(rows, columns=list(PAIRED_COLUMNS))
