"""The temporal weightings from the literature beside TAR in the regime study's R3 (``results/regimes/PLAN.md``,
"Baselines in R3"), as a study.

Stage ``baselines`` (``python -m benchmarks.studies baselines run baselines``): first uniform's seed-0 run again
(the reproduction check below), then every baseline (``tilted``, ``truncate``, ``keyframe``, ``focal``,
``dro_time``; ``--weightings`` picks) at its default settings with R3's settings, seed by seed; with ``--uniform``
also every uniform seed (needed when the check fails).

``table``: Table III extended with the baselines (success per difficulty group and overall, the paired difference
of the overall success to uniform with its 95% CI and p, Holm over the baseline rows), beside R3's uniform and TAR
rows, recomputed from the runs (``table.md``, ``table.csv``, ``paired.csv``, ``fit.csv``). ``collect`` keeps no
``weights.csv``: no analysis of the baselines reads one.

**Pairing with R3's uniform runs.** The baselines are trained at a later commit than R3's runs, and the study
pairs only runs of one commit and machine. Training is deterministic on the CPU, so the stage trains uniform's
seed 0 again at the baselines' commit: when its per-rollout results equal those of R3's committed seed-0 run,
the code paths the uniform runs take have not changed and the baselines pair with R3's uniform runs; otherwise
``table`` refuses that pairing and the uniform runs are trained again beside the baselines (``--uniform``).
"""

from __future__ import annotations

import argparse
import io
import math
from dataclasses import replace
from pathlib import Path

import pandas as pd

from benchmarks.studies import regimes
from benchmarks.studies.cli import RESULTS
from benchmarks.studies.compare import FINAL_SHARE, check_pairs, fit_frame, holm_into
from benchmarks.studies.core import Arm, Grid, Planner, Spec
from benchmarks.studies.protocol import BASELINE, TREATMENT
from benchmarks.studies.records import provenance, reproduces
from benchmarks.studies.stages import Context, Stage, Study, named, plan
from benchmarks.studies.writers import controls_markdown, fit_markdown, fmt_p, write_outputs

__all__ = ["STAGES", "STUDY", "WEIGHTINGS", "fit_table", "table_markdown"]

WEIGHTINGS = ("tilted", "truncate", "keyframe", "focal", "dro_time")


def baselines_grid(sizes: regimes.RegimeSizes, weightings=WEIGHTINGS) -> Grid:
    """The baselines' runs at R3's settings and seeds."""
    arms = tuple(Arm.objective(w) for w in weightings)
    return Grid("baselines", "the literature's weightings in R3", sizes.r3, arms, sizes.scale.seeds)


def uniform_grid(sizes: regimes.RegimeSizes) -> Grid:
    """Uniform's runs at R3's settings and seeds, trained beside the baselines."""
    return Grid("uniform", "uniform beside the baselines", sizes.r3, (Arm.objective(BASELINE),), sizes.scale.seeds)


def r3_runs(sizes: regimes.RegimeSizes, regimes_out: Path) -> dict[str, list[Spec]]:
    """R3's committed runs (uniform and TAR) as the regime study plans them, by objective."""
    return regimes.r3_grid(sizes).specs(Planner(sizes.scale, regimes_out, "datasets"))


def fit_table(runs: list) -> pd.DataFrame:
    """Per objective, :func:`~benchmarks.studies.compare.fit_summary` of its finished runs (with their number)."""
    groups = {o: [r for r in runs if r.objective == o and r.finished] for o in dict.fromkeys(r.objective for r in runs)}
    return fit_frame(groups, "objective", counted=True)


def _holm_lines(paired: pd.DataFrame, index) -> list[str]:
    lines = [
        "| objective | pairs | Δ overall vs uniform | p | Holm p (over the baselines) | MDE (80%) |",
        "|---|---|---|---|---|---|",
    ]
    for rec in paired.loc[index].to_dict("records"):
        lines.append(
            f"| {rec['objective']} | {rec['n_pairs']} | {rec['delta_mean']:+.2f} | {fmt_p(rec['p_value'])} | "
            f"{fmt_p(rec['holm_p'])} | {'-' if math.isnan(rec['mde']) else format(rec['mde'], '.2f')} |"
        )
    return lines


