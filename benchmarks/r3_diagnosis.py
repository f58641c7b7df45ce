"""Regime R3 diagnosed: where TAR's weight goes on the training demonstrations and which tasks it helps.

Usage::

    python benchmarks/r3_diagnosis.py [--runs DIR] [--out DIR] [--dims FILE]
    python benchmarks/r3_diagnosis.py dims --from DIR [--data DIR] [--out FILE]

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
* with the per-dimension recording (``--dims``, default ``results/regimes/diagnosis/dims.csv.gz`` with the
  default ``--runs``): ``dims_groups.csv`` (per objective and seed: the share of the step loss from the x, y, z
  dims and each dim's mean loss over all steps, high-weight steps and the rest, switch steps and the others),
  ``dims_deciles.csv`` (the same per weight decile of the run), the section "Per action dimension" of
  ``diagnosis.md`` and ``dims_time.png`` (weight, gripper action and each dim's loss along one demonstration).

The runs record one loss per step (the mean over the action dims). The ``dims`` command records each dim's
loss: for every R3 pair of ``--from`` (runs with their ``checkpoint.pt``, which the committed copies leave out),
it rebuilds the policy and objective from the final checkpoint and config, records the demonstrations of the
run's ``weights.csv`` again (:func:`record_dims`), checks that the loss, weight and gripper action equal the
run's own at the last step, and writes ``dims.csv.gz`` (:data:`DIMS_COLUMNS`). The step at which TAR reaches
full strength has no checkpoint: it is not recorded per dimension.

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

import numpy as np
import pandas as pd
import yaml

from benchmarks.analysis.figures import plot_weight_phases
from benchmarks.studies.compare import check_pairs
from benchmarks.studies.regimes import BASELINE, SIZES, TREATMENT
from tar_rl.report import PHASES, Run, load_run, phase_labels

HERE = Path(__file__).resolve().parent
DEFAULT_RUNS = HERE / "results" / "regimes" / "runs"
DEFAULT_OUT = HERE / "results" / "regimes" / "diagnosis"
#: The per-action-dimension recording of R3's final checkpoints (written by the ``dims`` command).
DEFAULT_DIMS = DEFAULT_OUT / "dims.csv.gz"
#: MetaWorld's action dims: x, y, z (the arm) and the gripper (the last).
DIM_NAMES = ("x", "y", "z", "gripper")
DIM_COLUMNS = tuple(f"loss_dim{i}" for i in range(len(DIM_NAMES)))
XYZ_COLUMNS = DIM_COLUMNS[:3]
#: The columns of ``dims.csv.gz``: ``weights.csv``'s, each action dim's loss, and the run they come from.
DIMS_COLUMNS = ("run", "objective", "seed", "step", "task", "episode", "t", "loss", "weight", "gripper", *DIM_COLUMNS)
#: High-weight steps: weight at or above this quantile of the weights of the step's run.
HIGH_QUANTILE = 0.9
#: Tasks in the per-dimension figure (the first of :func:`figure_tasks`).
DIMS_FIGURE_TASKS = 3
#: Largest relative difference allowed between a recomputed loss or weight and the run's own ``weights.csv``.
RECOMPUTE_RTOL = 1e-5
#: Steps on either side of a gripper switch that count as near it.
WINDOW = 2
#: Tasks in the weight-against-time figure (largest |Δ|, ties by name).
FIGURE_TASKS = 4
FLOAT = "%.6f"


def r3_settings() -> dict:
    """R3's defining settings (from the study's overrides in ``regimes.py``): head, tasks, demonstrations, steps
    (R4 and R5 share the last three with another head), and the training step at which TAR reaches full strength
    (the first recording step)."""
    overrides = dict(o.split("=", 1) for o in SIZES["cpu"].r3)
    return {
        "policy.name": overrides["policy"],
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
    keys = ("policy.name", "data.tasks", "data.n_demos", "optim.steps")
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


def diagnosis_markdown(pairs: Pairs, phases, switches, tasks, corr, dims_section: list[str] | None = None) -> str:
    """``diagnosis.md``: the tables, the correlations, the helped and hurt tasks and what the numbers show, and
    ``dims_section`` (:func:`dims_markdown`; without it, a line saying the dims are not analysed)."""
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


# -- Per action dimension: recording the final checkpoints ------------------------------------------


def _read_checkpoint(path: Path) -> dict:
    """A run's final checkpoint as saved, of any checkpoint format (R3's are of format 1: their ``data_info``
    lacks the task instructions, which the MLP head with a task embedding does not read)."""
    import torch

    if not path.is_file():
        raise SystemExit(f"r3_diagnosis: no checkpoint at {path} (the per-dimension losses need the final policy)")
    state = torch.load(path, map_location="cpu", weights_only=True)
    missing = [k for k in ("config", "data_info", "objective", "step", "finished") if k not in state]
    if missing:
        raise SystemExit(f"r3_diagnosis: {path} is not a training checkpoint (no {', '.join(missing)})")
    return state


class _Demos:
    """The training demonstrations as :func:`recipes.record.demo_episodes` reads them (``data``, ``metadata``)."""

    def __init__(self, data, metadata: dict):
        self.data, self.metadata = data, metadata


def _training_demos(root: Path, cfg, tasks: tuple[str, ...], info: dict, keys) -> _Demos:
    """The run's training dataset under ``root``, read from its memory maps without writing anything.

    The dataset is the folder whose metadata names the run's tasks, demonstrations per task, seed, chunk
    horizon and history; its observation statistics must equal the checkpoint's (the data the policy was
    trained on). Read directly, whatever the dataset format version: R3's is of version 2, which
    :func:`tar_rl.data.load_dataset` refuses; version 3 differs in metadata only, the storage is the same.
    """
    import json

    import torch
    from tensordict import TensorDict

    wanted = {
        "tasks": list(tasks),
        "n_demos": cfg.data.n_demos,
        "seed": cfg.data.seed,
        "chunk_horizon": cfg.data.chunk_horizon,
        "history": cfg.data.history,
    }
    found = []
    for meta_path in sorted(root.glob("*/metadata.json")):
        metadata = json.loads(meta_path.read_text())
        if all(metadata.get(k) == v for k, v in wanted.items()):
            found.append((meta_path.parent, metadata))
    if len(found) != 1:
        raise SystemExit(
            f"r3_diagnosis: {len(found)} datasets under {root} have the settings {wanted} (one is needed); "
            "name the folder holding the runs' training data with --data"
        )
    folder, metadata = found[0]
    if list(metadata["stats"]["observation"]["mean"]) != list(info["obs_mean"]):
        raise SystemExit(f"r3_diagnosis: {folder} holds other data than the checkpoint was trained on")
    total = int(metadata["total_steps"])
    columns = {}
    for name in dict.fromkeys([*keys, "episode", "task_id"]):
        spec = metadata["keys"][name]
        memmap = np.memmap(
            folder / "buffer" / "storage" / f"{name}.memmap",
            dtype=spec["dtype"],
            mode="r",
            shape=(total, *spec["shape"]),
        )
        columns[name] = torch.from_numpy(np.array(memmap))
    return _Demos(TensorDict(columns, [total]), metadata)


def record_dims(run: Run, data_root: Path | None = None, demos: dict | None = None) -> pd.DataFrame:
    """The run's recording at its last step rebuilt from its final checkpoint, with each action dim's loss.

    The policy and objective are built from the checkpoint's config and weights; the demonstrations are those
    of its ``weights.csv`` (the first ``logging.record_episodes`` of each training task); the rows are
    :func:`recipes.record.record_weights`'s (columns :data:`DIMS_COLUMNS`). ``data_root`` defaults to the run's
    ``data.root``; ``demos`` caches the datasets read, across runs.

    Raises:
        SystemExit: no checkpoint, an unfinished one, no training data, or recomputed losses, weights or
            gripper actions that differ from the run's ``weights.csv`` at the last step (beyond
            :data:`RECOMPUTE_RTOL`).
    """
    import torch

    from tar_rl.policies import DataInfo
    from tar_rl.recipes.builders import make_objective, make_policy
    from tar_rl.recipes.record import demo_episodes, record_weights
    from tar_rl.recipes.rundir import with_defaults
    from tar_rl.recipes.validate import validate
    from tar_rl.runs import CHECKPOINT, weights_columns

    state = _read_checkpoint(run.path / CHECKPOINT)
    config = with_defaults(state["config"])
    config["init"] = {"from": None}  # rebuilding needs neither a post-training source nor held-out data
    config["diagnostics"]["heldout_demos"] = 0
    job = validate(config)
    cfg = job.config
    if not state["finished"] or state["step"] != cfg.optim.steps:
        raise SystemExit(f"r3_diagnosis: {run.path} holds step {state['step']} of {cfg.optim.steps}, not the final one")
    torch.manual_seed(cfg.seed)
    policy = make_policy(cfg.policy, DataInfo.from_dict(state["data_info"]))
    objective = make_objective(cfg.objective, cfg.optim.steps, cfg.seed, policy)
    objective.load_state_dict(state["objective"])
    root = Path(data_root or cfg.data.root)
    demos = {} if demos is None else demos
    if root not in demos:
        demos[root] = _training_demos(root, cfg, job.train_tasks, state["data_info"], policy.keys)
    episodes = demo_episodes(demos[root], job.train_tasks, cfg.logging.record_episodes, policy.keys, "cpu")
    rows = record_weights(objective, episodes, cfg.data.slice_len, cfg.optim.steps)
    df = pd.DataFrame(rows, columns=weights_columns(len(rows[0])))
    _check_recomputed(run, df, cfg.optim.steps)
    return df.assign(run=run.name, objective=run.objective, seed=run.seed)[list(DIMS_COLUMNS)]


def _check_recomputed(run: Run, df: pd.DataFrame, step: int) -> None:
    """Refuse a recording that differs from the run's own at ``step`` (other demonstrations, policy or data)."""
    own = run.weights[run.weights["step"] == step].reset_index(drop=True)
    keys = ["task", "episode", "t"]
    if len(own) != len(df) or not (own[keys].to_numpy() == df[keys].to_numpy()).all():
        raise SystemExit(f"r3_diagnosis: {run.name}: the recomputed steps are not those of its weights.csv at {step}")
    for column in ("loss", "weight", "gripper"):
        mine, theirs = df[column].to_numpy(dtype=float), own[column].to_numpy(dtype=float)
        if not np.allclose(mine, theirs, rtol=RECOMPUTE_RTOL, atol=1e-9):
            worst = float(np.max(np.abs(mine - theirs)))
            raise SystemExit(
                f"r3_diagnosis: {run.name}: the recomputed {column} differs from its weights.csv at step {step} "
                f"(largest difference {worst:.3g})"
            )


