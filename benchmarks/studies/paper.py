"""The paper's experiments (Sec. III-IV) as a study: runs through the offline BC recipe, then tables and figures.

Stages (``python -m benchmarks.studies paper run STAGE``; every run lands in ``<out>/runs/``):

* ``protocol``: policy families x {uniform, tar} x seeds at the scale's fixed demonstration budget and evaluation
  protocol.
* ``controls``: the scale's control family with the paper's weightings (uniform, tar, shuffle, random, invert,
  perturb_high, perturb_low; :data:`tar_rl.report.OBJECTIVE_ORDER`) on the control seeds. The baselines from the
  literature (``tilted``, ...) are not in the paper's table.
* ``budget``: uniform and TAR per demonstration budget (the scale's list).
* ``sensitivity``: TAR over gamma x w_max x cap, and uniform, on a *tuning* evaluation seed set (``eval.seed`` =
  the scale's ``sens_eval_seed``, 2000 by default) that is not the final tables' (``eval.seed`` = 1000).
* ``all``: the four in this order.

``table`` writes each report into ``<out>/<report>/`` (``--reports`` picks; every one by default), refusing one
whose runs have none finished (:mod:`.paper_tables`): ``table`` (Table I per family with Figs. 3-4, from the
protocol runs), ``controls`` (Table III), ``critical_windows`` (the share of TAR's weight mass per phase from the
TAR protocol runs' ``weights.csv``, and Fig. 5), ``budget`` and ``sensitivity``.

Scales (:data:`SIZES`): ``paper`` (MT50, the paper's 100K steps, TAR from 20K over 30K, 50 rollouts per task at
seed 1000, the five families; a GPU machine), ``cpu`` (the MLP family on eight tasks, two per difficulty group,
sized to about an hour per stage on 2 cores) and ``ci`` (two tasks, 2 steps, one short rollout: what the tests
run). Baseline and TAR runs of a pair differ only in ``objective=``: same data, seeds, evaluation variations and
every other setting.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass, replace

from benchmarks.studies.cli import names
from benchmarks.studies.core import Arm, Grid, Scale
from benchmarks.studies.protocol import BASELINE, EIGHT_TASKS, PAIR, TREATMENT
from benchmarks.studies.records import provenance
from benchmarks.studies.stages import Context, Stage, Study, named, stage_specs

__all__ = ["PAPER_FAMILIES", "SIZES", "STAGES", "STUDY", "PaperSizes"]

REPORTS = ("table", "controls", "critical_windows", "budget", "sensitivity")
# The paper's five families (ACT, Octo linear, Octo diffusion, a flow head, and the MLP reference).
PAPER_FAMILIES = ("mlp", "act", "octo_linear", "octo_diffusion", "flow")


@dataclass(frozen=True)
class PaperSizes:
    """The sizes of the paper's experiments at one scale.

    Attributes:
        scale: the overrides every run shares, the protocol's seeds and the time model.
        families: policy families of ``protocol`` / ``table``.
        control_family: the family of ``controls``, ``budget``, ``sensitivity``.
        control_seeds: seeds of ``controls``.
        budget_demos: demonstrations per task of ``budget``.
        budget_seeds: seeds of ``budget``.
        sens_gamma, sens_w_max, sens_cap: the ``sensitivity`` grid.
        sens_seeds: seeds of ``sensitivity``.
        sens_eval_seed: evaluation seed of ``sensitivity`` (the tuning set; the tables use ``eval.seed``).
        fig5_tasks: tasks drawn in Fig. 5.
    """

    scale: Scale
    families: tuple[str, ...]
    control_family: str = "mlp"
    control_seeds: tuple[int, ...] = (0, 1, 2, 3)
    budget_demos: tuple[int, ...] = (1, 3, 10, 25)
    budget_seeds: tuple[int, ...] = (0, 1, 2, 3)
    sens_gamma: tuple[float, ...] = (0.5, 1.0, 2.0)
    sens_w_max: tuple[float, ...] = (2.0, 3.0, 5.0)
    sens_cap: tuple[str, ...] = ("paper", "exact")
    sens_seeds: tuple[int, ...] = (0, 1)
    sens_eval_seed: int = 2000
    fig5_tasks: tuple[str, ...] = ("reach", "pick-place-wall", "assembly")


SIZES: dict[str, PaperSizes] = {
    "paper": PaperSizes(
        scale=Scale(
            name="paper",
            about="the paper's protocol: MT50, 100K steps (TAR from 20K over 30K), 50 rollouts per task at seed "
            "1000, five families; for a GPU machine",
            common=(
                "data=mt50",
                "data.n_demos=25",
                "optim=paper",
                "eval=paper",
                "logging=quiet",
                "logging.record_episodes=3",
            ),
            seeds=(0, 1, 2),
            jobs=1,
            step_seconds=0.02,
            rollout_seconds=0.06,  # 16 evaluation workers
        ),
        families=PAPER_FAMILIES,
        control_seeds=(0, 1, 2),
        budget_demos=(1, 3, 10, 25),
        budget_seeds=(0, 1, 2),
        sens_seeds=(0,),
    ),
    "cpu": PaperSizes(
        scale=Scale(
            name="cpu",
            about="the MLP family on 8 tasks (two per group), 10 demos, 8K steps, 20 rollouts per task at seed 1000; "
            "about an hour per command on 2 cores (2 runs at once)",
            common=(
                f"data.tasks={EIGHT_TASKS}",
                "data.n_demos=10",
                "optim.steps=8000",
                "eval.rollouts=20",
                "eval.seed=1000",
                "logging=quiet",
                "logging.record_episodes=3",
                "threads=1",
            ),
            seeds=(0, 1, 2, 3, 4, 5, 6, 7),
            jobs=2,
        ),
        families=("mlp",),
    ),
    "ci": PaperSizes(
        scale=Scale(
            name="ci",
            about="two tasks, 2 demos, 2 steps, one 20-step rollout: the tests' size (no meaningful numbers)",
            common=(
                "data.tasks=[reach,basketball]",
                "data.n_demos=2",
                "data.batch_segments=4",
                "data.slice_len=8",
                "data.workers=1",
                "policy.hidden=[16,16]",
                "optim.steps=2",
                "optim.warmup=1",
                "eval.rollouts=1",
                "eval.horizon=20",
                "eval.workers=1",
                "logging=quiet",
                "logging.every=1",
                "logging.checkpoint_every=1",
                "threads=1",
            ),
            seeds=(0, 1),
            jobs=1,
        ),
        families=("mlp",),
        control_seeds=(0,),
        budget_demos=(1, 2),
        budget_seeds=(0,),
        sens_gamma=(1.0, 2.0),
        sens_w_max=(3.0,),
        sens_cap=("paper",),
        sens_seeds=(0,),
        fig5_tasks=("reach", "basketball"),
    ),
}


# -- The stages ------------------------------------------------------------------------------------------


def protocol_grids(sizes: PaperSizes) -> list[Grid]:
    """Per family, uniform and TAR on the protocol's seeds."""
    return [
        Grid("protocol", f"{f}: uniform, tar", (f"policy={f}",), PAIR, sizes.scale.seeds, True) for f in sizes.families
    ]


