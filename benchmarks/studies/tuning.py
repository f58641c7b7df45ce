"""TAR's tuning in the regime study's R3, as pre-registered (``results/regimes/PLAN.md``, "Tuning TAR in R3").

Stages (``python -m benchmarks.studies tuning run STAGE``; every run lands in ``<out>/runs/``, named by its
settings):

* ``tune``: R3's runs (MT50, 50 demonstrations per task, about 20 passes) for TAR over gamma x cap x w_max, the
  two element variants (``tar_arm``, ``tar_dimnorm``) and uniform, on the tuning seeds, evaluated on the tuning
  evaluation seed (2000) only.
* ``select``: applies the selection rule (:func:`select`) to the finished tuning runs and writes
  ``<out>/selected.json``; refused until every tuning run has finished, and refused to change once a final run
  has started.
* ``final``: the selected cell, the selected variant and uniform on the final seeds, with R3's evaluation
  (seed 1000).

``table`` writes ``tuning.md``/``tuning.csv`` (every setting's success and paired difference to uniform on the
tuning seed, per seed, with its fit and weight statistics and their rank correlations with the difference) and,
once final runs finished, ``final.md``/``final.csv`` (paired comparisons to uniform with Holm over the two, and
the MDE; at the cpu scale also tar-rl's defaults as R3 compared them, from the regime study's ``decision.csv``,
and how many final uniform runs reproduce R3's committed ones). ``collect`` keeps no ``weights.csv``: no analysis
of the tuning reads one. The ``ci`` scale runs the same stages on two tasks for a few steps with a smaller grid
(the tests' size).
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from benchmarks.studies import regimes
from benchmarks.studies.cli import RESULTS
from benchmarks.studies.compare import FINAL_SHARE, check_pairs, fit_summary, holm_into, paired
from benchmarks.studies.core import Arm, Grid, Scale, Spec, seed_major
from benchmarks.studies.protocol import BASELINE
from benchmarks.studies.records import provenance, read_json, reproduces
from benchmarks.studies.stages import Context, Gate, Stage, Study, named
from benchmarks.studies.writers import fit_markdown, fmt_p, write_outputs

__all__ = ["SIZES", "STAGES", "STUDY", "Tuning", "select", "settings"]

VARIANTS = ("tar_arm", "tar_dimnorm")  # in the order the plan lists them (a tie goes to the first)
DEFAULTS = {"gamma": 1.0, "cap": "paper", "w_max": 3.0}  # tar-rl's defaults (the paper publishes no values)
TIE = 0.25  # points of success within which two settings tie (the plan's rule)
SELECTED_FILE = "selected.json"


@dataclass(frozen=True)
class Tuning:
    """The tuning's sizes at one scale.

    Attributes:
        scale: the regime study's scale (shared overrides, time model).
        r3: R3's overrides (:mod:`.regimes`), without the evaluation seed.
        gammas, caps, w_maxes: the grid of TAR cells.
        tune_seeds: training seeds of the tuning runs.
        tune_eval_seed: the tuning evaluation seed.
        final_seeds: training seeds of the final runs.
        final_eval_seed: R3's evaluation seed.
    """

    scale: Scale
    r3: tuple[str, ...]
    gammas: tuple[float, ...]
    caps: tuple[str, ...]
    w_maxes: tuple[float, ...]
    tune_seeds: tuple[int, ...]
    tune_eval_seed: int
    final_seeds: tuple[int, ...]
    final_eval_seed: int


def _without_eval_seed(overrides: Sequence[str]) -> tuple[str, ...]:
    return tuple(o for o in overrides if not o.startswith("eval.seed="))


SIZES = {
    "cpu": Tuning(
        scale=regimes.SIZES["cpu"].scale,
        r3=_without_eval_seed(regimes.SIZES["cpu"].r3),
        gammas=(0.25, 0.5, 1.0),
        caps=("paper", "exact"),
        w_maxes=(1.5, 3.0),
        tune_seeds=(0, 1, 2, 3),
        tune_eval_seed=2000,
        final_seeds=(0, 1, 2, 3, 4, 5, 6, 7),
        final_eval_seed=1000,
    ),
    "ci": Tuning(
        scale=regimes.SIZES["ci"].scale,
        r3=_without_eval_seed(regimes.SIZES["ci"].r3),
        gammas=(0.5,),
        caps=("paper",),
        w_maxes=(3.0,),
        tune_seeds=(0,),
        tune_eval_seed=2000,
        final_seeds=(0,),
        final_eval_seed=1000,
    ),
}


# -- Settings ----------------------------------------------------------------------------------------


def cell_name(gamma: float, cap: str, w_max: float) -> str:
    return f"tar-g{gamma:g}-{cap}-w{w_max:g}"


def settings(tuning: Tuning) -> dict[str, tuple[str, ...]]:
    """Every tuned setting by name (the TAR cells, then the variants, then uniform) -> its objective overrides."""
    out = {
        cell_name(g, c, w): ("objective=tar", f"objective.gamma={g}", f"objective.cap={c}", f"objective.w_max={w}")
        for g in tuning.gammas
        for c in tuning.caps
        for w in tuning.w_maxes
    }
    out.update({v: (f"objective={v}",) for v in VARIANTS})
    out[BASELINE] = (f"objective={BASELINE}",)
    return out


def tune_grid(tuning: Tuning) -> Grid:
    """Every setting on the tuning seeds, evaluated on the tuning evaluation seed."""
    arms = tuple(Arm(name, objective) for name, objective in settings(tuning).items())
    base = (*tuning.r3, f"eval.seed={tuning.tune_eval_seed}")
    return Grid("tune", "every setting on the tuning seeds", base, arms, tuning.tune_seeds)


def final_grid(tuning: Tuning, selected: dict) -> Grid:
    """The selected cell, the selected variant and uniform on the final seeds, with R3's evaluation."""
    every = settings(tuning)
    arms = tuple(Arm(name, every[name]) for name in (selected["cell"], selected["variant"], BASELINE))
    base = (*tuning.r3, f"eval.seed={tuning.final_eval_seed}")
    return Grid("final", "the selected settings on the final seeds", base, arms, tuning.final_seeds)


