"""A regime diagnosed (R3 by default; R4 and R5, the chunked heads, with ``--regime``): where TAR's weight goes on
the training demonstrations and which tasks it helps.

Usage::

    python -m benchmarks.analysis diagnosis [--regime R3|R4|R5] [--runs DIR] [--out DIR] [--dims FILE]
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

A chunked-heads regime (``--regime R4``: ``act``; ``R5``: ``flow``) has three arms a seed (uniform, ``tar`` at
tar-rl's defaults, ``tar_gentle``), and the study's results budget keeps the weights of seed 0 only. Its diagnosis
(default ``--out``: ``results/regimes/diagnosis_<head>``) computes the phase and switch tables over the seeds whose
runs all kept their weights (:attr:`.pairs.Pairs.weighted`, named in the output), the per-task Δ over every pair,
and adds:

* ``tasks.csv`` (``tar``) and ``tasks_tar_gentle.csv``: the R3 columns with the arm's per-task weight statistics
  beside them (:func:`weight_stats`: mean weight at switch steps, largest weight, ESS fraction, and the uniform
  policy's loss on the recorded demonstrations; the runs record no held-out loss per task);
* ``correlations.csv``: per arm, the Spearman correlation of the task's Δ with each of :data:`TASK_STATS`, its p and
  the Holm-adjusted p over the arm's statistics;
* ``bins.csv``: per arm and bin of normalised episode time, every seed's mean TAR weight on training demonstrations
  and held-out loss (its ``summary.json``'s fit diagnostics), mean and sd over the seeds;
* ``scatter.png`` (Δ of ``tar`` against each statistic), ``bins.png`` (the bins) and ``weights_time.png``.

The CSV and markdown files are deterministic (fixed float formats). The command refuses, naming what is
missing, a folder without the regime's runs (naming the regime), an incomplete pair, an unfinished run, a run without
its weights (R3; a chunked-heads regime: no seed whose runs all kept them), and a per-dimension recording of other
runs (or any with a chunked-heads regime).
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
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
from benchmarks.analysis.pairs import DEFAULT_RUNS, REGIMES, STEP_KEYS, WINDOW, Pairs, load_pairs, regime
from benchmarks.studies.protocol import BASELINE, TREATMENT
from benchmarks.studies.writers import fmt_num, fmt_p
from tar_rl.report import PHASES, Run, holm
from tar_rl.report.figures import plot_weight_phases
from tar_rl.report.phases import label_steps

__all__ = ["TASK_STATS", "Diagnosis", "default_out", "diagnose", "main", "write"]

DEFAULT_OUT = DEFAULT_DIMS.parent
#: The per-task statistics a chunked-heads regime's Δ is ranked against (column of the task table -> what it is).
TASK_STATS = {
    "switch_share": "share of gripper-switch steps in the recorded demonstrations",
    "weight_switch": "mean weight at gripper-switch steps",
    "weight_max": "largest weight",
    "weight_ess": "ESS fraction of the weights (per demonstration, mean)",
    "uniform_loss": "uniform policy's per-step loss on the recorded demonstrations",
    "uniform": "uniform success (%)",
}
#: Tasks in the weight-against-time figure (largest |Δ|, ties by name).
FIGURE_TASKS = 4
FLOAT = "%.6f"


def default_out(label: str) -> Path:
    """Where the diagnosis of regime ``label`` goes: ``results/regimes/diagnosis`` for R3, ``diagnosis_<head>``
    for a chunked-heads regime (``diagnosis_act`` for R4)."""
    if label == "R3":
        return DEFAULT_OUT
    return DEFAULT_RUNS.parent / f"diagnosis_{regime(label).settings['policy.name']}"


def labelled(pairs: Pairs) -> pd.DataFrame:
    """The labelled weights (:func:`tar_rl.report.phases.label_steps`) of every run of the seeds with weights
    (:attr:`Pairs.weighted`; every seed in R3) with ``objective`` (the arm), ``seed`` and ``at`` (full/last)."""
    names = {v: k for k, v in pairs.steps.items()}
    parts = []
    for seed in pairs.weighted:
        for objective, run in pairs.runs[seed].items():
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


def task_table(pairs: Pairs, df: pd.DataFrame, arm: str = TREATMENT) -> pd.DataFrame:
    """Per task: mean success (percent) of uniform and of ``arm`` (the column named by the arm) over all the
    pairs, Δ = arm - uniform, its standard deviation over pairs, the pairs where the arm is higher / lower, and the
    share of switch steps in the task's recorded demonstrations (those of the first seed with weights' ``arm`` run;
    every run of a regime shares the data seed, so records the same demonstrations)."""
    uniform = pd.DataFrame({s: final_success(p[BASELINE]) for s, p in pairs.runs.items()})
    tar = pd.DataFrame({s: final_success(p[arm]) for s, p in pairs.runs.items()})
    delta = tar - uniform
    demos = df[(df["objective"] == arm) & (df["at"] == "last") & (df["seed"] == min(pairs.weighted))]
    share = demos.groupby("task")["switch"].agg(["sum", "size"])
    out = pd.DataFrame(
        {
            "task": uniform.index,
            "uniform": uniform.mean(axis=1).to_numpy(),
            arm: tar.mean(axis=1).to_numpy(),
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


def correlations(tasks: pd.DataFrame, columns: Sequence[str] = ("switch_share", "uniform")) -> dict:
    """Spearman rank correlation (rho, p) of Δ with each of ``columns`` (default: the switch share and uniform's
    success) over the tasks where both are known; ``nan`` with fewer than 3 such tasks or a constant column (no
    ranking to correlate)."""
    from scipy.stats import spearmanr

    out = {}
    for column in columns:
        ok = tasks[["delta", column]].dropna()
        if len(ok) < 3 or ok["delta"].nunique() < 2 or ok[column].nunique() < 2:
            out[column] = (math.nan, math.nan)
            continue
        rho, p = spearmanr(ok["delta"], ok[column])
        out[column] = (float(rho), float(p))
    return out


def weight_stats(pairs: Pairs, df: pd.DataFrame, arm: str) -> pd.DataFrame:
    """Per task, from the last recording of the seeds with weights (pooled over them): the ``arm`` run's mean
    weight at gripper-switch steps (``weight_switch``, ``nan`` without a switch step), its largest weight
    (``weight_max``), the mean over its recorded demonstrations of their ESS fraction ``(sum w)^2 / (T sum w^2)``
    (``weight_ess``: 1 for equal weights, ``1 / T`` for all the weight on one step), and the uniform run's mean
    per-step loss on the same demonstrations (``uniform_loss``)."""
    last = df[df["at"] == "last"]
    mine = last[last["objective"] == arm]
    per_demo = mine.groupby(["seed", "task", "episode"])["weight"].agg(
        ess=lambda w: float(w.sum() ** 2 / (len(w) * (w**2).sum()))
    )
    switch = mine[mine["switch"]].groupby("task")["weight"].mean()
    out = pd.DataFrame({"weight_max": mine.groupby("task")["weight"].max()})
    out["weight_switch"] = switch.reindex(out.index)
    out["weight_ess"] = per_demo.groupby("task")["ess"].mean()
    out["uniform_loss"] = last[last["objective"] == BASELINE].groupby("task")["loss"].mean()
    return out[["weight_switch", "weight_max", "weight_ess", "uniform_loss"]]


def chunked_task_table(pairs: Pairs, df: pd.DataFrame, arm: str) -> pd.DataFrame:
    """:func:`task_table` of ``arm`` with the task's :func:`weight_stats` beside it."""
    tasks = task_table(pairs, df, arm)
    return tasks.join(weight_stats(pairs, df, arm), on="task")