def controls_grid(sizes: PaperSizes) -> Grid:
    """The control family with every weighting of the paper's Table III, on the control seeds."""
    from tar_rl.objectives import WEIGHTINGS
    from tar_rl.report import OBJECTIVE_ORDER

    arms = tuple(Arm.objective(o) for o in OBJECTIVE_ORDER if o in WEIGHTINGS)
    base = (f"policy={sizes.control_family}",)
    return Grid("controls", "the paper's weightings", base, arms, sizes.control_seeds, True)


def budget_grids(sizes: PaperSizes) -> list[Grid]:
    """Per demonstration budget, uniform and TAR on the budget seeds."""
    f = sizes.control_family
    return [
        Grid("budget", f"{n} demos", (f"policy={f}", f"data.n_demos={n}"), PAIR, sizes.budget_seeds, True)
        for n in sizes.budget_demos
    ]


def sensitivity_grid(sizes: PaperSizes) -> Grid:
    """Uniform and TAR over the grid, on the tuning evaluation seed."""
    cells = tuple(
        Arm(
            f"tar-g{g:g}-w{w:g}-{c}",
            (f"objective={TREATMENT}", f"objective.gamma={g}", f"objective.w_max={w}", f"objective.cap={c}"),
        )
        for g in sizes.sens_gamma
        for w in sizes.sens_w_max
        for c in sizes.sens_cap
    )
    base = (f"policy={sizes.control_family}", f"eval.seed={sizes.sens_eval_seed}")
    return Grid("sensitivity", "the TAR grid", base, (Arm.objective(BASELINE), *cells), sizes.sens_seeds)


