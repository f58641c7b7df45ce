"""The temporal weightings from the literature beside TAR in the regime study's R3 (``results/regimes/PLAN.md``,
"Baselines in R3"), as commands.

Usage::

    python benchmarks/r3_baselines.py COMMAND [--scale cpu|ci] [--out DIR] [--jobs N] [--data-root DIR] [--dry-run]

Commands (runs land in ``<out>/runs/``, named by their settings; running again skips finished runs and resumes
interrupted ones):

* ``run``: first uniform's seed-0 run again (the reproduction check below), then every baseline
  (``tilted``, ``truncate``, ``keyframe``, ``focal``, ``dro_time``) at its default settings with R3's
  settings, seed by seed; with ``--uniform`` also every uniform seed (needed when the check fails).
* ``table``: Table III extended with the baselines (success per difficulty group and overall, the paired
  difference of the overall success to uniform with its 95% CI and p, Holm over the baseline rows), beside
  R3's uniform and TAR rows, recomputed from the runs (``table.md``, ``table.csv``, ``paired.csv``, written
  into ``<out>`` or, with ``--tables DIR``, into ``DIR``).
* ``collect --from DIR``: copy finished runs into ``<out>/runs`` (config, summary, compressed logs; never
  ``weights.csv``, which no analysis of the baselines reads).

**Pairing with R3's uniform runs.** The baselines are trained at a later commit than R3's runs, and the study
pairs only runs of one commit and machine. Training is deterministic on the CPU, so ``run`` trains uniform's
seed 0 again at the baselines' commit: when its per-rollout results equal those of R3's committed seed-0 run,
the code paths the uniform runs take have not changed and the baselines pair with R3's uniform runs; otherwise
``table`` refuses that pairing and the uniform runs are trained again beside the baselines (``run --uniform``).
"""

from __future__ import annotations

import argparse
import io
import math
import sys
from pathlib import Path

import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the other benchmark scripts beside this script
from paper_analysis import controls_markdown, fmt_p
from paper_experiments import Planner, Spec, execute, provenance
from regimes import (
    FINAL_SHARE,
    check_pairs,
    collect,
    exit_code,
    fit_markdown,
    fit_summary,
    jobs_and_out,
    r3_specs,
    reproduces,
    seed_major,
    study_of,
    study_parser,
    tables_dir,
)

COMMANDS = ("run", "table", "collect")
BASELINE, TREATMENT = "uniform", "tar"
WEIGHTINGS = ("tilted", "truncate", "keyframe", "focal", "dro_time")


def baseline_specs(planner: Planner, study, weightings=WEIGHTINGS) -> dict[str, list[Spec]]:
    """The baselines' runs at R3's settings and seeds, by weighting."""
    return {w: [planner.spec(*study.r3, f"seed={s}", f"objective={w}") for s in study.scale.seeds] for w in weightings}


def uniform_specs(planner: Planner, study) -> list[Spec]:
    return [planner.spec(*study.r3, f"seed={s}", f"objective={BASELINE}") for s in study.scale.seeds]


def r3_runs(study, regimes_out: Path) -> dict[str, list[Spec]]:
    """R3's committed runs (uniform and TAR) as planned by ``regimes.py``, by objective."""
    planner = Planner(study.scale, regimes_out, "datasets")
    specs = r3_specs(study, planner)
    return {o: [s for s in specs if s.config["objective"]["name"] == o] for o in (BASELINE, TREATMENT)}


def fit_table(runs: list) -> pd.DataFrame:
    """Per objective, :func:`regimes.fit_summary` of its finished runs (with the number of runs)."""
    rows = []
    for objective in dict.fromkeys(r.objective for r in runs):
        mine = [r for r in runs if r.objective == objective and r.finished]
        rows.append({"objective": objective, "runs": len(mine), **fit_summary(mine)})
    return pd.DataFrame(rows)


def table(runs: list, uniform_source: str, reproduction: str) -> tuple[str, pd.DataFrame, pd.DataFrame, pd.DataFrame]:
    """Table III with the baselines: markdown, the compare table, the paired table with Holm over the baselines and
    the fit table (:func:`fit_table`)."""
    from tar_rl.report import compare, holm, min_detectable_effect, paired_table

    done = [r for r in runs if r.finished]
    fit = fit_table(done)
    summary = compare(done, file=io.StringIO())
    paired = paired_table(done, file=io.StringIO())
    overall = paired[(paired["metric"] == "success") & (paired["level"] == "overall")]
    rows = overall[overall["objective"].isin(WEIGHTINGS)]
    paired["holm_p"] = math.nan
    paired["mde"] = math.nan
    for index, p in zip(rows.index, holm(list(rows["p_value"]))):
        paired.loc[index, "holm_p"] = p
    for index, rec in overall.iterrows():
        paired.loc[index, "mde"] = min_detectable_effect(rec["delta_std"], int(rec["n_pairs"]))
    family = done[0].policy
    holm_lines = [
        "| objective | pairs | Δ overall vs uniform | p | Holm p (over the baselines) | MDE (80%) |",
        "|---|---|---|---|---|---|",
    ]
    for rec in paired.loc[rows.index].to_dict("records"):
        holm_lines.append(
            f"| {rec['objective']} | {rec['n_pairs']} | {rec['delta_mean']:+.2f} | {fmt_p(rec['p_value'])} | "
            f"{fmt_p(rec['holm_p'])} | {'-' if math.isnan(rec['mde']) else format(rec['mde'], '.2f')} |"
        )
    md = "\n".join(
        [
            "# Table III extended: the baselines from the literature in R3",
            "",
            "R3's settings (MT50, 50 demonstrations per task, about 20 passes, 20 rollouts per task at seed 1000). "
            "Success % (mean ± std over seeds) per difficulty group and overall, and the paired difference of the "
            "overall success to uniform (95% CI, paired t-test). Every weighting at its default settings.",
            "",
            f"Uniform and TAR rows: {uniform_source} ({reproduction}).",
            "",
            controls_markdown(paired, summary, family),
            "",
            *holm_lines,
            "",
            f"Fit and weights, means over each objective's runs: the final uniform training loss and the held-out "
            f"per-step loss (each run's `summary.json`, `fit`), the alignment (Spearman correlation over ten bins of "
            f"episode time between the weight on training demonstrations and the held-out loss), and over the last "
            f"{FINAL_SHARE:.0%} of training steps the largest weight in a segment and the effective-sample-size "
            f"fraction of the weights (1 = uniform).",
            "",
            *fit_markdown(fit, ("objective", "runs")),
        ]
    )
    return md + "\n", summary, paired, fit