def correlation_table(tasks_by_arm: dict[str, pd.DataFrame]) -> pd.DataFrame:
    """Per arm and statistic of :data:`TASK_STATS`: the tasks both are known for, the Spearman rank correlation of
    the arm's Δ with it (:func:`correlations`), its p and the Holm-adjusted p over the arm's statistics."""
    rows = []
    for arm, tasks in tasks_by_arm.items():
        corr = correlations(tasks, tuple(TASK_STATS))
        adjusted = holm([corr[c][1] for c in TASK_STATS])
        for column, p_holm in zip(TASK_STATS, adjusted):
            known = int(tasks[["delta", column]].notna().all(axis=1).sum())
            rho, p = corr[column]
            rows.append({"arm": arm, "statistic": column, "tasks": known, "rho": rho, "p": p, "holm_p": p_holm})
    return pd.DataFrame(rows)


def bins_table(pairs: Pairs) -> pd.DataFrame:
    """Per arm and bin of normalised episode time, over every seed (each run's ``summary.json``, its fit
    diagnostics' alignment): TAR's mean weight on the run's training demonstrations and the run's held-out
    per-step loss, mean and standard deviation over the seeds; ``alignment``, the arm's mean Spearman correlation
    of the two over the bins (:func:`tar_rl.diagnostics.alignment`)."""
    rows = []
    for arm in pairs.arms:
        fits = [(pairs.runs[s][arm].summary.get("fit") or {}).get("alignment") or {} for s in pairs.runs]
        weights = pd.DataFrame([f.get("weight_by_bin") for f in fits], dtype=float)
        losses = pd.DataFrame([f.get("heldout_loss_by_bin") for f in fits], dtype=float)
        rhos = pd.Series([f.get("spearman") for f in fits], dtype=float)
        for b in weights.columns:
            rows.append(
                {
                    "arm": arm,
                    "bin": int(b),
                    "start": b / len(weights.columns),
                    "weight": weights[b].mean(),
                    "weight_sd": weights[b].std(),
                    "heldout_loss": losses[b].mean(),
                    "heldout_loss_sd": losses[b].std(),
                    "seeds": int(weights[b].notna().sum()),
                    "alignment": rhos.mean(),
                }
            )
    return pd.DataFrame(rows)


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


