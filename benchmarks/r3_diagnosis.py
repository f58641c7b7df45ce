"""Regime R3 diagnosed: where TAR's weight goes on the training demonstrations and which tasks it helps.

Usage::

    python benchmarks/r3_diagnosis.py [--runs DIR] [--out DIR]

Reads the committed runs of the regime study (``--runs``, default ``results/regimes/runs``), keeps the
R3 runs (the config's ``data.tasks``, ``data.n_demos`` and ``optim.steps`` are R3's in ``regimes.py``),
pairs them by seed (uniform, tar) and writes into ``--out`` (default ``results/regimes/diagnosis``):

* ``phases.csv``: per objective, recording step and phase (:func:`tar_rl.report.phase_labels`), the
  phase's share of the recorded steps, its share of the weight mass and its mean weight, pooled over
  tasks, mean and standard deviation over seeds. The uniform runs record what TAR would weigh on the
  uniform policy's losses: they are the reference.
* ``switches.csv``: per objective, recording step and seed (and pooled over seeds), the mean weight and
  loss at gripper-switch steps against the other steps, and within :data:`WINDOW` steps of a switch
  against outside it (see :func:`switch_steps`).
* ``tasks.csv``: per task, uniform's and TAR's final success over the pairs, their difference Δ, and the
  task's share of switch steps in its recorded demonstrations.
* ``diagnosis.md``: the tables, the rank correlations of Δ with the switch share and with uniform's
  success, the tasks TAR helps and hurts, and a plain description of the numbers.
* ``scatter.png`` (Δ against switch share and against uniform success) and ``weights_time.png`` (weight,
  loss and gripper action along one demonstration of the tasks with the largest |Δ|).

The CSV and markdown files are deterministic (fixed float formats). The command refuses, naming what is
missing, a folder without R3 runs, an incomplete pair, an unfinished run and a run without its weights.
Per-action-dimension weights are not analysed: the runs record one loss per step, summed over dimensions.
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from tar_rl.report import PHASES, Run, load_run, phase_labels

sys.path.insert(0, str(Path(__file__).resolve().parent))  # regimes.py and paper_analysis.py beside this script
from paper_analysis import plot_weight_phases
from regimes import BASELINE, STUDIES, TREATMENT, check_pairs

HERE = Path(__file__).resolve().parent
DEFAULT_RUNS = HERE / "results" / "regimes" / "runs"
DEFAULT_OUT = HERE / "results" / "regimes" / "diagnosis"
#: Steps on either side of a gripper switch that count as near it.
WINDOW = 2
#: Tasks in the weight-against-time figure (largest |Δ|, ties by name).
FIGURE_TASKS = 4
FLOAT = "%.6f"


def r3_settings() -> dict:
    """R3's defining settings (from the study's overrides in ``regimes.py``): tasks, demonstrations, steps,
    and the training step at which TAR reaches full strength (the first recording step)."""
    overrides = dict(o.split("=", 1) for o in STUDIES["cpu"].r3)
    return {
        "data.tasks": yaml.safe_load(overrides["data.tasks"]),
        "data.n_demos": int(overrides["data.n_demos"]),
        "optim.steps": int(overrides["optim.steps"]),
        "full_step": int(yaml.safe_load(overrides["logging.record_weights_at"])[0]),
    }


def _get(config: dict, dotted: str):
    node = config
    for key in dotted.split("."):
        node = node.get(key) if isinstance(node, dict) else None
    return node


@dataclass
class Pairs:
    """R3's runs paired by seed; ``steps`` maps the labels ``full`` and ``last`` to recording steps."""

    runs: dict[int, dict[str, Run]]
    steps: dict[str, int]


def load_pairs(runs_dir: Path) -> Pairs:
    """The R3 runs of ``runs_dir``, one uniform and one tar run per seed.

    Raises:
        SystemExit: no R3 runs, a seed without its two runs (or with more), an unfinished run, or a run
            without weights at both recording steps; the message names what is missing.
    """
    r3 = r3_settings()
    keys = ("data.tasks", "data.n_demos", "optim.steps")
    if not runs_dir.is_dir():
        raise SystemExit(f"r3_diagnosis: {runs_dir} is not a folder")
    found = []
    for path in sorted(p for p in runs_dir.iterdir() if (p / "config.yaml").is_file()):
        config = yaml.safe_load((path / "config.yaml").read_text())
        if all(_get(config, k) == r3[k] for k in keys):
            found.append(load_run(path))
    if not found:
        wanted = ", ".join(f"{k} {r3[k]}" for k in keys)
        raise SystemExit(f"r3_diagnosis: no R3 runs in {runs_dir} (runs whose config has {wanted})")
    steps = {"full": r3["full_step"], "last": r3["optim.steps"]}
    pairs: dict[int, dict[str, Run]] = {}
    for run in found:
        slot = pairs.setdefault(run.seed, {})
        if run.objective not in (BASELINE, TREATMENT) or run.objective in slot:
            raise SystemExit(f"r3_diagnosis: unexpected R3 run {run.name} (seed {run.seed}, {run.objective})")
        slot[run.objective] = run
    for seed, slot in sorted(pairs.items()):
        for objective in (BASELINE, TREATMENT):
            if objective not in slot:
                have = ", ".join(r.name for r in slot.values())
                raise SystemExit(f"r3_diagnosis: R3's pair of seed {seed} is incomplete: no {objective} run ({have})")
        _check_runs(slot, steps)
        check_pairs(list(slot.values()))
    return Pairs(dict(sorted(pairs.items())), steps)