def _names(text: str) -> tuple[str, ...]:
    names = tuple(v.strip() for v in text.split(",") if v.strip())
    unknown = [n for n in names if n not in WEIGHTINGS]
    if unknown or not names:
        raise argparse.ArgumentTypeError(f"expected names from {', '.join(WEIGHTINGS)}, got {text!r}")
    return names


def _parser() -> argparse.ArgumentParser:
    p = study_parser(
        "r3_baselines.py", "The baselines from the literature in R3.", COMMANDS, "benchmarks/results/regimes/baselines"
    )
    p.add_argument("--regimes", default=None, help="the regime study's folder (default: benchmarks/results/regimes)")
    p.add_argument("--uniform", action="store_true", help="run: also train every uniform seed beside the baselines")
    p.add_argument(
        "--weightings", type=_names, default=WEIGHTINGS, help=f"only these baselines (default: {','.join(WEIGHTINGS)})"
    )
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point (module docstring). Returns 0, or 1 when a run failed (the others still ran)."""
    from tar_rl.io import atomic_write, write_csv_atomic, write_json_atomic
    from tar_rl.report import load_run

    argv = sys.argv[1:] if argv is None else list(argv)
    args = _parser().parse_args(argv)
    study = study_of(args)
    here = Path(__file__).resolve().parent / "results" / "regimes"
    jobs, out = jobs_and_out(args, study.scale, "r3_baselines", here / "baselines")
    if args.regimes is None and args.scale != "cpu":
        raise SystemExit(f"r3_baselines: --regimes is required with --scale {args.scale}")
    regimes_out = Path(args.regimes) if args.regimes else here
    planner = Planner(study.scale, out, args.data_root)
    uniform = uniform_specs(planner, study)
    if args.command == "collect":
        if not args.source:
            raise SystemExit("r3_baselines: collect needs --from DIR (a runs folder)")
        names = collect(Path(args.source), out)
        print(f"copied {len(names)} finished run(s) into {out / 'runs'}: " + ", ".join(names))
        return 0
    if args.command == "run":
        specs = [uniform[0], *seed_major(baseline_specs(planner, study, args.weightings))]
        if args.uniform:
            specs = [*uniform, *specs]
        return exit_code(execute(study.scale, specs, jobs, args.dry_run, out / "logs"))
    # table
    committed = r3_runs(study, regimes_out)
    ok, why = reproduces(uniform[0].run_dir, committed[BASELINE][0].run_dir)
    own_uniform = [s for s in uniform if s.finished]
    planned = baseline_specs(planner, study, args.weightings)
    baselines = [load_run(s.run_dir) for group in planned.values() for s in group if s.finished]
    if not baselines:
        raise SystemExit("r3_baselines: no finished baseline run yet")
    if ok:
        base = [load_run(s.run_dir) for s in committed[BASELINE] + committed[TREATMENT] if s.finished]
        source, note = "R3's committed runs", f"uniform's seed 0 trained again at the baselines' commit: {why}"
    elif len(own_uniform) == len(uniform):
        base = [load_run(s.run_dir) for s in own_uniform]
        source, note = "uniform trained beside the baselines; TAR's row left out (another commit)", why
        check_pairs([*base, *baselines])
    else:
        raise SystemExit(
            f"r3_baselines: uniform's seed 0 trained again does not reproduce R3's committed run ({why}); "
            "train every uniform seed beside the baselines with `run --uniform`"
        )
    md, summary, paired, fit = table([*base, *baselines], source, note)
    dest = tables_dir(args, out)
    atomic_write(dest / "table.md", lambda f: f.write(md))
    write_csv_atomic(summary.round(6), dest / "table.csv")
    write_csv_atomic(paired.round(6), dest / "paired.csv")
    write_csv_atomic(fit.round(6), dest / "fit.csv")
    write_json_atomic(provenance(study.scale, argv, "r3_baselines.py"), dest / "provenance.json")
    print(md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
