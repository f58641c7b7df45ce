"""The paired comparison of arms with a baseline, and the fit and weight statistics of runs.

Runs pair by seed; a pair trained at different commits, machines or devices is refused
(:func:`check_pairs`). :func:`paired` gives one arm's paired statistics at a metric and level (the mean paired
difference, its 95% CI, the paired t-test's p and the minimum detectable effect), :func:`contrast` one pre-registered
comparison's row (success, Fast20, NEPS) and per-group rows, :func:`holm_into` the Holm correction over a family of
them; :func:`finished_runs` a planned stage's finished runs per arm and seed.
"""

from __future__ import annotations

import io
import math
from collections.abc import Sequence
from dataclasses import dataclass

import pandas as pd

__all__ = [
    "FINAL_SHARE",
    "Comparison",
    "check_pairs",
    "contrast",
    "contrasts",
    "final_train_mean",
    "finished_runs",
    "finite_mean",
    "fit_means",
    "fit_summary",
    "holm_into",
    "paired",
    "stage_fits",
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


def overall_success(run) -> float:
    """A finished run's overall success in percent (its final evaluation)."""
    from tar_rl.report import run_percent

    return run_percent(run)[("success", "overall")]


def contrast(label: str, treatment: Sequence, baseline: Sequence) -> tuple[dict, pd.DataFrame]:
    """One comparison's row (success, Fast20 and NEPS: means, the mean paired difference, its 95% CI, the paired
    t-test's p, the MDE at 80% power, pairs where the treatment is higher) and its per-group rows."""
    from tar_rl.report import min_detectable_effect, paired_table

    t_name, b_name = treatment[0].objective, baseline[0].objective
    paired = paired_table([*treatment, *baseline], baseline=b_name, objectives=[t_name], file=io.StringIO())
    row: dict = {"comparison": label}
    for metric in ("success", "fast20", "neps"):
        rec = paired[(paired["metric"] == metric) & (paired["level"] == "overall")].iloc[0]
        row[f"{metric}_treatment"], row[f"{metric}_baseline"] = rec["objective_mean"], rec["baseline_mean"]
        row[f"d_{metric}"] = rec["delta_mean"]
        row[f"d_{metric}_ci_low"], row[f"d_{metric}_ci_high"] = rec["ci_low"], rec["ci_high"]
        row[f"p_{metric}"] = rec["p_value"]
        if metric == "success":
            row["pairs"] = int(rec["n_pairs"])
            row["mde_success"] = min_detectable_effect(rec["delta_std"], int(rec["n_pairs"]))
    by_seed = {r.seed: overall_success(r) for r in baseline}
    row["higher"] = sum(overall_success(r) > by_seed[r.seed] for r in treatment)
    groups = paired[(paired["metric"] == "success") & (paired["level"] != "overall")].assign(comparison=label)
    return row, groups


@dataclass(frozen=True)
class Comparison:
    """``treatment - baseline`` in one stage; ``primary`` comparisons form the study's Holm family."""

    label: str
    stage: str
    treatment: str
    baseline: str
    primary: bool


def contrasts(comparisons: Sequence[Comparison], loaded: dict) -> tuple[list[dict], list[pd.DataFrame]]:
    """Every comparison of ``comparisons`` over the seeds both its arms have (``loaded``: per stage, the finished
    runs per arm and seed, :func:`finished_runs`), refused where a pair was trained at different commits, machines
    or devices (:func:`check_pairs`): the rows of :func:`contrast` with ``primary``, Holm over the primary ones present
    (``holm_p``), and their per-group rows."""
    rows, groups = [], []
    for c in comparisons:
        arms = loaded.get(c.stage) or {}
        if not arms:
            continue
        seeds = sorted(set(arms.get(c.treatment, {})) & set(arms.get(c.baseline, {})))
        if not seeds:
            continue
        treatment, baseline = [arms[c.treatment][s] for s in seeds], [arms[c.baseline][s] for s in seeds]
        check_pairs([*treatment, *baseline])
        row, group = contrast(c.label, treatment, baseline)
        rows.append({**row, "primary": c.primary})
        groups.append(group)
    holm_into([r for r in rows if r["primary"]], "p_success")
    return rows, groups


def stage_fits(loaded: dict) -> list[dict]:
    """The fit and weights (:func:`fit_summary`) of each stage's arms over the seeds every arm of the stage has
    (``loaded`` as :func:`contrasts`): ``stage``, ``arm``, ``seeds`` and the statistics."""
    fits = []
    for stage, arms in loaded.items():
        common = sorted(set.intersection(*(set(a) for a in arms.values()))) if arms else []
        for arm, by_seed in arms.items():
            if common:
                fits.append(
                    {"stage": stage, "arm": arm, "seeds": len(common)} | fit_summary([by_seed[s] for s in common])
                )
    return fits


def finished_runs(specs: dict, who: str, stage: str, complete: bool) -> tuple[dict[str, dict[int, object]], list[str]]:
    """A stage's finished runs per arm and seed (loaded; ``specs``: its planned runs per arm) and the names of its
    planned runs not finished, seed by seed.

    Raises:
        SystemExit: with ``complete``, a run of the plan is missing (``who`` names the study).
    """
    from benchmarks.studies.core import seed_major
    from tar_rl.report import load_run

    missing = [s.run_dir.name for s in seed_major(specs) if not s.finished]
    if complete and missing:
        raise SystemExit(f"{who}: {stage} misses {len(missing)} run(s) of its plan: {', '.join(missing)}")
    loaded = {arm: {s.config["seed"]: load_run(s.run_dir) for s in group if s.finished} for arm, group in specs.items()}
    return loaded, missing


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