def _check_runs(slot: dict[str, Run], steps: dict[str, int]) -> None:
    for run in slot.values():
        if not run.finished:
            raise SystemExit(f"r3_diagnosis: {run.name} has not finished ({'; '.join(run.notes)})")
        recorded = set() if run.weights is None else set(run.weights["step"].astype(int))
        lacking = sorted(set(steps.values()) - recorded)
        if lacking:
            raise SystemExit(f"r3_diagnosis: {run.name} has no recorded weights at training step(s) {lacking}")
    tasks = {run.eval_settings["tasks"] for run in slot.values()}
    if len(tasks) > 1:
        raise SystemExit(f"r3_diagnosis: the runs {', '.join(r.name for r in slot.values())} evaluated other tasks")


# -- Labelling the recorded steps -------------------------------------------------------------------


def switch_steps(gripper) -> np.ndarray:
    """Gripper-switch steps of one demonstration: the gripper action changes sign from the previous step.

    The sign is taken as closing (``> 0``) or not (``<= 0``, zero counting as open, as in
    :func:`tar_rl.report.first_gripper_close`): a step is a switch step when it is closing and the previous
    step is not, or the reverse. The first step is never a switch step.
    """
    closing = np.asarray(gripper, dtype=float) > 0
    out = np.zeros(len(closing), dtype=bool)
    out[1:] = closing[1:] != closing[:-1]
    return out


def near(flags: np.ndarray, window: int) -> np.ndarray:
    """Steps within ``window`` steps (either side) of a flagged step, the flagged steps included."""
    out = flags.copy()
    for k in range(1, window + 1):
        out[k:] |= flags[:-k]
        out[:-k] |= flags[k:]
    return out


def label_steps(weights: pd.DataFrame, window: int = WINDOW) -> pd.DataFrame:
    """``weights`` rows sorted by (step, task, episode, t), with ``phase``, ``switch`` and ``near_switch``."""
    df = weights.sort_values(["step", "task", "episode", "t"], kind="stable").reset_index(drop=True)
    phase = np.empty(len(df), dtype=object)
    switch = np.zeros(len(df), dtype=bool)
    nearby = np.zeros(len(df), dtype=bool)
    for idx in df.groupby(["step", "task", "episode"], sort=False).indices.values():
        g = df["gripper"].to_numpy()[idx]
        phase[idx] = phase_labels(g)
        switch[idx] = switch_steps(g)
        nearby[idx] = near(switch[idx], window)
    return df.assign(phase=phase, switch=switch, near_switch=nearby)


def labelled(pairs: Pairs) -> pd.DataFrame:
    """Every R3 run's labelled weights (:func:`label_steps`) with ``objective``, ``seed`` and ``at`` (full/last)."""
    names = {v: k for k, v in pairs.steps.items()}
    parts = []
    for seed, slot in pairs.runs.items():
        for objective, run in slot.items():
            w = run.weights[run.weights["step"].isin(list(names))]
            parts.append(label_steps(w).assign(objective=objective, seed=seed))
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


def _f(v: float, digits: int = 2, signed: bool = False) -> str:
    if v is None or not math.isfinite(float(v)):
        return "-"
    return f"{float(v):+.{digits}f}" if signed else f"{float(v):.{digits}f}"