def table_markdown(runs: list, uniform_source: str, reproduction: str) -> tuple[str, dict[str, pd.DataFrame]]:
    """Table III with the baselines: markdown and the tables ``table.csv`` (the compare table), ``paired.csv``
    (the paired table with Holm over the baselines and the MDE) and ``fit.csv`` (:func:`fit_table`)."""
    from tar_rl.report import compare, min_detectable_effect, paired_table

    done = [r for r in runs if r.finished]
    fit = fit_table(done)
    summary = compare(done, file=io.StringIO())
    paired = paired_table(done, file=io.StringIO())
    overall = paired[(paired["metric"] == "success") & (paired["level"] == "overall")]
    rows = overall[overall["objective"].isin(WEIGHTINGS)]
    paired["holm_p"] = math.nan
    paired["mde"] = math.nan
    adjusted = [{"p": p} for p in rows["p_value"]]
    holm_into(adjusted, "p")
    for index, rec in zip(rows.index, adjusted):
        paired.loc[index, "holm_p"] = rec["holm_p"]
    for index, rec in overall.iterrows():
        paired.loc[index, "mde"] = min_detectable_effect(rec["delta_std"], int(rec["n_pairs"]))
    md = [
        "# Table III extended: the baselines from the literature in R3",
        "",
        "R3's settings (MT50, 50 demonstrations per task, about 20 passes, 20 rollouts per task at seed 1000). "
        "Success % (mean ± std over seeds) per difficulty group and overall, and the paired difference of the "
        "overall success to uniform (95% CI, paired t-test). Every weighting at its default settings.",
        "",
        f"Uniform and TAR rows: {uniform_source} ({reproduction}).",
        "",
        controls_markdown(paired, summary, done[0].policy),
        "",
        *_holm_lines(paired, rows.index),
        "",
        f"Fit and weights, means over each objective's runs: the final uniform training loss and the held-out "
        f"per-step loss (each run's `summary.json`, `fit`), the alignment (Spearman correlation over ten bins of "
        f"episode time between the weight on training demonstrations and the held-out loss), and over the last "
        f"{FINAL_SHARE:.0%} of training steps the largest weight in a segment and the effective-sample-size "
        f"fraction of the weights (1 = uniform).",
        "",
        *fit_markdown(fit, ("objective", "runs")),
    ]
    return "\n".join(md) + "\n", {"table.csv": summary, "paired.csv": paired, "fit.csv": fit}


def _uniform_first(ctx: Context, grids: list[Grid]) -> list[Grid]:
    """Uniform's seed 0 (the reproduction check), every uniform seed with ``--uniform``, then the baselines."""
    uniform, baselines = grids
    return [uniform if ctx.args.uniform else replace(uniform, seeds=uniform.seeds[:1]), baselines]


STAGES = named(
    Stage(
        "baselines",
        "uniform's seed 0 again (every seed with --uniform), then the baselines, seed by seed",
        grids=lambda ctx: [uniform_grid(ctx.sizes), baselines_grid(ctx.sizes, ctx.args.weightings)],
        trains=_uniform_first,
    ),
)


def table(ctx: Context) -> None:
    """Table III with the baselines, paired with R3's committed runs when uniform reproduces (module docstring)."""
    from tar_rl.report import load_run

    regimes_out = Path(ctx.args.regimes) if ctx.args.regimes else RESULTS / "regimes"
    committed = r3_runs(ctx.sizes, regimes_out)
    planned = plan(ctx)
    uniform = planned["uniform"]
    ok, why = reproduces(uniform[0].run_dir, committed[BASELINE][0].run_dir)
    own_uniform = [s for s in uniform if s.finished]
    baselines = [load_run(s.run_dir) for s in planned["baselines"] if s.finished]
    if not baselines:
        raise SystemExit("baselines: no finished baseline run yet")
    if ok:
        base = [load_run(s.run_dir) for s in committed[BASELINE] + committed[TREATMENT] if s.finished]
        source, note = "R3's committed runs", f"uniform's seed 0 trained again at the baselines' commit: {why}"
    elif len(own_uniform) == len(uniform):
        base = [load_run(s.run_dir) for s in own_uniform]
        source, note = "uniform trained beside the baselines; TAR's row left out (another commit)", why
        check_pairs([*base, *baselines])
    else:
        raise SystemExit(
            f"baselines: uniform's seed 0 trained again does not reproduce R3's committed run ({why}); "
            "train every uniform seed beside the baselines with `run baselines --uniform`"
        )
    md, tables = table_markdown([*base, *baselines], source, note)
    prov = provenance(ctx.scale, ctx.study.name, ctx.argv[1:])
    write_outputs(ctx.tables, {"table.md": md}, tables, prov)
    print(md)


def _weightings(text: str) -> tuple[str, ...]:
    names = tuple(v.strip() for v in text.split(",") if v.strip())
    unknown = [n for n in names if n not in WEIGHTINGS]
    if unknown or not names:
        raise argparse.ArgumentTypeError(f"expected names from {', '.join(WEIGHTINGS)}, got {text!r}")
    return names


def _options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--regimes", default=None, help="the regime study's folder (default: benchmarks/results/regimes)")
    p.add_argument("--uniform", action="store_true", help="run: also train every uniform seed beside the baselines")
    p.add_argument(
        "--weightings",
        type=_weightings,
        default=WEIGHTINGS,
        help=f"only these baselines (default: {','.join(WEIGHTINGS)})",
    )


def _with_options(sizes: regimes.RegimeSizes, args: argparse.Namespace) -> regimes.RegimeSizes:
    if args.regimes is None and args.scale != "cpu":
        raise SystemExit(f"baselines: --regimes is required with --scale {args.scale}")
    return regimes.STUDY.with_options(sizes, args)


STUDY = Study(
    name="baselines",
    about="The baselines from the literature in R3.",
    scales=regimes.SIZES,
    stages=STAGES,
    table=table,
    results=lambda scale: "regimes/baselines" if scale == "cpu" else None,
    options=_options,
    with_options=_with_options,
)