def check_families(families) -> None:
    """Refuse families that are not registered policy heads, naming the registered ones."""
    from tar_rl.policies import POLICIES

    unknown = [f for f in families if f not in POLICIES]
    if unknown:
        raise SystemExit(
            f"paper: policy families {unknown} are not registered policy heads; registered: {sorted(POLICIES)}. "
            "Choose others with --families."
        )


# -- The study -------------------------------------------------------------------------------------------


_EACH = (
    Stage("protocol", "policy families x {uniform, tar}", grids=lambda ctx: protocol_grids(ctx.sizes)),
    Stage("controls", "the paper's weightings on the control family", grids=lambda ctx: [controls_grid(ctx.sizes)]),
    Stage("budget", "uniform and TAR per demonstration budget", grids=lambda ctx: budget_grids(ctx.sizes)),
    Stage("sensitivity", "TAR's grid and uniform, tuning seed", grids=lambda ctx: [sensitivity_grid(ctx.sizes)]),
)
STAGES = named(*_EACH, Stage("all", "the four stages in this order", first=_EACH))


def table(ctx: Context) -> None:
    """Every report of ``--reports`` from the finished runs, each into ``<out>/<report>/``."""
    from benchmarks.studies import paper_tables as t

    sizes, prov = ctx.sizes, provenance(ctx.scale, ctx.study.name, ctx.argv[1:])
    writers = {
        "table": lambda specs, folder: t.report_table(specs, folder, prov),
        "controls": lambda specs, folder: t.report_controls(specs, folder, prov, sizes.control_family),
        "critical_windows": lambda specs, folder: t.report_critical_windows(specs, folder, prov, sizes.fig5_tasks),
        "budget": lambda specs, folder: t.report_budget(specs, folder, prov),
        "sensitivity": lambda specs, folder: t.report_sensitivity(specs, folder, prov, sizes.sens_eval_seed),
    }
    for report in ctx.args.reports:
        stage = "protocol" if report in ("table", "critical_windows") else report
        folder = ctx.out / report
        t.start_output(folder, prov)
        writers[report](stage_specs(ctx, STAGES[stage]), folder)


def _reports(text: str) -> tuple[str, ...]:
    chosen = names(text)
    unknown = [r for r in chosen if r not in REPORTS]
    if unknown:
        raise argparse.ArgumentTypeError(f"expected reports from {', '.join(REPORTS)}, got {text!r}")
    return chosen


def _options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--families", type=names, default=None, help="override the scale's policy families")
    p.add_argument("--fig5-tasks", type=names, default=None, help="tasks drawn in Fig. 5 (default: the scale's)")
    p.add_argument("--reports", type=_reports, default=REPORTS, help=f"table: these reports (default: {REPORTS})")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="extra Hydra override for every run")


def _with_options(sizes: PaperSizes, args: argparse.Namespace) -> PaperSizes:
    if args.seeds is not None:
        s = args.seeds
        sizes = replace(sizes, scale=replace(sizes.scale, seeds=s), control_seeds=s, budget_seeds=s, sens_seeds=s)
    if args.fig5_tasks is not None:
        sizes = replace(sizes, fig5_tasks=args.fig5_tasks)
    if args.families is not None:
        sizes = replace(sizes, families=args.families, control_family=args.families[0])
    check_families((*sizes.families, sizes.control_family))
    return sizes


STUDY = Study(
    name="paper",
    about="The paper's experiments: runs via the offline BC recipe, then tables and figures.",
    scales=SIZES,
    stages=STAGES,
    table=table,
    results=lambda scale: f"paper-{scale}",
    options=_options,
    with_options=_with_options,
    announce=True,
)