# -- The selection rule ------------------------------------------------------------------------------


def distance(name: str) -> tuple[int, float]:
    """How far a TAR cell lies from tar-rl's defaults: (settings changed, size of the change).

    The size adds ``|log2|`` of gamma's and w_max's ratios to the defaults and 1 for the exact cap, so
    that gamma 0.5 is a smaller change than gamma 0.25 and one changed setting is nearer than two.
    """
    _, g, cap, w = name.split("-")
    gamma, w_max = float(g[1:]), float(w[1:])
    changes = [
        abs(math.log2(gamma / DEFAULTS["gamma"])),
        float(cap != DEFAULTS["cap"]),
        abs(math.log2(w_max / DEFAULTS["w_max"])),
    ]
    return sum(c > 0 for c in changes), sum(changes)


def mean_paired_delta(success: dict[int, float], uniform: dict[int, float]) -> float:
    """Mean over the seeds both have of (setting - uniform) overall success; NaN when none is shared."""
    shared = sorted(set(success) & set(uniform))
    return sum(success[s] - uniform[s] for s in shared) / len(shared) if shared else math.nan


def select(success: dict[str, dict[int, float]]) -> dict:
    """The plan's rule on the tuning seed's overall success (``setting -> seed -> %``, uniform under ``"uniform"``).

    The TAR cell and, separately, the variant with the highest mean paired difference to uniform;
    settings within :data:`TIE` points of the best tie, and a tie goes to the cell nearest the paper's
    defaults (:func:`distance`; then the higher difference) and to the variant listed first in
    :data:`VARIANTS`. Returns ``{"cell", "variant", "deltas"}``.
    """
    uniform = success[BASELINE]
    deltas = {name: mean_paired_delta(values, uniform) for name, values in success.items() if name != BASELINE}
    if any(math.isnan(d) for d in deltas.values()):
        raise SystemExit("tuning: a setting shares no seed with uniform; every tuning run must finish first")
    cells = [n for n in deltas if n.startswith("tar-")]
    best = max(deltas[n] for n in cells)
    cell = min((n for n in cells if deltas[n] >= best - TIE), key=lambda n: (distance(n), -deltas[n]))
    best_variant = max(deltas[v] for v in VARIANTS)
    variant = next(v for v in VARIANTS if deltas[v] >= best_variant - TIE)
    return {"cell": cell, "variant": variant, "deltas": {n: round(d, 6) for n, d in deltas.items()}}


# -- Reading runs --------------------------------------------------------------------------------------