def _seed_list(seeds: Sequence[int]) -> str:
    return ", ".join(str(s) for s in seeds)


def _bin_span(b: int, bins: int) -> str:
    """Bin ``b`` of ``bins`` as its span of normalised episode time (``0.0-0.1``)."""
    return f"{fmt_num(b / bins, 1)}-{fmt_num((b + 1) / bins, 1)}"


def _bins_md(bins: pd.DataFrame, arms: Sequence[str]) -> list[str]:
    head = ["bin (episode time)", *(f"weight `{a}` (sd)" for a in arms), *(f"held-out loss `{a}`" for a in arms)]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    by = bins.set_index(["arm", "bin"])
    count = bins["bin"].nunique()
    for b in sorted(bins["bin"].unique()):
        cells = [f"{b} ({_bin_span(b, count)})"]
        cells += [f"{fmt_num(by.loc[(a, b), 'weight'], 2)} ({fmt_num(by.loc[(a, b), 'weight_sd'], 2)})" for a in arms]
        cells += [fmt_num(by.loc[(a, b), "heldout_loss"], 4) for a in arms]
        lines.append("| " + " | ".join(cells) + " |")
    alignment = ", ".join(f"`{a}` {fmt_num(by.loc[(a, 0), 'alignment'], 2, True)}" for a in arms)
    return [
        *lines,
        "",
        f"Alignment (Spearman over the bins of weight and held-out loss, mean over seeds): {alignment}.",
    ]


def _correlation_md(corr: pd.DataFrame) -> list[str]:
    lines = ["| arm | Δ against | tasks | Spearman rho | p | Holm p |", "|---|---|---|---|---|---|"]
    for r in corr.to_dict("records"):
        lines.append(
            f"| {r['arm']} | {TASK_STATS[r['statistic']]} (`{r['statistic']}`) | {r['tasks']} "
            f"| {fmt_num(r['rho'], 3, True)} | {fmt_p(r['p'])} | {fmt_p(r['holm_p'])} |"
        )
    return lines