def record_all_dims(runs_dir: Path, data_root: Path | None = None) -> pd.DataFrame:
    """:func:`record_dims` of every R3 run of ``runs_dir`` (:func:`load_pairs`), ordered by seed, uniform first."""
    pairs = load_pairs(runs_dir)
    demos: dict = {}
    parts = []
    for slot in pairs.runs.values():
        for objective in (BASELINE, TREATMENT):
            print(f"r3_diagnosis: recording {slot[objective].name}", file=sys.stderr)
            parts.append(record_dims(slot[objective], data_root, demos))
    return pd.concat(parts, ignore_index=True)


def write_dims(dims: pd.DataFrame, path: Path) -> Path:
    """``dims`` as a gzip-compressed CSV (floats to 6 significant digits; the same bytes for the same table)."""
    import gzip

    from tar_rl.io import atomic_write

    text = dims.to_csv(index=False, float_format="%.6g", lineterminator="\n").encode()

    def write(f) -> None:
        with gzip.GzipFile(fileobj=f, mode="wb", mtime=0, filename="") as gz:
            gz.write(text)

    return atomic_write(path, write, binary=True)


def read_dims(path: Path) -> pd.DataFrame:
    """A ``dims.csv.gz`` written by :func:`write_dims`.

    Raises:
        SystemExit: no such file, or a file without the columns :data:`DIMS_COLUMNS`.
    """
    if not path.is_file():
        raise SystemExit(f"r3_diagnosis: no per-dimension recording at {path} (write it with the dims command)")
    df = pd.read_csv(path)
    missing = [c for c in DIMS_COLUMNS if c not in df.columns]
    if missing:
        raise SystemExit(f"r3_diagnosis: {path} lacks the column(s) {missing}")
    return df