def overall_success(specs: dict[str, list[Spec]]) -> tuple[dict[str, dict[int, float]], dict[str, list]]:
    """``setting -> seed -> overall success %`` of the finished runs, and the loaded runs per setting."""
    from tar_rl.report import load_run, run_percent

    success: dict[str, dict[int, float]] = {}
    loaded: dict[str, list] = {}
    for name, group in specs.items():
        runs = [load_run(s.run_dir) for s in group if s.finished]
        loaded[name] = runs
        success[name] = {r.seed: run_percent(r)[("success", "overall")] for r in runs}
    return success, loaded


def _check_commits(loaded: dict[str, list]) -> None:
    """Refuse a setting's run and uniform's run of one seed trained at different commits or machines (uniform's
    runs may not have finished yet)."""
    for name, runs in loaded.items():
        if name != BASELINE:
            check_pairs([*runs, *loaded.get(BASELINE, [])])


def tuning_table(
    success: dict[str, dict[int, float]], tuning: Tuning, loaded: dict[str, list] | None = None
) -> tuple[str, pd.DataFrame]:
    """Every setting's overall success and paired difference to uniform on the tuning seed, per seed; with the
    loaded runs (``setting -> runs``) also each setting's :func:`.compare.fit_summary` (:func:`fit_section`)."""
    from tar_rl.report import paired_t

    uniform = success.get(BASELINE, {})
    rows = []
    for name, values in success.items():
        shared = sorted(set(values) & set(uniform))
        st = paired_t([values[s] - uniform[s] for s in shared])
        rows.append(
            {
                "setting": name,
                "n_seeds": len(values),
                "success": sum(values.values()) / len(values) if values else math.nan,
                "n_pairs": len(shared),
                "delta": st["mean"] if name != BASELINE else 0.0,
                "ci_low": st["ci_low"] if name != BASELINE else math.nan,
                "ci_high": st["ci_high"] if name != BASELINE else math.nan,
                **{f"seed{s}": values.get(s, math.nan) for s in tuning.tune_seeds},
            }
        )
    df = pd.DataFrame(rows)
    seeds = " | ".join(f"seed {s}" for s in tuning.tune_seeds)
    lines = [
        f"| setting | success % | Δ vs uniform [95% CI] | pairs | {seeds} |",
        "|---" * (4 + len(tuning.tune_seeds)) + "|",
    ]
    for r in rows:
        ci = "" if math.isnan(r["ci_low"]) else f" [{r['ci_low']:+.2f}, {r['ci_high']:+.2f}]"
        delta = "-" if r["setting"] == BASELINE or not r["n_pairs"] else f"{r['delta']:+.2f}{ci}"
        per_seed = " | ".join("-" if math.isnan(r[f"seed{s}"]) else f"{r[f'seed{s}']:.1f}" for s in tuning.tune_seeds)
        success = "-" if math.isnan(r["success"]) else f"{r['success']:.1f}"
        lines.append(f"| {r['setting']} | {success} | {delta} | {r['n_pairs']} | {per_seed} |")
    md = [
        "# TAR's tuning in R3: every setting on the tuning seed",
        "",
        f"R3's runs evaluated on eval.seed = {tuning.tune_eval_seed} only (the final comparisons use "
        f"{tuning.final_eval_seed}). Success in %; Δ = setting - uniform over paired seeds.",
        "",
        *lines,
    ]
    if loaded is not None:
        fit_lines, fit = fit_section(df, loaded)
        df = df.merge(fit, on="setting", how="left")
        md += ["", *fit_lines]
    return "\n".join(md) + "\n", df


def fit_section(deltas: pd.DataFrame, loaded: dict[str, list]) -> tuple[list[str], pd.DataFrame]:
    """Per setting, :func:`.compare.fit_summary` of its (finished) runs, and the Spearman correlation over the TAR
    settings (cells and variants with a paired difference) of the difference to uniform with the largest weight,
    the ESS fraction and the held-out loss: whether the settings that concentrate the weight less, and fit
    held-out steps better, do better."""
    from scipy import stats

    fit = pd.DataFrame([{"setting": name, **fit_summary(runs)} for name, runs in loaded.items()])
    lines = [
        "Fit and weights, means over each setting's runs: the final uniform training loss, the held-out per-step "
        f"loss, the alignment, and over the last {FINAL_SHARE:.0%} of training steps the largest weight in a "
        "segment and the effective-sample-size fraction of the weights (1 = uniform).",
        "",
        *fit_markdown(fit, ("setting",)),
    ]
    both = deltas.merge(fit, on="setting")
    both = both[(both["setting"] != BASELINE) & (both["n_pairs"] > 0)]
    for name, label in (
        ("weight_max", "the largest weight"),
        ("weight_ess", "the ESS fraction"),
        ("heldout_loss", "the held-out loss"),
    ):
        shown = both[both[name].notna()]
        if len(shown) >= 3 and shown[name].nunique() > 1 and shown["delta"].nunique() > 1:  # else undefined
            rho, p = stats.spearmanr(shown["delta"], shown[name])
            n = len(shown)
            lines += ["", f"Spearman correlation of Δ with {label} over {n} TAR settings: {rho:+.2f} (p {fmt_p(p)})."]
    return lines, fit