def _chunked_description(pairs: Pairs, phases, switches, tasks_by_arm: dict, corr: pd.DataFrame, bins) -> list[str]:
    """Plain sentences reading the numbers of a chunked-heads regime's tables (values only)."""
    arm = pairs.arms[1]
    n, seeds = len(pairs.runs), pairs.weighted
    rollouts = pairs.runs[min(pairs.runs)][arm].eval_settings["eval.rollouts"]
    mine = bins[bins["arm"] == arm].sort_values("bin")
    top_bin = mine.sort_values(["weight", "bin"], ascending=[False, True]).iloc[0]
    low_bin = mine.sort_values(["weight", "bin"], ascending=[True, True]).iloc[0]
    loss_bin = mine.sort_values(["heldout_loss", "bin"], ascending=[False, True]).iloc[0]
    last = phases[(phases["objective"] == arm) & (phases["at"] == "last")]
    top = last.sort_values(["ratio", "phase"], ascending=[False, True]).iloc[0]
    low = last.sort_values(["ratio", "phase"], ascending=[True, True]).iloc[0]
    ref = {p: _pick(phases, BASELINE, "last", p)["ratio"] for p in (top["phase"], low["phase"])}
    pooled = switches[(switches["seed"] == "all") & (switches["objective"] == arm)]
    ratios = {r["at"]: r["switch_ratio"] for r in pooled.to_dict("records")}
    per_seed = switches[(switches["seed"] != "all") & (switches["objective"] == arm)]
    above = int((per_seed["switch_ratio"] > 1).sum())
    base = bins[bins["arm"] == BASELINE].set_index("bin")["heldout_loss"]
    change = mine.set_index("bin")["heldout_loss"] - base
    lower = change[change < 0]

    def span(b) -> str:
        return _bin_span(int(b), len(mine))

    lines = [
        f"- Over episode time (all {n} seeds), `{arm}`'s mean weight is highest in the bin "
        f"{span(top_bin['bin'])} ({fmt_num(top_bin['weight'], 2)}, sd {fmt_num(top_bin['weight_sd'], 2)} over seeds) "
        f"and lowest in {span(low_bin['bin'])} ({fmt_num(low_bin['weight'], 2)}); its held-out loss is highest in "
        f"{span(loss_bin['bin'])} ({fmt_num(loss_bin['heldout_loss'], 4)}); alignment "
        f"{fmt_num(top_bin['alignment'], 2, True)}. Against uniform's held-out loss per bin, `{arm}`'s is lower in "
        f"{len(lower)} of {len(change)} bins"
        + (
            f" (most in {span(lower.idxmin())}: {fmt_num(base[lower.idxmin()], 4)} -> "
            f"{fmt_num(base[lower.idxmin()] + lower.min(), 4)})"
            if len(lower)
            else ""
        )
        + f" and higher in {int((change > 0).sum())}.",
        f"- At the last step (seed{'s' if len(seeds) > 1 else ''} {_seed_list(seeds)}), `{arm}`'s weight mass per "
        f"phase relative to the phase's share of steps is highest in {top['phase']} ({fmt_num(top['ratio'], 2)}) "
        f"and lowest in {low['phase']} ({fmt_num(low['ratio'], 2)}); on the uniform policy's losses the same ratios "
        f"are {fmt_num(ref[top['phase']], 2)} and {fmt_num(ref[low['phase']], 2)}.",
        f"- The mean weight at gripper-switch steps is {fmt_num(ratios.get('full'), 2)} times that at the other steps "
        f"when TAR reaches full strength and {fmt_num(ratios.get('last'), 2)} times at the last step; above 1 in "
        f"{above} of {len(per_seed)} (seed, step) recordings.",
    ]
    for name, tasks in tasks_by_arm.items():
        helped, hurt = int((tasks["delta"] > 0).sum()), int((tasks["delta"] < 0).sum())
        mine_corr = corr[corr["arm"] == name]
        found = mine_corr[mine_corr["holm_p"] < 0.05]
        listed = "; ".join(
            f"{r['statistic']} {fmt_num(r['rho'], 2, True)} (p {fmt_p(r['p'])}, Holm {fmt_p(r['holm_p'])})"
            if math.isfinite(r["rho"])
            else f"{r['statistic']} not ranked (constant over the tasks)"
            for r in mine_corr.to_dict("records")
        )
        verdict = "none at Holm p < 0.05" if found.empty else f"at Holm p < 0.05: {', '.join(found['statistic'])}"
        lines.append(
            f"- `{name}`: over {len(tasks)} tasks, higher than uniform in {helped}, lower in {hurt}, equal in "
            f"{len(tasks) - helped - hurt} (mean Δ {fmt_num(tasks['delta'].mean(), 2, True)}). Spearman correlation "
            f"of the task's Δ with {listed}: {verdict}."
        )
    first = tasks_by_arm[arm]
    both = pd.DataFrame({"delta": first["switch_share"], "uniform": first["uniform"]})
    rho, p = correlations(both, ("uniform",))["uniform"]
    lines.append(
        f"- The switch share and uniform's success themselves correlate over the tasks at rho "
        f"{fmt_num(rho, 2, True)} (p {fmt_p(p)}): their rankings of the tasks overlap."
    )
    lines.append(
        f"- A task's Δ rests on {n} pairs of {rollouts} evaluation rollouts per run: one rollout is "
        f"{fmt_num(100 / rollouts, 1)} points of one run's success, {fmt_num(100 / rollouts / n, 2)} points of the "
        f"mean over {n} pairs."
    )
    return lines


