"""Regime R3 diagnosed: where TAR's weight goes on the training demonstrations and which tasks it helps.

Usage::

    python -m benchmarks.analysis diagnosis [--runs DIR] [--out DIR] [--dims FILE]
    python -m benchmarks.analysis dims --from DIR [--data DIR] [--out FILE]

Reads the committed runs of the regime study (``--runs``, default ``results/regimes/runs``), keeps the
R3 runs (the config's head, ``data.tasks``, ``data.n_demos`` and ``optim.steps`` are R3's in
:mod:`benchmarks.studies.regimes`; :mod:`.pairs`), pairs them by seed (uniform, tar) and writes into ``--out``
(default ``results/regimes/diagnosis``):

* ``phases.csv``: per objective, recording step and phase (:func:`tar_rl.report.phase_labels`), the
  phase's share of the recorded steps, its share of the weight mass and its mean weight, pooled over
  tasks, mean and standard deviation over seeds. The uniform runs record what TAR would weigh on the
  uniform policy's losses: they are the reference.
* ``switches.csv``: per objective, recording step and seed (and pooled over seeds), the mean weight and
  loss at gripper-switch steps against the other steps, and within :data:`WINDOW` steps of a switch
  against outside it (see :func:`tar_rl.report.phases.switch_steps`).
* ``tasks.csv``: per task, uniform's and TAR's final success over the pairs, their difference Δ, and the
  task's share of switch steps in its recorded demonstrations.
* ``diagnosis.md``: the tables, the rank correlations of Δ with the switch share and with uniform's
  success, the tasks TAR helps and hurts, and a plain description of the numbers.
* ``scatter.png`` (Δ against switch share and against uniform success) and ``weights_time.png`` (weight,
  loss and gripper action along one demonstration of the tasks with the largest |Δ|).
* with the per-dimension recording (``--dims``, default ``results/regimes/diagnosis/dims.csv.gz`` with the
  default ``--runs``): ``dims_groups.csv`` (per objective and seed: the share of the step loss from the x, y, z
  dims and each dim's mean loss over all steps, high-weight steps and the rest, switch steps and the others),
  ``dims_deciles.csv`` (the same per weight decile of the run), the section "Per action dimension" of
  ``diagnosis.md`` and ``dims_time.png`` (weight, gripper action and each dim's loss along one demonstration).

The runs record one loss per step (the mean over the action dims). The ``dims`` command (:mod:`.dims`)
records each dim's loss: for every R3 pair of ``--from`` (runs with their ``checkpoint.pt``, which the committed
copies leave out), it rebuilds the policy and objective from the final checkpoint and config, records the
demonstrations of the run's ``weights.csv`` again (:func:`.dims.record_dims`), checks that the loss, weight and
gripper action equal the run's own at the last step, and writes ``dims.csv.gz`` (:data:`.dims.DIMS_COLUMNS`). The
step at which TAR reaches full strength has no checkpoint: it is not recorded per dimension.

The CSV and markdown files are deterministic (fixed float formats). The command refuses, naming what is
missing, a folder without R3 runs, an incomplete pair, an unfinished run, a run without its weights, and a
per-dimension recording of other runs.
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from benchmarks.analysis.dims import (
    DEFAULT_DIMS,
    DIMS_FIGURE_TASKS,
    check_dims_runs,
    dims_decile_table,
    dims_group_table,
    dims_markdown,
    label_dims,
    plot_dims_time,
    read_dims,
)
from benchmarks.analysis.pairs import DEFAULT_RUNS, STEP_KEYS, WINDOW, Pairs, load_pairs
from benchmarks.studies.protocol import BASELINE, TREATMENT
from benchmarks.studies.writers import fmt_num
from tar_rl.report import PHASES, Run
from tar_rl.report.figures import plot_weight_phases
from tar_rl.report.phases import label_steps

__all__ = ["Diagnosis", "diagnose", "main", "write"]

DEFAULT_OUT = DEFAULT_DIMS.parent
#: Tasks in the weight-against-time figure (largest |Δ|, ties by name).
FIGURE_TASKS = 4
FLOAT = "%.6f"


def labelled(pairs: Pairs) -> pd.DataFrame:
    """Every R3 run's labelled weights (:func:`tar_rl.report.phases.label_steps`) with ``objective``, ``seed`` and
    ``at`` (full/last)."""
    names = {v: k for k, v in pairs.steps.items()}
    parts = []
    for seed, slot in pairs.runs.items():
        for objective, run in slot.items():
            w = run.weights[run.weights["step"].isin(list(names))]
            parts.append(label_steps(w, STEP_KEYS, WINDOW).assign(objective=objective, seed=seed))
    df = pd.concat(parts, ignore_index=True)
    return df.assign(at=df["step"].map(names))


# -- Tables -----------------------------------------------------------------------------------------


def phase_table(df: pd.DataFrame) -> pd.DataFrame:
    """Per (objective, at, phase): step share, weight share and mean weight, pooled over tasks, mean and
    standard deviation over seeds; ``ratio`` = weight share / step share (> 1: more than its share)."""
    rows = []
    for (objective, at, seed), one in df.groupby(["objective", "at", "seed"], sort=True):
        total = one["weight"].sum()
        for phase in PHASES:
            sel = one[one["phase"] == phase]
            rows.append(
                {
                    "objective": objective,
                    "at": at,
                    "phase": phase,
                    "seed": seed,
                    "step_share": len(sel) / len(one),
                    "weight_share": sel["weight"].sum() / total,
                    "mean_weight": sel["weight"].mean() if len(sel) else math.nan,
                }
            )
    per_seed = pd.DataFrame(rows)
    out = per_seed.groupby(["objective", "at", "phase"], sort=False).agg(
        step_share=("step_share", "mean"),
        weight_share=("weight_share", "mean"),
        weight_share_sd=("weight_share", "std"),
        mean_weight=("mean_weight", "mean"),
        mean_weight_sd=("mean_weight", "std"),
        seeds=("seed", "nunique"),
    )
    out = out.reset_index()
    return out.assign(ratio=out["weight_share"] / out["step_share"])


def _ratio_row(one: pd.DataFrame) -> dict:
    sw, near_ = one["switch"].to_numpy(), one["near_switch"].to_numpy()
    w, loss = one["weight"].to_numpy(dtype=float), one["loss"].to_numpy(dtype=float)
    row = {"steps": len(one), "switch_steps": int(sw.sum())}
    for name, sel in (("switch", sw), ("near", near_)):
        row[f"weight_{name}"] = w[sel].mean() if sel.any() else math.nan
        row[f"weight_not_{name}"] = w[~sel].mean() if (~sel).any() else math.nan
        row[f"{name}_ratio"] = row[f"weight_{name}"] / row[f"weight_not_{name}"]
        row[f"loss_{name}_ratio"] = loss[sel].mean() / loss[~sel].mean() if sel.any() and (~sel).any() else math.nan
    return row


def switch_table(df: pd.DataFrame) -> pd.DataFrame:
    """Per (objective, at) and seed, then pooled over seeds (``seed`` = ``all``): mean weight at switch steps
    and at the others and their ratio; the same within :data:`WINDOW` steps of a switch (``near``) and for the loss."""
    rows = []
    for (objective, at), part in df.groupby(["objective", "at"], sort=True):
        for seed, one in part.groupby("seed", sort=True):
            rows.append({"objective": objective, "at": at, "seed": str(seed), **_ratio_row(one)})
        rows.append({"objective": objective, "at": at, "seed": "all", **_ratio_row(part)})
    return pd.DataFrame(rows)


def final_success(run: Run) -> pd.Series:
    """Success rate (percent) per task at the run's final evaluation."""
    rows = run.final[run.final["level"] == "task"]
    return pd.Series(100.0 * rows["success"].to_numpy(dtype=float), index=rows["name"].to_numpy())


