"""Why does TAR help ``act``? R6 of the regime study (``results/regimes/PLAN.md``, "Why TAR helps act") as a study.

R6 repeats R4 (the ``act`` head on MT50 with 50 demonstrations per task, TAR at tar-rl's defaults) with the paper's
controls, a tuned uniform baseline and the perturbation test. Stages (``python -m benchmarks.studies why_act run
STAGE``; runs land in ``<out>/runs``, ``<out>`` being ``results/regimes/r6`` by default):

* ``placement`` (R6a): ``shuffle``, ``random`` and ``invert`` at TAR's defaults, seed by seed, with the seed's
  ``uniform`` and ``tar`` runs: R4's own (in ``<out>/../runs``) for the seeds R4 trained on this kind of machine
  (:attr:`WhySizes.reused_seeds`), trained again here for the others.
* ``tune`` (R6c): uniform over learning rates on the tuning evaluation seed, the grid extended along the half-decade
  ladder while its best rate is at an edge; writes ``<out>/tuning.json`` with the pre-registered rule's outcome.
* ``tuned`` (R6c): ``uniform`` and ``tar`` at the tuned rate, every seed, when ``tuning.json`` says the rule trains
  them.
* ``perturb`` (R6b): ``perturb_high`` and ``perturb_low`` with the seed's ``uniform`` and ``tar`` as above.

Each stage records its plan's digest when its first run starts (``<out>/started.json``). ``--tree DIR`` trains the
runs with another checkout's code (the study commit's worktree); this study's runs are trained at R4's commit.
``table`` writes each pre-registered comparison over its paired seeds (a pair trained at different commits, on
different machines or devices is refused, naming the runs), Holm over the primary ones, per-group rows, the arms'
fit and weights and the tuning grid; with ``--complete`` a stage with a run of its plan missing is refused.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from benchmarks.studies import sweep
from benchmarks.studies.cli import with_seeds
from benchmarks.studies.compare import (
    FINAL_SHARE,
    Comparison,
    contrast,
    contrasts,
    finished_runs,
    overall_success,
    stage_fits,
)
from benchmarks.studies.core import Arm, Grid, Scale, Spec
from benchmarks.studies.records import provenance, read_json
from benchmarks.studies.regimes import SIZES as REGIME_SIZES
from benchmarks.studies.regimes import chunked_base
from benchmarks.studies.stages import Context, Digest, Gate, Stage, Study, named, stage_arms
from benchmarks.studies.sweep import execute
from benchmarks.studies.writers import comparison_lines, fmt_num, groups_and_fit_lines, pending_lines, write_outputs

__all__ = [
    "BASE_ARMS",
    "COMPARISONS",
    "CONTROLS",
    "PERTURB",
    "SIZES",
    "STAGES",
    "STUDY",
    "Comparison",
    "WhySizes",
    "contrast",
    "ladder_neighbour",
    "select_rate",
    "write_tables",
]

BASE_ARMS = ("uniform", "tar")  # the arms R4 trained: reused where R4's runs pair with R6's
CONTROLS = ("shuffle", "random", "invert")  # R6a
PERTURB = ("perturb_high", "perturb_low")  # R6b
STARTED_FILE, TUNING_FILE = "started.json", "tuning.json"


@dataclass(frozen=True)
class WhySizes:
    """R6's sizes at one scale.

    Attributes:
        scale: the regime study's scale (shared overrides, seeds, time model).
        base: the overrides of R4's ``act`` runs (without seed and objective).
        reused_seeds: the seeds whose R4 ``uniform`` and ``tar`` runs pair with R6's (trained on this kind of
            machine at the study's commit); the other seeds' are trained again by R6.
        tune_seeds: the tuning grid's seeds.
        tune_eval_seed: the tuning evaluation seed.
        tune_rates: the tuning grid's first rates (ascending); ``reference`` is R4's.
        reference: R4's learning rate.
        margin: points by which the best rate must beat ``reference`` for the tuned pair to be trained.
    """

    scale: Scale
    base: tuple[str, ...]
    reused_seeds: tuple[int, ...]
    tune_seeds: tuple[int, ...]
    tune_eval_seed: int
    tune_rates: tuple[float, ...]
    reference: float
    margin: float


def _r4_base(label: str, scale: str) -> tuple[str, ...]:
    return chunked_base(REGIME_SIZES[scale], label)


_TUNE = dict(tune_eval_seed=2000, tune_rates=(3e-4, 1e-3, 3e-3), reference=1e-3, margin=2.0)
SIZES = {
    "cpu": WhySizes(
        scale=REGIME_SIZES["cpu"].scale,
        base=_r4_base("R4", "cpu"),
        reused_seeds=(0, 1, 2, 3, 7),  # R4's CPU seeds; 4-6 ran on an H200 (PLAN.md, "Deviations")
        tune_seeds=(0, 1),
        **_TUNE,
    ),
    "ci": WhySizes(
        scale=REGIME_SIZES["ci"].scale,
        base=_r4_base("R4", "ci"),
        reused_seeds=(0,),
        tune_seeds=(0,),
        **_TUNE,
    ),
}


# -- The tuning rule ---------------------------------------------------------------------------------------


def ladder_neighbour(rate: float, up: bool) -> float:
    """The next rate of the half-decade ladder (1e-4, 3e-4, 1e-3, 3e-3, ...) above (``up``) or below ``rate``."""
    exponent = math.floor(math.log10(rate) + 1e-9)
    mantissa = round(rate / 10**exponent)
    if mantissa not in (1, 3):
        raise ValueError(f"{rate!r} is not on the half-decade ladder (1 or 3 x a power of ten)")
    if up:
        return float(f"3e{exponent}") if mantissa == 1 else float(f"1e{exponent + 1}")
    return float(f"1e{exponent}") if mantissa == 3 else float(f"3e{exponent - 1}")


def select_rate(success: dict[float, float], reference: float) -> tuple[float, float | None]:
    """The best rate of a grid (highest mean success; a tie goes to the rate nearer ``reference`` on a log scale,
    then the lower one) and the rate to try next: the ladder's neighbour beyond the edge the best one is at, or
    ``None`` when the best is inside the grid or the neighbour would exceed 1."""
    rates = sorted(success)
    best = min(rates, key=lambda r: (-success[r], abs(math.log(r / reference)), r))
    nxt = None
    if best == rates[-1]:
        nxt = ladder_neighbour(best, up=True)
        nxt = nxt if nxt <= 1 else None
    elif best == rates[0]:
        nxt = ladder_neighbour(best, up=False)
    return best, nxt


# -- The stages ------------------------------------------------------------------------------------------


def with_base_arms(ctx: Context, name: str, arms: tuple[str, ...]) -> Grid:
    """``arms`` with the seed's ``uniform`` and ``tar`` runs, seeds in order: R4's runs (the regime study's folder
    above this study's) for the :attr:`WhySizes.reused_seeds`, this study's folder for the others."""
    sizes = ctx.sizes
    every = tuple(Arm.objective(a) for a in (*BASE_ARMS, *arms))
    reused = frozenset((a, s) for a in BASE_ARMS for s in sizes.reused_seeds)
    about = f"{', '.join(arms)} with the seed's uniform and tar"
    return Grid(name, about, sizes.base, every, sizes.scale.seeds, reused=reused, reused_from=ctx.out.parent)


def tune_grid(sizes: WhySizes, rates) -> Grid:
    """The tuning runs (uniform at each rate, the tuning seeds, the tuning evaluation seed), per rate."""
    base = (*sizes.base, f"eval.seed={sizes.tune_eval_seed}", "objective=uniform")
    arms = tuple(Arm(f"lr={r:g}", (f"optim.lr={r:g}",)) for r in sorted(rates))
    return Grid("tune", "uniform over learning rates", base, arms, sizes.tune_seeds, seed_last=True)


def tuned_grid(sizes: WhySizes, rate: float) -> Grid:
    """The tuned pair: ``uniform`` and ``tar`` at ``rate``, every seed."""
    base = (*sizes.base, f"optim.lr={rate:g}")
    return Grid("tuned", "the tuned pair", base, tuple(Arm.objective(a) for a in BASE_ARMS), sizes.scale.seeds)


def tuning(ctx: Context) -> dict | None:
    """The recorded outcome of the tuning grid (``tuning.json``), or None before it is complete."""
    return read_json(ctx.out / TUNING_FILE)


def grid_success(specs: dict[str, list[Spec]]) -> dict[float, float] | None:
    """Mean overall success (%) per rate over the tuning seeds, or None while a run is unfinished."""
    from tar_rl.report import load_run, run_percent

    out = {}
    for group in specs.values():
        if not all(s.finished for s in group):
            return None
        values = [run_percent(load_run(s.run_dir))[("success", "overall")] for s in group]
        out[float(group[0].config["optim"]["lr"])] = sum(values) / len(values)
    return out


def run_tune(ctx: Context) -> list[Spec]:
    """Train the tuning grid, extend it while its best rate is at an edge, and record the outcome."""
    from tar_rl.io import write_json_atomic

    sizes, dry, tree = ctx.sizes, ctx.args.dry_run, ctx.tree
    rates = list(sizes.tune_rates)
    while True:
        specs = tune_grid(sizes, rates).specs(ctx.planner)
        rate_by_rate = [s for group in specs.values() for s in group]
        failed = execute(ctx.scale, rate_by_rate, ctx.jobs, dry, ctx.logs, tree=tree)
        success = grid_success(specs)
        if failed or success is None:
            return failed
        best, nxt = select_rate(success, sizes.reference)
        if nxt is None:
            break
        print(f"the best rate {best:g} is at an edge of {sorted(success)}: adding {nxt:g}")
        rates.append(nxt)
    gain = success[best] - success[sizes.reference]
    record = {
        "rates": sorted(success),
        "success": {f"{r:g}": success[r] for r in sorted(success)},
        "best": best,
        "gain_over_reference": gain,
        "train_pair": gain >= sizes.margin,
        "rule": f"the tuned pair trains when the best rate beats {sizes.reference:g} by >= {sizes.margin:g} points "
        f"(mean overall success of seeds {list(sizes.tune_seeds)}, evaluation seed {sizes.tune_eval_seed})",
    }
    if not dry:
        write_json_atomic(record, ctx.out / TUNING_FILE)
    print(f"tuning: best {best:g} ({gain:+.2f} points over {sizes.reference:g}); tuned pair: {record['train_pair']}")
    return []


# -- The tables --------------------------------------------------------------------------------------------


COMPARISONS = (
    Comparison("R6 tar - shuffle", "placement", "tar", "shuffle", True),
    Comparison("R6 tar - random", "placement", "tar", "random", True),
    Comparison("R6 tar - invert", "placement", "tar", "invert", True),
    Comparison("R6 shuffle - uniform", "placement", "shuffle", "uniform", True),
    Comparison("R6 random - uniform", "placement", "random", "uniform", True),
    Comparison("R6 invert - uniform", "placement", "invert", "uniform", True),
    Comparison("R6 perturb_low - perturb_high", "perturb", "perturb_low", "perturb_high", True),
    Comparison("R6c tar - uniform", "tuned", "tar", "uniform", True),
    Comparison("R6 tar - uniform", "placement", "tar", "uniform", False),
    Comparison("R6 perturb_high - uniform", "perturb", "perturb_high", "uniform", False),
    Comparison("R6 perturb_low - uniform", "perturb", "perturb_low", "uniform", False),
)


def stage_runs(ctx: Context, stage: str, complete: bool) -> tuple[dict[str, dict[int, object]], list[str]]:
    """A stage's finished runs per arm and seed (loaded) and the names of its planned runs not finished.

    Raises:
        SystemExit: the plan changed after its runs started; with ``complete``, a run of the plan is missing.
    """
    specs = stage_arms(ctx, STAGES[stage])
    if specs is None:
        return {}, []
    return finished_runs(specs, "why_act", stage, complete)


def comparison_rows(ctx: Context, complete: bool) -> tuple[list[dict], list[pd.DataFrame], list[dict], dict, list]:
    """Every comparison with paired seeds (Holm over the primary ones present), their per-group rows, the fit
    and weights of each stage's arms over its paired seeds, the missing runs per stage and the arms' per-seed
    differences to uniform (:func:`paired_rows`)."""
    loaded, missing = {}, {}
    for stage in ("placement", "tuned", "perturb"):
        loaded[stage], missing[stage] = stage_runs(ctx, stage, complete)
    rows, groups = contrasts(COMPARISONS, loaded)
    return rows, groups, stage_fits(loaded), missing, paired_rows(loaded)


#: The paired figure's R6 rows, ``(stage, arm, label)``, each arm minus the same stage's ``uniform`` per seed: the
#: placement arms (TAR and its controls), the perturbation arms and the tuned pair's TAR.
PAIRED = (
    *(("placement", arm, f"R6 act: {arm}") for arm in ("tar", *CONTROLS)),
    *(("perturb", arm, f"R6 act: {arm}") for arm in PERTURB),
    ("tuned", "tar", "R6c act: tar (tuned lr)"),
)


def paired_rows(loaded: dict[str, dict[str, dict[int, object]]]) -> list[dict]:
    """Each arm of :data:`PAIRED` minus its stage's ``uniform`` per seed, in points of overall success: ``label``,
    ``group`` (``R6``), ``seed``, ``delta``; the paired-difference figure of the regime study reads them
    (``paired.csv``). ``loaded``: per stage, the finished runs per arm and seed. The placement stage's ``tar``
    (R4's pairs repeated) is drawn only for the seeds with a control."""

    def drawn(stage: str, seed: int) -> bool:
        arms = loaded.get(stage, {})
        return stage != "placement" or any(seed in arms.get(c, {}) for c in CONTROLS)

    rows = []
    for stage, arm, label in PAIRED:
        uniform = loaded.get(stage, {}).get("uniform", {})
        for seed, run in sorted(loaded.get(stage, {}).get(arm, {}).items()):
            if seed in uniform and drawn(stage, seed):
                delta = overall_success(run) - overall_success(uniform[seed])
                rows.append({"label": label, "group": "R6", "seed": seed, "delta": delta})
    return rows


def tuning_rows(ctx: Context) -> list[dict]:
    """The tuning grid's finished runs: overall success per rate and seed on the tuning evaluation seed."""
    from tar_rl.report import load_run, run_percent

    record = tuning(ctx)
    rates = record["rates"] if record else ctx.sizes.tune_rates
    rows = []
    for group in tune_grid(ctx.sizes, rates).specs(ctx.planner).values():
        for spec in group:
            if spec.finished:
                run = load_run(spec.run_dir)
                success = run_percent(run)[("success", "overall")]
                rows.append({"lr": float(spec.config["optim"]["lr"]), "seed": run.seed, "success": success})
    return rows


def decision_markdown(rows, groups: pd.DataFrame, fits, tune: Sequence[dict], record, missing) -> str:
    """R6's comparisons, per-group rows, fit and weights, tuning grid and missing runs, as markdown."""
    out = ["# Why does TAR help act? R6's comparisons", "", *comparison_lines(rows), ""]
    out += [
        "Success, Fast20 and NEPS in 100 x units; Δ = T - B over the seeds both arms have (lower Fast20/NEPS is "
        "better). Holm over R6's primary comparisons present (every row with a Holm p; `R6 tar - uniform` repeats R4 "
        "on R6's pairs, and the perturbation arms against uniform are secondary). MDE: the smallest true Δ success a "
        "paired t-test detects with 80% power at the observed spread. T higher: pairs where T's success is higher.",
        "",
        *groups_and_fit_lines(groups, fits, FINAL_SHARE),
    ]
    if tune:
        out += ["", "## Tuning uniform's learning rate (evaluation seed 2000)", ""]
        frame = pd.DataFrame(tune)
        out += ["| learning rate | seeds | success % per seed | mean |", "|---|---|---|---|"]
        for lr, g in frame.groupby("lr", sort=True):
            per_seed = ", ".join(f"{s}: {fmt_num(v)}" for s, v in zip(g["seed"], g["success"]))
            out.append(f"| {lr:g} | {len(g)} | {per_seed} | {fmt_num(g['success'].mean())} |")
        if record:
            out += [
                "",
                f"Best rate {record['best']:g}, {record['gain_over_reference']:+.2f} points over R4's; "
                f"{record['rule']}: "
                + ("the tuned pair is trained." if record["train_pair"] else "no tuned pair is trained."),
            ]
    out += pending_lines(missing)
    return "\n".join(out) + "\n"


def write_tables(ctx: Context, prov: dict, dest: Path, complete: bool = False) -> str:
    """R6's tables (markdown + CSV) from the finished runs of ``ctx.out`` (and R4's beside it), written into
    ``dest``; returns the markdown. ``complete``: refuse a planned stage with a run missing (the final table)."""
    rows, groups, fits, missing, paired = comparison_rows(ctx, complete)
    tune = tuning_rows(ctx)
    group_df = pd.concat(groups, ignore_index=True) if groups else pd.DataFrame()
    md = decision_markdown(rows, group_df, fits, tune, tuning(ctx), missing)
    tables = {"decision.csv": pd.DataFrame(rows)}
    if len(group_df):
        tables["groups.csv"] = group_df
    if tune:
        tables["tuning.csv"] = pd.DataFrame(tune)
    if paired:
        tables["paired.csv"] = pd.DataFrame(paired)
    write_outputs(dest, {"decision.md": md}, tables, prov)
    return md


# -- The study -------------------------------------------------------------------------------------------


def _rates(ctx: Context) -> tuple[float, ...]:
    """The tuning grid's rates: the recorded ones once the grid is complete, else the first ones."""
    record = tuning(ctx)
    return record["rates"] if record else ctx.sizes.tune_rates


def _trains_pair(ctx: Context) -> dict | None:
    record = tuning(ctx)
    return record if record is not None and record["train_pair"] else None


def _no_tuned_pair(ctx: Context) -> str:
    return (
        f"why_act: the tuned pair is planned once the tuning grid is complete and its rule trains it "
        f"({ctx.out / TUNING_FILE}: {tuning(ctx)}); run `tune` first"
    )


STARTED = Digest(STARTED_FILE)
STAGES = named(
    Stage(
        "placement",
        "R6a: the controls at TAR's defaults with the seed's uniform and tar",
        grids=lambda ctx: [with_base_arms(ctx, "placement", CONTROLS)],
        records=STARTED,
    ),
    Stage(
        "tune",
        "R6c: uniform over learning rates, extended while the best is at an edge; writes tuning.json",
        grids=lambda ctx: [tune_grid(ctx.sizes, _rates(ctx))],
        records=Digest(STARTED_FILE, of=lambda ctx: tune_grid(ctx.sizes, ctx.sizes.tune_rates)),
        action=run_tune,
    ),
    Stage(
        "tuned",
        "R6c: uniform and tar at the tuned rate",
        grids=lambda ctx, record: [tuned_grid(ctx.sizes, record["best"])],
        gates=(Gate("a tuning record whose rule trains the tuned pair", _trains_pair, _no_tuned_pair),),
        records=STARTED,
    ),
    Stage(
        "perturb",
        "R6b: the perturbation arms with the seed's uniform and tar",
        grids=lambda ctx: [with_base_arms(ctx, "perturb", PERTURB)],
        records=STARTED,
    ),
)


def table(ctx: Context) -> None:
    """R6's comparisons (:func:`write_tables`)."""
    prov = provenance(ctx.scale, ctx.study.name, ctx.argv[1:])
    print(write_tables(ctx, prov, ctx.tables, complete=ctx.args.complete))


def _options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--complete", action="store_true", help="table: refuse a stage with a run of its plan missing")
    sweep.add_tree_option(
        p, "run: train with this checkout's code (a git worktree at the study's commit, with its own .venv)"
    )


def keep_weights(ctx: Context) -> list[str]:
    """Seed 0's runs of every arm (the weights of each arm on one seed)."""
    names = []
    for stage in ("placement", "perturb"):
        names += [group[0].run_dir.name for group in stage_arms(ctx, STAGES[stage], check=False).values() if group]
    return names


STUDY = Study(
    name="why_act",
    about="Why does TAR help act? R6: the paper's controls, a tuned baseline and the perturbation test.",
    scales=SIZES,
    stages=STAGES,
    table=table,
    results=lambda scale: "regimes/r6" if scale == "cpu" else None,
    options=_options,
    with_options=with_seeds,
    keep_weights=keep_weights,
)