def chunked_markdown(diag: Diagnosis) -> str:
    """``diagnosis.md`` of a chunked-heads regime: what the numbers show, the weight over episode time (every
    seed), per phase and at gripper switches (the seeds with weights), and per task (every pair)."""
    pairs = diag.pairs
    label, arms, seeds = pairs.regime, pairs.arms, pairs.weighted
    head = pairs.runs[min(pairs.runs)][BASELINE].policy
    names = {s: " / ".join(slot[a].name for a in arms) for s, slot in pairs.runs.items()}
    tasks_by_arm = {arms[1]: diag.tasks, **{a: diag.extra[f"tasks_{a}"] for a in arms[2:]}}
    with_weights = f"seed{'s' if len(seeds) > 1 else ''} {_seed_list(seeds)}"
    config = pairs.runs[min(seeds)][arms[1]].config
    settings = config.get("diagnostics") or {}
    recorded = (config.get("logging") or {}).get("record_episodes")
    kept = (
        f"only {with_weights} of the {len(pairs.runs)} keep their recorded weights (`weights.csv`, the study's results "
        f"budget), so these tables are over {with_weights} alone"
        + (" and have no spread over seeds" if len(seeds) == 1 else "")
        if len(seeds) < len(pairs.runs)
        else f"every seed keeps its recorded weights (`weights.csv`): these tables are over {with_weights}"
    )
    out = [
        f"# {label} diagnosis (`{head}`): where TAR's weight goes and which tasks it helps",
        "",
        f"From the {len(pairs.runs)} committed {label} seeds ({' / '.join(arms)}: {'; '.join(names.values())}), "
        f"computed by `python -m benchmarks.analysis diagnosis --regime {label}`. `tar` is TAR at tar-rl's "
        "defaults, `tar_gentle` the gentle preset (gamma 0.5, exact cap, w_max 1.5).",
        "",
        f"- **Weights per step** (phases, gripper switches, the per-task weight statistics): {kept}. A run records "
        f"TAR's weights, at its own settings and at full strength, on the per-step losses of {recorded} training "
        f"demonstrations per task at training step {pairs.steps['full']} (TAR reaches full strength) and "
        f"{pairs.steps['last']} (the last); the uniform run's are what TAR at tar-rl's defaults would weigh on the "
        "uniform policy's losses (the reference).",
        "- **Weight over episode time**: every seed, from each run's `summary.json` (its fit diagnostics: TAR's mean "
        f"weight per bin of normalised episode time on {settings.get('train_episodes')} training demonstrations per "
        f"task, the held-out per-step loss on {settings.get('heldout_demos')} held-out demonstrations per task, both "
        "at the end of training).",
        f"- **Per-task Δ**: all {len(pairs.runs)} pairs, success at the final evaluation.",
        "",
        "## What the numbers show",
        "",
        *_chunked_description(
            pairs, diag.phases, diag.switches, tasks_by_arm, diag.extra["correlations"], diag.extra["bins"]
        ),
        "",
        "## Weight over episode time (every seed)",
        "",
        f"Mean over the {len(pairs.runs)} seeds (sd over seeds) of each run's mean TAR weight per bin of normalised "
        "episode time, and of its held-out per-step loss (`bins.csv`).",
        "",
        *_bins_md(diag.extra["bins"], arms),
        "",
        f"## Weight per phase ({with_weights})",
        "",
        "Phases from the gripper action (approach, contact onset, transport, completion; anchored at the first "
        "gripper-closing step). Shares pooled over the 50 tasks' recorded demonstrations; with one seed the sd is "
        "not defined (`-`).",
        "",
        *_phase_md(diag.phases, pairs.steps),
        "",
        f"## Gripper switches ({with_weights})",
        "",
        "A switch step is a step whose gripper action is closing (> 0) while the previous step's is not (<= 0, "
        "zero counts as open), or the reverse, within one demonstration; the first step is never one. "
        f"'Within ±{WINDOW}' is the steps at most {WINDOW} steps from a switch step.",
        "",
        *_switch_md(diag.switches, pairs.steps),
        "",
        "## Per task",
        "",
        f"Δ = arm - uniform success (points), mean over the {len(pairs.runs)} pairs at the final evaluation, ranked "
        f"against the task's statistics (Spearman, over the tasks where the statistic is known; Holm over the "
        f"{len(TASK_STATS)} statistics of an arm). The weight statistics are the arm's own run's at the last step "
        f"({with_weights}); `uniform_loss` is the uniform run's per-step loss on the recorded training "
        "demonstrations: the runs record the held-out loss overall and per phase only, not per task.",
        "",
        *_correlation_md(diag.extra["correlations"]),
        "",
    ]
    for name, tasks in tasks_by_arm.items():
        out += [
            f"`{name}` higher: {_task_list(tasks[tasks['delta'] > 0])}.",
            "",
            f"`{name}` lower: {_task_list(tasks[tasks['delta'] < 0].iloc[::-1])}.",
            "",
        ]
    others = ", ".join(f"`tasks_{a}.csv`" for a in arms[2:])
    out += [
        f"All tasks are in `tasks.csv` (`{arms[1]}`) and {others}; the correlations in `correlations.csv`. Figures: "
        "`scatter.png` (Δ of `tar` against each statistic), `bins.png` (weight and held-out loss over episode time, "
        f"every seed), `weights_time.png` (weight, loss and gripper action along one demonstration of the tasks "
        f"with the largest |Δ|, `{arms[1]}` run of seed {min(seeds)}, last step).",
    ]
    return "\n".join(out) + "\n"