# -- Per action dimension: the analysis (of dims.csv.gz alone) --------------------------------------


def xyz_share(df: pd.DataFrame) -> pd.Series:
    """Per step, the share of its loss from the arm's dims: ``(loss_dim0 + loss_dim1 + loss_dim2) / (the four's sum)``
    (NaN where the four are all 0)."""
    total = df[list(DIM_COLUMNS)].sum(axis=1)
    return df[list(XYZ_COLUMNS)].sum(axis=1) / total.where(total > 0)


def label_dims(dims: pd.DataFrame, quantile: float = HIGH_QUANTILE) -> pd.DataFrame:
    """``dims`` rows per run in time order (:func:`label_steps`: ``phase``, ``switch``, ``near_switch``) with
    ``xyz_share`` (:func:`xyz_share`), ``high`` (weight at or above the run's ``quantile`` of weights, numpy's
    linear interpolation) and ``decile`` (1-10, the run's steps ranked by weight, ties in row order)."""
    parts = []
    for _, one in dims.groupby("run", sort=False):
        one = label_steps(one)
        w = one["weight"].to_numpy(dtype=float)
        rank = pd.Series(w).rank(method="first").to_numpy()
        decile = np.ceil(10 * rank / len(w)).astype(int)
        parts.append(one.assign(high=w >= np.quantile(w, quantile), decile=decile))
    df = pd.concat(parts, ignore_index=True)
    return df.assign(xyz_share=xyz_share(df))