def task_table(pairs: Pairs, df: pd.DataFrame) -> pd.DataFrame:
    """Per task: mean success (percent) of uniform and TAR over the pairs, Δ = TAR - uniform, its standard
    deviation over pairs, the pairs where TAR is higher / lower, and the share of switch steps in the task's
    recorded demonstrations (those of the first seed's TAR run; every R3 run shares the data seed, so records
    the same demonstrations)."""
    uniform = pd.DataFrame({s: final_success(p[BASELINE]) for s, p in pairs.runs.items()})
    tar = pd.DataFrame({s: final_success(p[TREATMENT]) for s, p in pairs.runs.items()})
    delta = tar - uniform
    demos = df[(df["objective"] == TREATMENT) & (df["at"] == "last") & (df["seed"] == min(pairs.runs))]
    share = demos.groupby("task")["switch"].agg(["sum", "size"])
    out = pd.DataFrame(
        {
            "task": uniform.index,
            "uniform": uniform.mean(axis=1).to_numpy(),
            "tar": tar.mean(axis=1).to_numpy(),
            "delta": delta.mean(axis=1).to_numpy(),
            "delta_sd": delta.std(axis=1).to_numpy(),
            "pairs_higher": (delta > 0).sum(axis=1).to_numpy(),
            "pairs_lower": (delta < 0).sum(axis=1).to_numpy(),
        }
    )
    out["switch_steps"] = out["task"].map(share["sum"]).fillna(0).astype(int)
    out["demo_steps"] = out["task"].map(share["size"]).fillna(0).astype(int)
    out["switch_share"] = out["switch_steps"] / out["demo_steps"].where(out["demo_steps"] > 0)
    return out.sort_values(["delta", "task"], ascending=[False, True], kind="stable").reset_index(drop=True)