# -- Figures ----------------------------------------------------------------------------------------


#: The scatter panels of R3: (column of the task table, axis label).
SCATTER_R3 = (
    ("switch_share", "share of gripper-switch steps in the recorded demonstrations"),
    ("uniform", "uniform success (%)"),
)


def plot_scatter(
    tasks: pd.DataFrame,
    corr: dict,
    path: Path,
    caption: str,
    panels: Sequence[tuple[str, str]] = SCATTER_R3,
    ylabel: str = "Δ success, TAR - uniform (points)",
) -> Path:
    """Δ success against per-task statistics, one panel per ``(column, label)`` of ``panels`` (default: the switch
    share and uniform's success, side by side; more panels go three to a row), one point per task, titled with
    ``corr[column]`` (rho, p)."""
    from tar_rl.report.plots import new_figure, save_png

    if len(panels) <= 2:
        fig = new_figure(9.0, 4.0)
        fig.subplots_adjust(left=0.08, right=0.98, top=0.88, bottom=0.16, wspace=0.25)
        axes = list(fig.subplots(1, len(panels), squeeze=False)[0])
        first = [axes[0]]
    else:
        rows = math.ceil(len(panels) / 3)
        fig = new_figure(12.0, 3.6 * rows + 0.4)
        fig.subplots_adjust(left=0.06, right=0.98, top=0.93, bottom=0.1, wspace=0.22, hspace=0.45)
        grid = fig.subplots(rows, 3, squeeze=False)
        axes = list(grid.ravel())
        for ax in axes[len(panels) :]:
            ax.set_visible(False)
        first = list(grid[:, 0])
    extremes = tasks.reindex(tasks["delta"].abs().sort_values(ascending=False, kind="stable").index)[:FIGURE_TASKS]
    for ax, (column, label) in zip(axes, panels):
        ax.scatter(tasks[column], tasks["delta"], s=14, color="C0")
        side = {"ha": "left", "xytext": (3, 2)} if column == "switch_share" else {"ha": "right", "xytext": (-3, 2)}
        for r in extremes.to_dict("records"):
            ax.annotate(r["task"], (r[column], r["delta"]), fontsize=6, textcoords="offset points", **side)
        ax.axhline(0.0, color="k", linewidth=0.6)
        ax.set_xlabel(label, fontsize=8)
        rho, p = corr[column]
        ax.set_title(f"Spearman rho {rho:+.2f} (p {fmt_p(p)})", fontsize=9)
    for ax in first:
        ax.set_ylabel(ylabel, fontsize=8)
    return save_png(fig, path, caption)