def _dims_row(one: pd.DataFrame) -> dict:
    arm, total = one[list(XYZ_COLUMNS)].to_numpy().sum(), one[list(DIM_COLUMNS)].to_numpy().sum()
    row = {
        "steps": len(one),
        "mean_weight": one["weight"].mean(),
        "xyz_share": one["xyz_share"].mean(),
        "xyz_mass": arm / total if total > 0 else math.nan,
        "loss": one["loss"].mean(),
    }
    return {**row, **{c: one[c].mean() for c in DIM_COLUMNS}}


#: The step groups of :func:`dims_group_table`: (split, group, the rows it keeps).
GROUPS = (
    ("all", "all", lambda df: np.ones(len(df), dtype=bool)),
    ("weight", "high", lambda df: df["high"].to_numpy()),
    ("weight", "rest", lambda df: ~df["high"].to_numpy()),
    ("switch", "switch", lambda df: df["switch"].to_numpy()),
    ("switch", "other", lambda df: ~df["switch"].to_numpy()),
)


def dims_group_table(df: pd.DataFrame) -> pd.DataFrame:
    """Per objective, seed and step group (:data:`GROUPS`: all steps; high-weight steps and the rest; switch steps
    and the others): the steps, their mean weight, mean ``xyz_share``, the arm's share of their summed loss
    (``xyz_mass``), and the mean loss and mean loss of each action dim."""
    rows = []
    for (objective, seed), one in df.groupby(["objective", "seed"], sort=True):
        for split, group, keep in GROUPS:
            rows.append(
                {"objective": objective, "seed": seed, "split": split, "group": group, **_dims_row(one[keep(one)])}
            )
    return pd.DataFrame(rows)


def dims_decile_table(df: pd.DataFrame) -> pd.DataFrame:
    """Per objective, seed and weight decile of the run (1: the lowest weights): as :func:`dims_group_table`."""
    rows = []
    for (objective, seed, decile), one in df.groupby(["objective", "seed", "decile"], sort=True):
        rows.append({"objective": objective, "seed": seed, "decile": decile, **_dims_row(one)})
    return pd.DataFrame(rows)


def _check_dims_runs(pairs: Pairs, dims: pd.DataFrame, path: Path) -> None:
    """Refuse a recording of other runs than the pairs', or of another step than their last."""
    names = {r.name for slot in pairs.runs.values() for r in slot.values()}
    recorded = set(dims["run"])
    if recorded != names:
        missing, other = sorted(names - recorded), sorted(recorded - names)
        raise SystemExit(f"r3_diagnosis: {path} records other runs than R3's pairs (lacking {missing}, extra {other})")
    if set(dims["step"]) != {pairs.steps["last"]}:
        raise SystemExit(f"r3_diagnosis: {path} records steps {sorted(set(dims['step']))}, not {pairs.steps['last']}")


