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
``table`` writes the comparisons (:mod:`.why_act_table`).
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass, replace
from pathlib import Path

from benchmarks.studies.cli import Context, Study
from benchmarks.studies.core import Arm, Planner, Scale, Spec, Stage, plan_digest, seed_major
from benchmarks.studies.records import check_started, read_json
from benchmarks.studies.regimes import SIZES as REGIME_SIZES
from benchmarks.studies.sweep import execute

__all__ = ["BASE_ARMS", "CONTROLS", "PERTURB", "SIZES", "STUDY", "WhySizes", "ladder_neighbour", "select_rate"]

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
    sizes = REGIME_SIZES[scale]
    for regime, head, extra in sizes.chunked_heads:
        if regime == label:
            return (f"policy={head}", *extra, *sizes.chunked)
    raise SystemExit(f"why_act: no regime {label} at the {scale} scale")


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


def reuse_planner(ctx: Context) -> Planner:
    """The planner of R4's runs: the regime study's folder above this study's."""
    p = ctx.planner
    return Planner(p.scale, ctx.out.parent, p.data_root, p.extra)


def with_base_arms(ctx: Context, arms: tuple[str, ...]) -> dict[str, list[Spec]]:
    """``arms`` with the seed's ``uniform`` and ``tar`` runs, per arm, seeds in order: R4's runs for the
    :attr:`WhySizes.reused_seeds`, this study's folder for the others."""
    sizes = ctx.sizes
    stage = Stage("", "", sizes.base, tuple(Arm.objective(a) for a in (*BASE_ARMS, *arms)), sizes.scale.seeds)
    r4 = reuse_planner(ctx)
    specs: dict[str, list[Spec]] = {}
    for arm in stage.arms:
        specs[arm.name] = [
            (r4 if arm.name in BASE_ARMS and s in sizes.reused_seeds else ctx.planner).spec(*stage.overrides(arm, s))
            for s in stage.seeds
        ]
    return specs


def tune_specs(ctx: Context, rates) -> dict[str, list[Spec]]:
    """The tuning runs (uniform at each rate, the tuning seeds, the tuning evaluation seed), per rate."""
    sizes = ctx.sizes
    base = (*sizes.base, f"eval.seed={sizes.tune_eval_seed}", "objective=uniform")
    arms = tuple(Arm(f"lr={r:g}", (f"optim.lr={r:g}",)) for r in sorted(rates))
    return Stage("tune", "uniform over learning rates", base, arms, sizes.tune_seeds, seed_last=True).specs(ctx.planner)


def tuned_specs(ctx: Context, rate: float) -> dict[str, list[Spec]]:
    """The tuned pair: ``uniform`` and ``tar`` at ``rate``, every seed."""
    base = (*ctx.sizes.base, f"optim.lr={rate:g}")
    arms = tuple(Arm.objective(a) for a in BASE_ARMS)
    return Stage("tuned", "the tuned pair", base, arms, ctx.sizes.scale.seeds).specs(ctx.planner)


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


def check_plan(ctx: Context, key: str, specs: dict[str, list[Spec]], record: bool) -> None:
    """Refuse a stage's plan that differs from the one its runs started with; with ``record``, record it."""
    path = ctx.out / STARTED_FILE

    def refusal(key, recorded, now):
        return (
            f"why_act: {key}'s plan changed after its runs started (recorded {recorded} in {path}, now {now}); a "
            f"plan may not change once its runs started: restore it, or remove {key}'s runs and its entry there"
        )

    check_started(path, {key: plan_digest(specs)}, record, refusal)


def stage_specs(ctx: Context, stage: str) -> dict[str, list[Spec]] | None:
    """A stage's runs per arm, or None for a gated stage whose record is missing (``tuned`` before
    ``tuning.json``, or when the rule trains no tuned pair)."""
    if stage == "placement":
        return with_base_arms(ctx, CONTROLS)
    if stage == "perturb":
        return with_base_arms(ctx, PERTURB)
    if stage == "tune":
        record = tuning(ctx)
        return tune_specs(ctx, record["rates"] if record else ctx.sizes.tune_rates)
    record = tuning(ctx)
    if record is None or not record["train_pair"]:
        return None
    return tuned_specs(ctx, record["best"])