def plot_time_bins(bins: pd.DataFrame, path: Path, caption: str) -> Path:
    """Two panels over normalised episode time: each arm's mean TAR weight per bin (mean over seeds, the error bar
    one sd over seeds, the unit-mean line) and its held-out per-step loss (the same)."""
    from tar_rl.report.plots import new_figure, save_png

    fig = new_figure(10.0, 4.0)
    fig.subplots_adjust(left=0.07, right=0.98, top=0.86, bottom=0.16, wspace=0.25)
    axes = fig.subplots(1, 2)
    arms = list(dict.fromkeys(bins["arm"]))
    for i, arm in enumerate(arms):
        one = bins[bins["arm"] == arm].sort_values("bin")
        width = 1 / len(one)
        x = one["start"].to_numpy() + width / 2 + (i - (len(arms) - 1) / 2) * width * 0.12
        for ax, column in ((axes[0], "weight"), (axes[1], "heldout_loss")):
            ax.errorbar(
                x,
                one[column],
                yerr=one[f"{column}_sd"].fillna(0.0),
                marker="o",
                markersize=4,
                linewidth=1.2,
                capsize=2,
                color=f"C{i}",
                label=f"{arm} (alignment {one['alignment'].iloc[0]:+.2f})",
            )
    axes[0].axhline(1.0, color="k", linewidth=0.6, linestyle=":")
    axes[0].set_ylabel("TAR's mean weight (training demonstrations)", fontsize=8)
    axes[1].set_ylabel("held-out per-step loss", fontsize=8)
    seeds = int(bins["seeds"].max())
    for ax, title in ((axes[0], "weight per bin of episode time"), (axes[1], "held-out loss per bin")):
        ax.set_xlabel("normalised episode time", fontsize=8)
        ax.set_xlim(0, 1)
        ax.set_title(f"{title} (mean, sd over {seeds} seeds)", fontsize=9)
        ax.grid(True, alpha=0.3)
    axes[0].legend(fontsize=7, loc="upper right")
    return save_png(fig, path, caption)


def figure_tasks(tasks: pd.DataFrame, count: int = FIGURE_TASKS) -> list[str]:
    """The ``count`` tasks with the largest |Δ| (ties by name)."""
    order = tasks.assign(size=-tasks["delta"].abs()).sort_values(["size", "task"], kind="stable")
    return list(order["task"][:count])


# -- Command line -----------------------------------------------------------------------------------


@dataclass
class Diagnosis:
    """What the command computes: the tables, the correlations and the markdown. ``tasks`` and ``corr`` are the
    first treatment arm's (R3: ``tar``); a chunked-heads regime's further tables are in ``extra``."""

    pairs: Pairs
    phases: pd.DataFrame
    switches: pd.DataFrame
    tasks: pd.DataFrame
    corr: dict
    markdown: str
    dims: pd.DataFrame | None = None  # the labelled per-dimension recording (label_dims), if given
    dims_groups: pd.DataFrame | None = None
    dims_deciles: pd.DataFrame | None = None
    #: A chunked-heads regime's further CSVs by name: ``tasks_<arm>`` for each arm after the first, ``correlations``
    #: (:func:`correlation_table`) and ``bins`` (:func:`bins_table`).
    extra: dict[str, pd.DataFrame] = field(default_factory=dict)

    def csv_texts(self) -> dict[str, str]:
        """``phases.csv``, ``switches.csv``, ``tasks.csv``, with the per-dimension recording ``dims_groups.csv`` and
        ``dims_deciles.csv``, and the :attr:`extra` tables, as text (fixed float format)."""
        tables = [("phases", self.phases), ("switches", self.switches), ("tasks", self.tasks)]
        if self.dims_groups is not None:
            tables += [("dims_groups", self.dims_groups), ("dims_deciles", self.dims_deciles)]
        tables += list(self.extra.items())
        return {
            f"{name}.csv": table.to_csv(index=False, float_format=FLOAT, lineterminator="\n") for name, table in tables
        }


def diagnose(runs_dir: Path, dims_path: Path | None = None, label: str = "R3") -> Diagnosis:
    """Everything but the figures, from the runs of regime ``label`` in ``runs_dir`` (:func:`load_pairs` refuses
    what is missing) and, with ``dims_path`` (R3 only), their per-dimension recording (:func:`read_dims`; it must
    record those runs)."""
    pairs = load_pairs(runs_dir, label)
    if label != "R3":
        if dims_path is not None:
            raise SystemExit(f"diagnosis: the per-dimension recording is R3's; {label} has none (leave out --dims)")
        return _diagnose_chunked(pairs)
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