def _over_seeds(table: pd.DataFrame, keys: list[str], column: str) -> pd.DataFrame:
    """Mean and standard deviation of ``column`` over seeds, per ``keys``."""
    return table.groupby(keys, sort=False)[column].agg(["mean", "std"])


def _dims_description(groups: pd.DataFrame, deciles: pd.DataFrame) -> list[str]:
    """Plain sentences reading the per-dimension numbers (values only)."""
    share = _over_seeds(groups, ["objective", "split", "group"], "xyz_share")["mean"]
    mass = _over_seeds(groups, ["objective", "split", "group"], "xyz_mass")["mean"]
    dec = _over_seeds(deciles, ["objective", "decile"], "xyz_share")["mean"]
    t, u = TREATMENT, BASELINE
    allsteps = groups[(groups["split"] == "all")].set_index(["objective", "seed"])
    ratios, lower = {}, {}
    for column in (*DIM_COLUMNS, "loss"):
        tar, uni = allsteps.loc[t, column], allsteps.loc[u, column]
        ratios[column] = tar.mean() / uni.mean()
        lower[column] = int((tar < uni.reindex(tar.index)).sum())
    seeds = len(allsteps.loc[t])
    dims_text = ", ".join(
        f"{name} {_f(ratios[c])} (TAR lower in {lower[c]} of {seeds} pairs)" for name, c in zip(DIM_NAMES, DIM_COLUMNS)
    )
    by_group = groups.groupby(["objective", "split", "group"], sort=False)[["steps", "loss_dim3"]].mean()
    switch_steps, steps = by_group.loc[(t, "switch", "switch"), "steps"], by_group.loc[(t, "all", "all"), "steps"]
    gripper_ratio = (
        by_group.loc[(t, "switch", "switch"), "loss_dim3"] / by_group.loc[(t, "switch", "other"), "loss_dim3"]
    )
    return [
        f"- Over all recorded steps the arm's dims (x, y, z) carry on average {_f(share[(t, 'all', 'all')])} of a "
        f"step's loss under TAR and {_f(share[(u, 'all', 'all')])} under uniform; of the summed loss they carry "
        f"{_f(mass[(t, 'all', 'all')])} and {_f(mass[(u, 'all', 'all')])}, the gripper dim the rest.",
        f"- At high-weight steps (TAR weight at or above the run's {int(100 * HIGH_QUANTILE)}th percentile) the xyz "
        f"share is {_f(share[(t, 'weight', 'high')])} against {_f(share[(t, 'weight', 'rest')])} at the other steps "
        f"in TAR's runs, and {_f(share[(u, 'weight', 'high')])} against {_f(share[(u, 'weight', 'rest')])} in "
        f"uniform's (scored with TAR's weights). By weight decile it goes from {_f(dec[(t, 1)])} (lowest) to "
        f"{_f(dec[(t, 10)])} (highest) in TAR's runs and from {_f(dec[(u, 1)])} to {_f(dec[(u, 10)])} in uniform's.",
        f"- At gripper-switch steps ({_f(switch_steps, 0)} of the {_f(steps, 0)} recorded steps of a run) the xyz "
        f"share is {_f(share[(t, 'switch', 'switch')])} against {_f(share[(t, 'switch', 'other')])} at the other "
        f"steps in TAR's runs ({_f(share[(u, 'switch', 'switch')])} against {_f(share[(u, 'switch', 'other')])} in "
        f"uniform's); the gripper dim's mean loss there is {_f(gripper_ratio, 0)} times that at the other steps "
        "(TAR's runs).",
        f"- TAR's mean loss per dim at the end of training relative to uniform's (mean over seeds, TAR / uniform): "
        f"{dims_text}; the step loss {_f(ratios['loss'])} (TAR lower in {lower['loss']} of {seeds} pairs).",
    ]