def run_tune(ctx: Context, dry: bool) -> list[Spec]:
    """Train the tuning grid, extend it while its best rate is at an edge, and record the outcome."""
    from tar_rl.io import write_json_atomic

    sizes = ctx.sizes
    rates = list(sizes.tune_rates)
    check_plan(ctx, "tune", tune_specs(ctx, rates), record=not dry)
    while True:
        specs = tune_specs(ctx, rates)
        rate_by_rate = [s for group in specs.values() for s in group]
        failed = execute(ctx.scale, rate_by_rate, ctx.jobs, dry, ctx.logs, tree=ctx.args.tree)
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


def plan(ctx: Context) -> dict[str, list[Spec]]:
    """Every stage's planned runs that can be planned now, by stage."""
    out = {}
    for stage in STUDY.stages:
        specs = stage_specs(ctx, stage)
        if specs is not None:
            out[stage] = seed_major(specs)
    return out


def run(ctx: Context, stage: str) -> list[Spec]:
    """Train one stage (module docstring); returns the runs that failed."""
    dry = ctx.args.dry_run
    if stage == "tune":
        return run_tune(ctx, dry)
    specs = stage_specs(ctx, stage)
    if specs is None:
        raise SystemExit(
            f"why_act: the tuned pair is planned once the tuning grid is complete and its rule trains it "
            f"({ctx.out / TUNING_FILE}: {tuning(ctx)}); run `tune` first"
        )
    check_plan(ctx, stage, specs, record=not dry)
    return execute(ctx.scale, seed_major(specs), ctx.jobs, dry, ctx.logs, tree=ctx.args.tree)


def table(ctx: Context) -> None:
    """R6's comparisons (:func:`.why_act_table.write_tables`)."""
    from benchmarks.studies.cli import tables_dir
    from benchmarks.studies.records import provenance
    from benchmarks.studies.why_act_table import write_tables

    prov = provenance(ctx.scale, ctx.study.name, ctx.argv[1:])
    print(write_tables(ctx, prov, tables_dir(ctx), complete=ctx.args.complete))


def _options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--complete", action="store_true", help="table: refuse a stage with a run of its plan missing")
    p.add_argument(
        "--tree",
        type=_tree,
        default=None,
        help="run: train with this checkout's code (a git worktree at the study's commit, with its own .venv)",
    )


def _tree(text: str) -> Path:
    tree = Path(text).resolve()
    if not (tree / ".venv" / "bin" / "python").is_file() or not (tree / "tar_rl").is_dir():
        raise argparse.ArgumentTypeError(f"{text} is not a checkout of tar-rl with its own .venv (.venv/bin/python)")
    return tree


def _with_options(sizes: WhySizes, args: argparse.Namespace) -> WhySizes:
    if args.seeds is None:
        return sizes
    return replace(sizes, scale=replace(sizes.scale, seeds=args.seeds))


def keep_weights(ctx: Context) -> list[str]:
    """Seed 0's runs of every arm (the weights of each arm on one seed)."""
    names = []
    for stage in ("placement", "perturb"):
        names += [group[0].run_dir.name for group in stage_specs(ctx, stage).values() if group]
    return names


STUDY = Study(
    name="why_act",
    about="Why does TAR help act? R6: the paper's controls, a tuned baseline and the perturbation test.",
    scales=SIZES,
    stages=("placement", "tune", "tuned", "perturb"),
    plan=plan,
    run=run,
    table=table,
    results=lambda scale: "regimes/r6" if scale == "cpu" else None,
    options=_options,
    with_options=_with_options,
    keep_weights=keep_weights,
)