def _phase_md(phases: pd.DataFrame, steps: dict[str, int]) -> list[str]:
    lines = [
        "| objective | training step | phase | share of steps | share of weight (sd) | weight / step share "
        "| mean weight (sd) |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in phases.to_dict("records"):
        lines.append(
            f"| {r['objective']} | {steps[r['at']]} | {r['phase']} | {_f(r['step_share'], 3)} "
            f"| {_f(r['weight_share'], 3)} ({_f(r['weight_share_sd'], 3)}) | {_f(r['ratio'])} "
            f"| {_f(r['mean_weight'])} ({_f(r['mean_weight_sd'])}) |"
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
            f"| {objective} | {steps[at]} | {len(seeds)} | {_f(pooled['weight_switch'])} / "
            f"{_f(pooled['weight_not_switch'])} = {_f(pooled['switch_ratio'])} "
            f"| {_f(seeds['switch_ratio'].mean())} ({_f(seeds['switch_ratio'].std())}) "
            f"| {_f(pooled['weight_near'])} / {_f(pooled['weight_not_near'])} = {_f(pooled['near_ratio'])} "
            f"| {_f(pooled['loss_switch_ratio'])} |"
        )
    return lines


def _task_list(tasks: pd.DataFrame) -> str:
    return ", ".join(f"{t} ({_f(d, 1, True)})" for t, d in zip(tasks["task"], tasks["delta"])) or "none"


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
        f"{top['phase']} ({_f(top['ratio'])}) and lowest in {low['phase']} ({_f(low['ratio'])}); on the uniform "
        f"policy's losses the same ratios are {_f(ref[top['phase']])} and {_f(ref[low['phase']])}.",
        f"- The mean weight at gripper-switch steps is {_f(ratios.get('full'))} times that at the other steps when "
        f"TAR reaches full strength and {_f(ratios.get('last'))} times at the last step (pooled over seeds); the "
        f"ratio is above 1 in {above} of {len(per_seed)} (seed, step) recordings.",
        f"- Over {len(tasks)} tasks, TAR's success is higher than uniform's in {helped}, lower in {hurt} and equal "
        f"in {len(tasks) - helped - hurt}. The Spearman correlation of Δ with the switch share is "
        f"{_f(corr['switch_share'][0], 2, True)} (p {_f(corr['switch_share'][1], 3)}), with uniform's success "
        f"{_f(corr['uniform'][0], 2, True)} (p {_f(corr['uniform'][1], 3)}).",
        f"- {int((tasks['switch_share'] == 0).sum())} tasks have no switch step in their recorded demonstrations; "
        f"{int((tasks['uniform'] >= 100).sum())} tasks have uniform success 100% in every pair.",
        f"- A task's Δ rests on {n} pairs of {rollouts} evaluation rollouts per run: one rollout is "
        f"{_f(100 / rollouts, 1)} points of one run's success, {_f(100 / rollouts / n, 2)} points of the mean over "
        f"{n} pairs.",
    ]


def diagnosis_markdown(pairs: Pairs, phases, switches, tasks, corr) -> str:
    """``diagnosis.md``: the tables, the correlations, the helped and hurt tasks and what the numbers show."""
    names = {s: f"{p[BASELINE].name} / {p[TREATMENT].name}" for s, p in pairs.runs.items()}
    out = [
        "# R3 diagnosis: where TAR's weight goes and which tasks it helps",
        "",
        f"From the {len(pairs.runs)} committed R3 pairs (uniform / TAR: {'; '.join(names.values())}), "
        "computed by `python benchmarks/r3_diagnosis.py`. Weights are TAR's weights at full strength on the "
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
        f"- Δ against the share of switch steps: rho {_f(corr['switch_share'][0], 3, True)}, "
        f"p {_f(corr['switch_share'][1], 3)}",
        f"- Δ against uniform's success: rho {_f(corr['uniform'][0], 3, True)}, p {_f(corr['uniform'][1], 3)}",
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
        "Not analysed: the weight per action dimension (the runs record one loss per step, summed over the "
        "action dimensions).",
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

    def csv_texts(self) -> dict[str, str]:
        """``phases.csv``, ``switches.csv`` and ``tasks.csv`` as text (fixed float format)."""
        return {
            f"{name}.csv": table.to_csv(index=False, float_format=FLOAT, lineterminator="\n")
            for name, table in (("phases", self.phases), ("switches", self.switches), ("tasks", self.tasks))
        }


def diagnose(runs_dir: Path) -> Diagnosis:
    """Everything but the figures, from the R3 runs of ``runs_dir`` (:func:`load_pairs` refuses what is missing)."""
    pairs = load_pairs(runs_dir)
    df = labelled(pairs)
    phases, switches, tasks = phase_table(df), switch_table(df), task_table(pairs, df)
    corr = correlations(tasks)
    return Diagnosis(pairs, phases, switches, tasks, corr, diagnosis_markdown(pairs, phases, switches, tasks, corr))


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
    return written


def main(argv: list[str] | None = None) -> int:
    """Entry point (module docstring)."""
    p = argparse.ArgumentParser(prog="r3_diagnosis.py", description="Where TAR's weight goes in R3, per task.")
    p.add_argument("--runs", default=str(DEFAULT_RUNS), help="the runs folder (default: results/regimes/runs)")
    p.add_argument("--out", default=str(DEFAULT_OUT), help="output folder (default: results/regimes/diagnosis)")
    args = p.parse_args(argv)
    out = Path(args.out)
    for path in write(diagnose(Path(args.runs)), out):
        print(path)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