def _dims_md(groups: pd.DataFrame, deciles: pd.DataFrame, dims_seeds: int) -> list[str]:
    labels = {
        ("all", "all"): "all steps",
        ("weight", "high"): f"weight >= run's p{int(100 * HIGH_QUANTILE)}",
        ("weight", "rest"): "the other steps",
        ("switch", "switch"): "gripper-switch steps",
        ("switch", "other"): "non-switch steps",
    }
    lines = [
        "| objective | step group | steps per run | mean weight | xyz share of step loss (sd) "
        "| xyz share of summed loss (sd) | mean loss x / y / z / gripper |",
        "|---|---|---|---|---|---|---|",
    ]
    for (objective, split, group), part in groups.groupby(["objective", "split", "group"], sort=False):
        dims_means = " / ".join(_f(part[c].mean(), 5) for c in DIM_COLUMNS)
        lines.append(
            f"| {objective} | {labels[(split, group)]} | {_f(part['steps'].mean(), 0)} "
            f"| {_f(part['mean_weight'].mean())} "
            f"| {_f(part['xyz_share'].mean(), 3)} ({_f(part['xyz_share'].std(), 3)}) "
            f"| {_f(part['xyz_mass'].mean(), 3)} ({_f(part['xyz_mass'].std(), 3)}) | {dims_means} |"
        )
    lines += [
        "",
        "By weight decile of each run (1: the lowest tenth of its steps by TAR weight), mean over seeds:",
        "",
        "| decile | TAR: mean weight | TAR: xyz share | uniform: mean weight | uniform: xyz share |",
        "|---|---|---|---|---|",
    ]
    by = deciles.groupby(["objective", "decile"], sort=True)[["mean_weight", "xyz_share"]].mean()
    for decile in sorted(deciles["decile"].unique()):
        tar, uni = by.loc[(TREATMENT, decile)], by.loc[(BASELINE, decile)]
        lines.append(
            f"| {decile} | {_f(tar['mean_weight'])} | {_f(tar['xyz_share'], 3)} | {_f(uni['mean_weight'])} "
            f"| {_f(uni['xyz_share'], 3)} |"
        )
    allsteps = groups[groups["split"] == "all"].set_index(["objective", "seed"])
    lines += [
        "",
        f"Mean loss per action dim over all recorded steps at the last step, mean (sd) over the {dims_seeds} seeds:",
        "",
        "| dim | uniform | TAR | TAR / uniform | pairs with TAR lower |",
        "|---|---|---|---|---|",
    ]
    for name, c in (*zip(DIM_NAMES, DIM_COLUMNS), ("step loss (mean of the four)", "loss")):
        tar, uni = allsteps.loc[TREATMENT, c], allsteps.loc[BASELINE, c]
        lines.append(
            f"| {name} | {_f(uni.mean(), 5)} ({_f(uni.std(), 5)}) | {_f(tar.mean(), 5)} ({_f(tar.std(), 5)}) "
            f"| {_f(tar.mean() / uni.mean(), 3)} | {int((tar < uni.reindex(tar.index)).sum())} of {len(tar)} |"
        )
    return lines


def dims_markdown(pairs: Pairs, groups: pd.DataFrame, deciles: pd.DataFrame) -> list[str]:
    """The section "Per action dimension" of ``diagnosis.md``."""
    seeds = groups["seed"].nunique()
    return [
        "## Per action dimension",
        "",
        f"Each step's loss split over MetaWorld's action dims (x, y, z, gripper), along the same recorded "
        f"demonstrations (3 per task), from the final checkpoints of the {seeds} pairs at step {pairs.steps['last']}: "
        "`python benchmarks/r3_diagnosis.py dims --from DIR` rebuilds each run's policy and objective from its "
        "checkpoint and config and records again: the loss, weight and gripper action equal the runs' own at that "
        f"step (checked, to a relative {RECOMPUTE_RTOL:g}), with each dim's loss beside them (`dims.csv.gz`). "
        f"Step {pairs.steps['full']}, where TAR reaches full strength, is not analysed per dimension: no checkpoint "
        "holds that step. The step loss is the mean of "
        "the four dims' squared errors; the xyz share of a step is (x + y + z) / (x + y + z + gripper) of its "
        "losses. The weight is TAR's (window-averaged, at full strength) in both objectives' runs: in uniform's it "
        "is what TAR would weigh on the uniform policy's losses. High-weight steps: weight at or above the "
        f"{int(100 * HIGH_QUANTILE)}th percentile of the run's recorded weights (a tenth of its steps). Switch steps "
        "as above. Mean (sd) over seeds of each run's value.",
        "",
        *_dims_description(groups, deciles),
        "",
        *_dims_md(groups, deciles, seeds),
        "",
        "Tables: `dims_groups.csv`, `dims_deciles.csv` (per seed). Figure: `dims_time.png` (TAR weight, gripper "
        f"action and each dim's loss along one demonstration of the {DIMS_FIGURE_TASKS} tasks with the largest |Δ|, "
        "TAR run of seed 0, last step).",
    ]