def _diagnose_chunked(pairs: Pairs) -> Diagnosis:
    """A chunked-heads regime's :class:`Diagnosis` (:func:`chunked_markdown`)."""
    df = labelled(pairs)
    phases, switches = phase_table(df), switch_table(df)
    by_arm = {arm: chunked_task_table(pairs, df, arm) for arm in pairs.arms[1:]}
    corr_table = correlation_table(by_arm)
    first = pairs.arms[1]
    extra = {f"tasks_{arm}": by_arm[arm] for arm in pairs.arms[2:]}
    extra |= {"correlations": corr_table, "bins": bins_table(pairs)}
    mine = corr_table[corr_table["arm"] == first]
    corr = {r["statistic"]: (r["rho"], r["p"]) for r in mine.to_dict("records")}
    diag = Diagnosis(pairs, phases, switches, by_arm[first], corr, "", extra=extra)
    diag.markdown = chunked_markdown(diag)
    return diag


def write(diag: Diagnosis, out: Path, figures: bool = True) -> list[Path]:
    """Write the CSV files, ``diagnosis.md`` and (with ``figures``) the PNGs into ``out``, each atomically."""
    from tar_rl.io import atomic_write

    written = []
    for name, text in {**diag.csv_texts(), "diagnosis.md": diag.markdown}.items():
        written.append(atomic_write(out / name, lambda f, text=text: f.write(text)))
    if not figures:
        return written
    pairs = diag.pairs
    arm = pairs.arms[1]
    first = pairs.runs[min(pairs.weighted)][arm]
    commit = first.git_commit or "unknown"
    if pairs.regime == "R3":
        caption = f"R3, {len(pairs.runs)} pairs; git: {commit}"
        written.append(plot_scatter(diag.tasks, diag.corr, out / "scatter.png", caption))
    else:
        caption = f"{pairs.regime} {first.policy}, {arm}: {len(pairs.runs)} pairs; weight statistics of seed "
        caption += f"{_seed_list(pairs.weighted)}; git: {commit}"
        panels = [(c, TASK_STATS[c]) for c in TASK_STATS]
        ylabel = f"Δ success, {arm} - uniform (points)"
        written.append(plot_scatter(diag.tasks, diag.corr, out / "scatter.png", caption, panels, ylabel))
        bins_caption = f"{pairs.regime} {first.policy}: each run's summary.json, {len(pairs.runs)} seeds; git: {commit}"
        written.append(plot_time_bins(diag.extra["bins"], out / "bins.png", bins_caption))
    written.append(
        plot_weight_phases(
            first.weights,
            out / "weights_time.png",
            figure_tasks(diag.tasks),
            step=pairs.steps["last"],
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
                f"{first.name}, final checkpoint (step {pairs.steps['last']}); git: {commit}",
            )
        )
    return written


def main(argv: list[str] | None = None) -> int:
    """Entry point (module docstring)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    p = argparse.ArgumentParser(
        prog="python -m benchmarks.analysis diagnosis", description="Where TAR's weight goes in a regime, per task."
    )
    p.add_argument("--regime", default="R3", choices=REGIMES, help="the regime (default: R3)")
    p.add_argument("--runs", default=str(DEFAULT_RUNS), help="the runs folder (default: results/regimes/runs)")
    p.add_argument(
        "--out",
        default=None,
        help="output folder (default: results/regimes/diagnosis for R3, diagnosis_<head> for R4 and R5)",
    )
    p.add_argument(
        "--dims",
        default=None,
        help="R3's per-dimension recording (default: results/regimes/diagnosis/dims.csv.gz with R3 and the default "
        "--runs)",
    )
    args = p.parse_args(argv)
    out = Path(args.out) if args.out else default_out(args.regime)
    default_dims = DEFAULT_DIMS if args.regime == "R3" and Path(args.runs) == DEFAULT_RUNS else None
    dims = Path(args.dims) if args.dims else default_dims
    for path in write(diagnose(Path(args.runs), dims, args.regime), out):
        print(path)
    return 0