def paper_reference(decision_csv: Path) -> dict | None:
    """R3's comparison of tar-rl's defaults with uniform (the ``R3`` row of the regime study's
    ``decision.csv``) as a row of :func:`final_table`; ``None`` without that file or row."""
    if not decision_csv.is_file():
        return None
    rows = pd.read_csv(decision_csv).set_index("regime")
    if "R3" not in rows.index:
        return None
    r = rows.loc["R3"]
    return {
        "role": "tar-rl defaults (R3)",
        "setting": cell_name(DEFAULTS["gamma"], DEFAULTS["cap"], DEFAULTS["w_max"]),
        "pairs": int(r["pairs"]),
        "uniform": r["success_uniform"],
        "setting_success": r["success_tar"],
        "delta": r["d_success"],
        "ci_low": r["d_success_ci_low"],
        "ci_high": r["d_success_ci_high"],
        "p": r["p_success"],
        "mde": r["mde_success"],
    }


def uniform_reproduced(final_uniform: Sequence[Path], r3_runs: Path) -> tuple[int, int]:
    """How many of the final uniform runs give the same final rollouts as R3's committed run of the same name
    (under ``r3_runs``), of how many have one: the runs tar-rl's defaults were compared with in R3."""
    pairs = [(run, r3_runs / run.name) for run in final_uniform if (r3_runs / run.name).is_dir()]
    return sum(reproduces(run, committed)[0] for run, committed in pairs), len(pairs)


def final_table(
    loaded: dict[str, list], selected: dict, reference: dict | None = None, reproduced: tuple[int, int] | None = None
) -> tuple[str, pd.DataFrame]:
    """The selected cell and variant against uniform on the final seeds: paired t, Holm over the two, MDE.

    ``reference`` (:func:`paper_reference`) adds tar-rl's defaults as R3 measured them, outside the Holm
    correction; ``reproduced`` (:func:`uniform_reproduced`) says whether R3's uniform runs are the final ones.
    """
    rows = []
    for role in ("cell", "variant"):
        name = selected[role]
        if not loaded.get(name) or not loaded.get(BASELINE):
            continue
        rec = paired([*loaded[BASELINE], *loaded[name]], loaded[name][0].objective)
        rows.append(
            {
                "role": role,
                "setting": name,
                "pairs": int(rec["n_pairs"]),
                "uniform": rec["baseline_mean"],
                "setting_success": rec["objective_mean"],
                "delta": rec["delta_mean"],
                "ci_low": rec["ci_low"],
                "ci_high": rec["ci_high"],
                "p": rec["p_value"],
                "mde": rec["mde"],
            }
        )
    holm_into(rows, "p")
    if reference is not None:
        rows.append({**reference, "holm_p": math.nan})
    lines = [
        "| role | setting | pairs | success % U / S | Δ [95% CI] | p | Holm p | MDE (80%) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['role']} | {r['setting']} | {r['pairs']} | {r['uniform']:.1f} / {r['setting_success']:.1f} "
            f"| {r['delta']:+.2f} [{r['ci_low']:+.2f}, {r['ci_high']:+.2f}] | {fmt_p(r['p'])} "
            f"| {'-' if math.isnan(r['holm_p']) else fmt_p(r['holm_p'])} | {r['mde']:.2f} |"
        )
    notes = [
        "Success in % at R3's evaluation (20 rollouts per task at seed 1000); Δ = setting - uniform over paired "
        "seeds (95% CI, paired t-test); Holm over the cell and the variant."
    ]
    if reference is not None:
        notes.append(
            "tar-rl's defaults (gamma 1, w_max 3, paper cap): R3's own comparison (the regime study), not part of "
            "the correction."
        )
    if reproduced is not None:
        notes.append(
            f"Uniform's final runs give the same rollouts as R3's committed uniform runs in {reproduced[0]} of "
            f"{reproduced[1]} seeds."
        )
    md = ["# TAR's tuning in R3: the selected settings on the final seed", "", *notes, "", *lines]
    return "\n".join(md) + "\n", pd.DataFrame(rows)