def correlations(tasks: pd.DataFrame) -> dict[str, tuple[float, float]]:
    """Spearman rank correlation (rho, p) of Δ with the switch share and with uniform's success; ``nan``
    with fewer than 3 tasks or a constant column (no ranking to correlate)."""
    from scipy.stats import spearmanr

    out = {}
    for column in ("switch_share", "uniform"):
        ok = tasks[["delta", column]].dropna()
        if len(ok) < 3 or ok["delta"].nunique() < 2 or ok[column].nunique() < 2:
            out[column] = (math.nan, math.nan)
            continue
        rho, p = spearmanr(ok["delta"], ok[column])
        out[column] = (float(rho), float(p))
    return out


# -- Markdown ---------------------------------------------------------------------------------------


def _phase_md(phases: pd.DataFrame, steps: dict[str, int]) -> list[str]:
    lines = [
        "| objective | training step | phase | share of steps | share of weight (sd) | weight / step share "
        "| mean weight (sd) |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in phases.to_dict("records"):
        lines.append(
            f"| {r['objective']} | {steps[r['at']]} | {r['phase']} | {fmt_num(r['step_share'], 3)} "
            f"| {fmt_num(r['weight_share'], 3)} ({fmt_num(r['weight_share_sd'], 3)}) | {fmt_num(r['ratio'], 2)} "
            f"| {fmt_num(r['mean_weight'], 2)} ({fmt_num(r['mean_weight_sd'], 2)}) |"
        )
    return lines


def _switch_md(switches: pd.DataFrame, steps: dict[str, int]) -> list[str]:
    lines = [
        f"| objective | training step | seeds | weight at switch / other | ratio: per-seed mean (sd) "
        f"| weight within ±{WINDOW} / outside | loss ratio switch / other |",
        "|---|---|---|---|---|---|---|",
    ]
    for (objective, at), part in switches.groupby(["objective", "at"], sort=True):
        pooled = part[part["seed"] == "all"].iloc[0]
        seeds = part[part["seed"] != "all"]
        lines.append(
            f"| {objective} | {steps[at]} | {len(seeds)} | {fmt_num(pooled['weight_switch'], 2)} / "
            f"{fmt_num(pooled['weight_not_switch'], 2)} = {fmt_num(pooled['switch_ratio'], 2)} "
            f"| {fmt_num(seeds['switch_ratio'].mean(), 2)} ({fmt_num(seeds['switch_ratio'].std(), 2)}) "
            f"| {fmt_num(pooled['weight_near'], 2)} / {fmt_num(pooled['weight_not_near'], 2)} = "
            f"{fmt_num(pooled['near_ratio'], 2)} "
            f"| {fmt_num(pooled['loss_switch_ratio'], 2)} |"
        )
    return lines


def _task_list(tasks: pd.DataFrame) -> str:
    return ", ".join(f"{t} ({fmt_num(d, 1, True)})" for t, d in zip(tasks["task"], tasks["delta"])) or "none"


def _pick(phases: pd.DataFrame, objective: str, at: str, phase: str) -> pd.Series:
    sel = phases[(phases["objective"] == objective) & (phases["at"] == at) & (phases["phase"] == phase)]
    return sel.iloc[0]


def _description(pairs: Pairs, phases, switches, tasks: pd.DataFrame, corr: dict) -> list[str]:
    """Plain sentences reading the numbers of the tables (values only, no explanation beyond them)."""
    n = len(pairs.runs)
    rollouts = pairs.runs[min(pairs.runs)][TREATMENT].eval_settings["eval.rollouts"]
    tar_last = phases[(phases["objective"] == TREATMENT) & (phases["at"] == "last")]
    top = tar_last.sort_values(["ratio", "phase"], ascending=[False, True]).iloc[0]
    low = tar_last.sort_values(["ratio", "phase"], ascending=[True, True]).iloc[0]
    ref = {p: _pick(phases, BASELINE, "last", p)["ratio"] for p in (top["phase"], low["phase"])}
    pooled = switches[(switches["seed"] == "all") & (switches["objective"] == TREATMENT)]
    ratios = {r["at"]: r["switch_ratio"] for r in pooled.to_dict("records")}
    per_seed = switches[(switches["seed"] != "all") & (switches["objective"] == TREATMENT)]
    above = int((per_seed["switch_ratio"] > 1).sum())
    helped, hurt = int((tasks["delta"] > 0).sum()), int((tasks["delta"] < 0).sum())
    return [
        f"- At the last step, TAR's weight mass per phase relative to the phase's share of steps is highest in "
        f"{top['phase']} ({fmt_num(top['ratio'], 2)}) and lowest in {low['phase']} "
        f"({fmt_num(low['ratio'], 2)}); on the uniform "
        f"policy's losses the same ratios are {fmt_num(ref[top['phase']], 2)} and {fmt_num(ref[low['phase']], 2)}.",
        f"- The mean weight at gripper-switch steps is {fmt_num(ratios.get('full'), 2)} times that at the other "
        "steps when "
        f"TAR reaches full strength and {fmt_num(ratios.get('last'), 2)} times at the last step (pooled over "
        "seeds); the "
        f"ratio is above 1 in {above} of {len(per_seed)} (seed, step) recordings.",
        f"- Over {len(tasks)} tasks, TAR's success is higher than uniform's in {helped}, lower in {hurt} and equal "
        f"in {len(tasks) - helped - hurt}. The Spearman correlation of Δ with the switch share is "
        f"{fmt_num(corr['switch_share'][0], 2, True)} (p {fmt_num(corr['switch_share'][1], 3)}), with uniform's "
        "success "
        f"{fmt_num(corr['uniform'][0], 2, True)} (p {fmt_num(corr['uniform'][1], 3)}).",
        f"- {int((tasks['switch_share'] == 0).sum())} tasks have no switch step in their recorded demonstrations; "
        f"{int((tasks['uniform'] >= 100).sum())} tasks have uniform success 100% in every pair.",
        f"- A task's Δ rests on {n} pairs of {rollouts} evaluation rollouts per run: one rollout is "
        f"{fmt_num(100 / rollouts, 1)} points of one run's success, {fmt_num(100 / rollouts / n, 2)} points of "
        "the mean over "
        f"{n} pairs.",
    ]


def diagnosis_markdown(pairs: Pairs, phases, switches, tasks, corr, dims_section: list[str] | None = None) -> str:
    """``diagnosis.md``: the tables, the correlations, the helped and hurt tasks and what the numbers show, and
    ``dims_section`` (:func:`dims_markdown`; without it, a line saying the dims are not analysed)."""
    names = {s: f"{p[BASELINE].name} / {p[TREATMENT].name}" for s, p in pairs.runs.items()}
    out = [
        "# R3 diagnosis: where TAR's weight goes and which tasks it helps",
        "",
        f"From the {len(pairs.runs)} committed R3 pairs (uniform / TAR: {'; '.join(names.values())}), "
        "computed by `python -m benchmarks.analysis diagnosis`. Weights are TAR's weights at full strength on the "
        f"per-step losses of 3 recorded training demonstrations per task, at training step {pairs.steps['full']} "
        f"(TAR reaches full strength) and {pairs.steps['last']} (the last). The uniform runs' weights are what TAR "
        "would weigh on the uniform policy's losses (the reference).",
        "",
        "## What the numbers show",
        "",
        *_description(pairs, phases, switches, tasks, corr),
        "",
        "## Weight per phase",
        "",
        "Phases from the gripper action (approach, contact onset, transport, completion; anchored at the first "
        "gripper-closing step). Shares pooled over the 50 tasks' recorded demonstrations, mean (sd) over seeds.",
        "",
        *_phase_md(phases, pairs.steps),
        "",
        "## Gripper switches",
        "",
        "A switch step is a step whose gripper action is closing (> 0) while the previous step's is not (<= 0, "
        "zero counts as open), or the reverse, within one demonstration; the first step is never one. "
        f"'Within ±{WINDOW}' is the steps at most {WINDOW} steps from a switch step. Pooled over seeds unless said.",
        "",
        *_switch_md(switches, pairs.steps),
        "",
        "## Per task",
        "",
        f"Δ = TAR - uniform success (points), mean over the {len(pairs.runs)} pairs at the final evaluation. "
        "Spearman rank correlations over the tasks:",
        "",
        f"- Δ against the share of switch steps: rho {fmt_num(corr['switch_share'][0], 3, True)}, "
        f"p {fmt_num(corr['switch_share'][1], 3)}",
        f"- Δ against uniform's success: rho {fmt_num(corr['uniform'][0], 3, True)}, p "
        f"{fmt_num(corr['uniform'][1], 3)}",
        "",
        f"TAR higher: {_task_list(tasks[tasks['delta'] > 0])}.",
        "",
        f"TAR lower: {_task_list(tasks[tasks['delta'] < 0].iloc[::-1])}.",
        "",
        f"Equal: {', '.join(tasks.loc[tasks['delta'] == 0, 'task']) or 'none'}.",
        "",
        "All tasks are in `tasks.csv`. Figures: `scatter.png` (Δ against switch share and uniform success), "
        "`weights_time.png` (weight, loss and gripper action along one demonstration of the tasks with the "
        "largest |Δ|, TAR run of seed 0, last step).",
        "",
        *(
            dims_section
            or [
                "Not analysed: the loss per action dimension (the runs record one loss per step, the mean over the "
                "action dimensions; the dims command records it from the final checkpoints)."
            ]
        ),
    ]
    return "\n".join(out) + "\n"


# -- Figures ----------------------------------------------------------------------------------------


def plot_scatter(tasks: pd.DataFrame, corr: dict, path: Path, caption: str) -> Path:
    """Δ success against the task's switch share and against uniform's success, one point per task."""
    from tar_rl.report.plots import new_figure, save_png

    fig = new_figure(9.0, 4.0)
    fig.subplots_adjust(left=0.08, right=0.98, top=0.88, bottom=0.16, wspace=0.25)
    axes = fig.subplots(1, 2)
    extremes = tasks.reindex(tasks["delta"].abs().sort_values(ascending=False, kind="stable").index)[:FIGURE_TASKS]
    for ax, column, label in (
        (axes[0], "switch_share", "share of gripper-switch steps in the recorded demonstrations"),
        (axes[1], "uniform", "uniform success (%)"),
    ):
        ax.scatter(tasks[column], tasks["delta"], s=14, color="C0")
        side = {"ha": "left", "xytext": (3, 2)} if column == "switch_share" else {"ha": "right", "xytext": (-3, 2)}
        for r in extremes.to_dict("records"):
            ax.annotate(r["task"], (r[column], r["delta"]), fontsize=6, textcoords="offset points", **side)
        ax.axhline(0.0, color="k", linewidth=0.6)
        ax.set_xlabel(label, fontsize=8)
        rho, p = corr[column]
        ax.set_title(f"Spearman rho {rho:+.2f} (p {p:.3f})", fontsize=9)
    axes[0].set_ylabel("Δ success, TAR - uniform (points)", fontsize=8)
    return save_png(fig, path, caption)


def figure_tasks(tasks: pd.DataFrame, count: int = FIGURE_TASKS) -> list[str]:
    """The ``count`` tasks with the largest |Δ| (ties by name)."""
    order = tasks.assign(size=-tasks["delta"].abs()).sort_values(["size", "task"], kind="stable")
    return list(order["task"][:count])


# -- Command line -----------------------------------------------------------------------------------


@dataclass
class Diagnosis:
    """What the command computes: the tables, the correlations and the markdown."""

    pairs: Pairs
    phases: pd.DataFrame
    switches: pd.DataFrame
    tasks: pd.DataFrame
    corr: dict
    markdown: str
    dims: pd.DataFrame | None = None  # the labelled per-dimension recording (label_dims), if given
    dims_groups: pd.DataFrame | None = None
    dims_deciles: pd.DataFrame | None = None

    def csv_texts(self) -> dict[str, str]:
        """``phases.csv``, ``switches.csv``, ``tasks.csv`` and, with the per-dimension recording,
        ``dims_groups.csv`` and ``dims_deciles.csv``, as text (fixed float format)."""
        tables = [("phases", self.phases), ("switches", self.switches), ("tasks", self.tasks)]
        if self.dims_groups is not None:
            tables += [("dims_groups", self.dims_groups), ("dims_deciles", self.dims_deciles)]
        return {
            f"{name}.csv": table.to_csv(index=False, float_format=FLOAT, lineterminator="\n") for name, table in tables
        }


def diagnose(runs_dir: Path, dims_path: Path | None = None) -> Diagnosis:
    """Everything but the figures, from the R3 runs of ``runs_dir`` (:func:`load_pairs` refuses what is missing)
    and, with ``dims_path``, their per-dimension recording (:func:`read_dims`; it must record those runs)."""
    pairs = load_pairs(runs_dir)
    df = labelled(pairs)
    phases, switches, tasks = phase_table(df), switch_table(df), task_table(pairs, df)
    corr = correlations(tasks)
    dims = groups = deciles = section = None
    if dims_path is not None:
        raw = read_dims(dims_path)
        check_dims_runs(pairs, raw, dims_path)
        dims = label_dims(raw)
        groups, deciles = dims_group_table(dims), dims_decile_table(dims)
        section = dims_markdown(pairs, groups, deciles)
    markdown = diagnosis_markdown(pairs, phases, switches, tasks, corr, section)
    return Diagnosis(pairs, phases, switches, tasks, corr, markdown, dims, groups, deciles)


def write(diag: Diagnosis, out: Path, figures: bool = True) -> list[Path]:
    """Write the CSV files, ``diagnosis.md`` and (with ``figures``) the PNGs into ``out``, each atomically."""
    from tar_rl.io import atomic_write

    written = []
    for name, text in {**diag.csv_texts(), "diagnosis.md": diag.markdown}.items():
        written.append(atomic_write(out / name, lambda f, text=text: f.write(text)))
    if figures:
        first = diag.pairs.runs[min(diag.pairs.runs)][TREATMENT]
        caption = f"R3, {len(diag.pairs.runs)} pairs; git: {first.git_commit or 'unknown'}"
        written.append(plot_scatter(diag.tasks, diag.corr, out / "scatter.png", caption))
        written.append(
            plot_weight_phases(
                first.weights,
                out / "weights_time.png",
                figure_tasks(diag.tasks),
                step=diag.pairs.steps["last"],
                caption=f"{first.name}, weights at the last step",
                gripper=True,
            )
        )
        if diag.dims is not None:
            written.append(
                plot_dims_time(
                    diag.dims,
                    first.name,
                    figure_tasks(diag.tasks, DIMS_FIGURE_TASKS),
                    out / "dims_time.png",
                    f"{first.name}, final checkpoint (step {diag.pairs.steps['last']}); "
                    f"git: {first.git_commit or 'unknown'}",
                )
            )
    return written


def main(argv: list[str] | None = None) -> int:
    """Entry point (module docstring)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    p = argparse.ArgumentParser(
        prog="python -m benchmarks.analysis diagnosis", description="Where TAR's weight goes in R3, per task."
    )
    p.add_argument("--runs", default=str(DEFAULT_RUNS), help="the runs folder (default: results/regimes/runs)")
    p.add_argument("--out", default=str(DEFAULT_OUT), help="output folder (default: results/regimes/diagnosis)")
    p.add_argument(
        "--dims",
        default=None,
        help="the per-dimension recording (default: results/regimes/diagnosis/dims.csv.gz with the default --runs)",
    )
    args = p.parse_args(argv)
    out = Path(args.out)
    dims = Path(args.dims) if args.dims else (DEFAULT_DIMS if Path(args.runs) == DEFAULT_RUNS else None)
    for path in write(diagnose(Path(args.runs), dims), out):
        print(path)
    return 0