def plot_dims_time(labelled_dims: pd.DataFrame, run: str, tasks: list[str], path: Path, caption: str) -> Path:
    """Per task (columns): TAR weight and gripper action (top), each action dim's loss on a log scale (bottom),
    along the run's first recorded demonstration of the task; gripper-switch steps dotted."""
    from matplotlib.lines import Line2D

    from tar_rl.report.plots import new_figure, save_png

    fig = new_figure(4.0 * len(tasks), 5.2)
    fig.subplots_adjust(left=0.07, right=0.93, top=0.9, bottom=0.12, wspace=0.38, hspace=0.12)
    axes = fig.subplots(2, len(tasks), sharex="col", squeeze=False)
    df = labelled_dims[labelled_dims["run"] == run]
    for k, task in enumerate(tasks):
        one = df[df["task"] == task]
        one = one[one["episode"] == one["episode"].min()].sort_values("t")
        t = one["t"].to_numpy()
        top, bottom = axes[0, k], axes[1, k]
        grip = top.twinx()
        top.plot(t, one["weight"], color="k", linewidth=1.2)
        top.axhline(1.0, color="k", linestyle=":", linewidth=0.6)
        grip.plot(t, one["gripper"], color="C4", linewidth=1.0, linestyle="--", drawstyle="steps-mid")
        grip.set_ylim(-1.15, 1.15)
        for i, c in enumerate(DIM_COLUMNS):
            bottom.plot(t, one[c].clip(lower=1e-8), color=f"C{i}", linewidth=1.0)
        bottom.set_yscale("log")
        for s in t[one["switch"].to_numpy()]:
            for ax in (top, bottom):
                ax.axvline(s, color="k", linestyle=":", linewidth=0.7)
        top.set_title(f"{task}, episode {int(one['episode'].iloc[0])}", fontsize=9)
        top.set_ylabel("TAR weight", fontsize=8)
        grip.set_ylabel("gripper action", color="C4", fontsize=8)
        bottom.set_ylabel("loss per action dim", fontsize=8)
        bottom.set_xlabel("time step t", fontsize=8)
        for ax in (top, bottom, grip):
            ax.tick_params(labelsize=7)
    handles = [
        Line2D([], [], color="k", label="TAR weight"),
        Line2D([], [], color="C4", linestyle="--", label="gripper action"),
        *(Line2D([], [], color=f"C{i}", label=f"loss {name}") for i, name in enumerate(DIM_NAMES)),
        Line2D([], [], color="k", linestyle=":", linewidth=0.7, label="gripper switch"),
    ]
    fig.legend(handles=handles, loc="upper center", ncol=len(handles), fontsize=8, frameon=False)
    return save_png(fig, path, caption)


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
        _check_dims_runs(pairs, raw, dims_path)
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


def dims_main(argv: list[str]) -> int:
    """``dims --from DIR [--data DIR] [--out FILE]``: record R3's final checkpoints per action dimension."""
    p = argparse.ArgumentParser(
        prog="r3_diagnosis.py dims", description="Each action dim's loss along R3's recorded demonstrations."
    )
    p.add_argument("--from", dest="runs", required=True, help="the folder holding R3's runs with their checkpoints")
    p.add_argument("--data", default=None, help="the folder holding their training dataset (default: data.root)")
    p.add_argument("--out", default=str(DEFAULT_DIMS), help="the CSV to write (default: results/regimes/diagnosis)")
    args = p.parse_args(argv)
    import torch

    torch.set_num_threads(1)  # as R3's runs recorded their weights (threads=1)
    dims = record_all_dims(Path(args.runs), Path(args.data) if args.data else None)
    print(write_dims(dims, Path(args.out)))
    return 0


def main(argv: list[str] | None = None) -> int:
    """Entry point (module docstring)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["dims"]:
        return dims_main(argv[1:])
    p = argparse.ArgumentParser(prog="r3_diagnosis.py", description="Where TAR's weight goes in R3, per task.")
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


if __name__ == "__main__":
    raise SystemExit(main())