# -- The study -------------------------------------------------------------------------------------------


def write_selection(ctx: Context) -> list[Spec]:
    """The ``select`` stage: the rule on the finished tuning runs, written to ``selected.json``."""
    from tar_rl.io import write_json_atomic

    specs = tune_grid(ctx.sizes).specs(ctx.planner)
    unfinished = [s.run_dir.name for s in seed_major(specs) if not s.finished]
    if unfinished:
        names = ", ".join(unfinished[:4])
        raise SystemExit(f"tuning: {len(unfinished)} tuning run(s) have not finished: {names}")
    success, loaded = overall_success(specs)
    _check_commits(loaded)
    choice = select(success)
    path = ctx.out / SELECTED_FILE
    selected = read_json(path)
    if selected is not None and (selected["cell"], selected["variant"]) != (choice["cell"], choice["variant"]):
        started = [s for s in seed_major(final_grid(ctx.sizes, selected).specs(ctx.planner)) if s.run_dir.exists()]
        if started:
            raise SystemExit(f"tuning: final runs of {path}'s choice have started; not changed")
    write_json_atomic(choice, path)
    print(f"selected: cell {choice['cell']}, variant {choice['variant']} ({path})")
    return []


STAGES = named(
    Stage("tune", "every setting on the tuning seeds", grids=lambda ctx: [tune_grid(ctx.sizes)]),
    Stage("select", "the selection rule on the finished tuning runs: selected.json", action=write_selection),
    Stage(
        "final",
        "the selected cell and variant and uniform on the final seeds",
        grids=lambda ctx, selected: [final_grid(ctx.sizes, selected)],
        gates=(
            Gate(
                "the selection record",
                read=lambda ctx: read_json(ctx.out / SELECTED_FILE),
                missing=lambda ctx: f"tuning: no {ctx.out / SELECTED_FILE} yet; run `select` first",
            ),
        ),
    ),
)


def final_outputs(ctx: Context, selected: dict) -> dict[str, tuple[str, pd.DataFrame]]:
    """``final.md``/``final.csv`` once a final run of the selection and uniform's finished (else nothing)."""
    planned = final_grid(ctx.sizes, selected).specs(ctx.planner)
    _, final = overall_success(planned)
    if not final.get(BASELINE) or not (final.get(selected["cell"]) or final.get(selected["variant"])):
        return {}
    _check_commits({k: v for k, v in final.items() if v})
    committed = RESULTS / "regimes"
    reference = paper_reference(committed / "decision.csv") if ctx.args.scale == "cpu" else None
    final_uniform = [s.run_dir for s in planned[BASELINE] if s.finished]
    reproduced = uniform_reproduced(final_uniform, committed / "runs") if reference else None
    return {"final": final_table(final, selected, reference, reproduced)}


def table(ctx: Context) -> None:
    """``tuning.md``/``.csv`` and, once final runs finished, ``final.md``/``.csv`` (module docstring)."""
    success, loaded = overall_success(tune_grid(ctx.sizes).specs(ctx.planner))
    if not any(success.values()):
        raise SystemExit("tuning: no finished tuning run yet")
    _check_commits({k: v for k, v in loaded.items() if v})
    outputs = {"tuning": tuning_table(success, ctx.sizes, loaded)}
    selected = read_json(ctx.out / SELECTED_FILE)
    if selected is not None:
        outputs.update(final_outputs(ctx, selected))
    texts = {f"{name}.md": md for name, (md, _) in outputs.items()}
    tables = {f"{name}.csv": df for name, (_, df) in outputs.items()}
    write_outputs(ctx.tables, texts, tables, provenance(ctx.scale, ctx.study.name, ctx.argv[1:]))
    for md in texts.values():
        print(md)


def _with_options(tuning: Tuning, args: argparse.Namespace) -> Tuning:
    if args.seeds is not None:
        raise SystemExit("tuning: --seeds does not apply (the plan fixes the tuning and final seeds)")
    return tuning


STUDY = Study(
    name="tuning",
    about="TAR's pre-registered tuning in R3: runs and tables.",
    scales=SIZES,
    stages=STAGES,
    table=table,
    results=lambda scale: "regimes/tuning" if scale == "cpu" else None,
    with_options=_with_options,
)
