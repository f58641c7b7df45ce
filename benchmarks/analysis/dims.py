"""R3 per action dimension: each action dim's loss along R3's recorded demonstrations, recorded again from the runs'
final checkpoints (``python -m benchmarks.analysis dims --from DIR``: :func:`record_all_dims`, written to
``dims.csv.gz``), and its analysis (:func:`label_dims`, :func:`dims_group_table`, :func:`dims_decile_table`,
:func:`dims_markdown`, :func:`plot_dims_time`), which the diagnosis (:mod:`.diagnosis`) adds to its outputs.

The recording rebuilds each run's policy and objective from its final checkpoint and config, records the
demonstrations of its ``weights.csv`` again, and checks that the loss, weight and gripper action equal the run's
own at the last step (to :data:`RECOMPUTE_RTOL`).
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from benchmarks.analysis.pairs import DEFAULT_RUNS, STEP_KEYS, WINDOW, Pairs, load_pairs
from benchmarks.analysis.rebuild import checkpoint_parser, rebuild_final
from benchmarks.studies.protocol import BASELINE, TREATMENT
from benchmarks.studies.writers import fmt_num
from tar_rl.report import Run
from tar_rl.report.phases import label_steps

__all__ = ["DIMS_COLUMNS", "label_dims", "read_dims", "record_all_dims", "record_dims", "write_dims"]

#: The per-action-dimension recording of R3's final checkpoints (written by the ``dims`` command).
DEFAULT_DIMS = DEFAULT_RUNS.parent / "diagnosis" / "dims.csv.gz"
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


# -- Per action dimension: recording the final checkpoints ------------------------------------------


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
    from tar_rl.recipes.record import record_weights
    from tar_rl.runs import weights_columns

    rebuilt = rebuild_final(run, data_root, {} if demos is None else demos, "dims")
    objective, cfg, episodes = rebuilt.objective, rebuilt.cfg, rebuilt.episodes
    rows = record_weights(objective, episodes, cfg.data.slice_len, cfg.optim.steps)
    df = pd.DataFrame(rows, columns=weights_columns(len(rows[0])))
    _check_recomputed(run, df, cfg.optim.steps)
    return df.assign(run=run.name, objective=run.objective, seed=run.seed)[list(DIMS_COLUMNS)]


def _check_recomputed(run: Run, df: pd.DataFrame, step: int) -> None:
    """Refuse a recording that differs from the run's own at ``step`` (other demonstrations, policy or data)."""
    own = run.weights[run.weights["step"] == step].reset_index(drop=True)
    keys = ["task", "episode", "t"]
    if len(own) != len(df) or not (own[keys].to_numpy() == df[keys].to_numpy()).all():
        raise SystemExit(f"dims: {run.name}: the recomputed steps are not those of its weights.csv at {step}")
    for column in ("loss", "weight", "gripper"):
        mine, theirs = df[column].to_numpy(dtype=float), own[column].to_numpy(dtype=float)
        if not np.allclose(mine, theirs, rtol=RECOMPUTE_RTOL, atol=1e-9):
            worst = float(np.max(np.abs(mine - theirs)))
            raise SystemExit(
                f"dims: {run.name}: the recomputed {column} differs from its weights.csv at step {step} "
                f"(largest difference {worst:.3g})"
            )


def record_all_dims(runs_dir: Path, data_root: Path | None = None) -> pd.DataFrame:
    """:func:`record_dims` of every R3 run of ``runs_dir`` (:func:`load_pairs`), ordered by seed, uniform first."""
    pairs = load_pairs(runs_dir)
    demos: dict = {}
    parts = []
    for slot in pairs.runs.values():
        for objective in (BASELINE, TREATMENT):
            print(f"dims: recording {slot[objective].name}", file=sys.stderr)
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
        raise SystemExit(f"dims: no per-dimension recording at {path} (write it with the dims command)")
    df = pd.read_csv(path)
    missing = [c for c in DIMS_COLUMNS if c not in df.columns]
    if missing:
        raise SystemExit(f"dims: {path} lacks the column(s) {missing}")
    return df


# -- Per action dimension: the analysis (of dims.csv.gz alone) --------------------------------------


def xyz_share(df: pd.DataFrame) -> pd.Series:
    """Per step, the share of its loss from the arm's dims: ``(loss_dim0 + loss_dim1 + loss_dim2) / (the four's sum)``
    (NaN where the four are all 0)."""
    total = df[list(DIM_COLUMNS)].sum(axis=1)
    return df[list(XYZ_COLUMNS)].sum(axis=1) / total.where(total > 0)


def label_dims(dims: pd.DataFrame, quantile: float = HIGH_QUANTILE) -> pd.DataFrame:
    """``dims`` rows per run in time order (:func:`tar_rl.report.phases.label_steps`: ``phase``, ``switch``,
    ``near_switch``) with ``xyz_share`` (:func:`xyz_share`), ``high`` (weight at or above the run's ``quantile`` of
    weights, numpy's linear interpolation) and ``decile`` (1-10, the run's steps ranked by weight, ties in row
    order)."""
    parts = []
    for _, one in dims.groupby("run", sort=False):
        one = label_steps(one, STEP_KEYS, WINDOW)
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


def check_dims_runs(pairs: Pairs, dims: pd.DataFrame, path: Path) -> None:
    """Refuse a recording of other runs than the pairs', or of another step than their last."""
    names = {r.name for slot in pairs.runs.values() for r in slot.values()}
    recorded = set(dims["run"])
    if recorded != names:
        missing, other = sorted(names - recorded), sorted(recorded - names)
        raise SystemExit(f"dims: {path} records other runs than R3's pairs (lacking {missing}, extra {other})")
    if set(dims["step"]) != {pairs.steps["last"]}:
        raise SystemExit(f"dims: {path} records steps {sorted(set(dims['step']))}, not {pairs.steps['last']}")


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
        f"{name} {fmt_num(ratios[c], 2)} (TAR lower in {lower[c]} of {seeds} pairs)"
        for name, c in zip(DIM_NAMES, DIM_COLUMNS)
    )
    by_group = groups.groupby(["objective", "split", "group"], sort=False)[["steps", "loss_dim3"]].mean()
    switch_steps, steps = by_group.loc[(t, "switch", "switch"), "steps"], by_group.loc[(t, "all", "all"), "steps"]
    gripper_ratio = (
        by_group.loc[(t, "switch", "switch"), "loss_dim3"] / by_group.loc[(t, "switch", "other"), "loss_dim3"]
    )
    return [
        "- Over all recorded steps the arm's dims (x, y, z) carry on average "
        f"{fmt_num(share[(t, 'all', 'all')], 2)} of a "
        f"step's loss under TAR and {fmt_num(share[(u, 'all', 'all')], 2)} under uniform; of the summed loss "
        "they carry "
        f"{fmt_num(mass[(t, 'all', 'all')], 2)} and {fmt_num(mass[(u, 'all', 'all')], 2)}, the gripper dim the rest.",
        f"- At high-weight steps (TAR weight at or above the run's {int(100 * HIGH_QUANTILE)}th percentile) the xyz "
        f"share is {fmt_num(share[(t, 'weight', 'high')], 2)} against "
        f"{fmt_num(share[(t, 'weight', 'rest')], 2)} at the other steps "
        f"in TAR's runs, and {fmt_num(share[(u, 'weight', 'high')], 2)} against "
        f"{fmt_num(share[(u, 'weight', 'rest')], 2)} in "
        f"uniform's (scored with TAR's weights). By weight decile it goes from {fmt_num(dec[(t, 1)], 2)} (lowest) to "
        f"{fmt_num(dec[(t, 10)], 2)} (highest) in TAR's runs and from {fmt_num(dec[(u, 1)], 2)} to "
        f"{fmt_num(dec[(u, 10)], 2)} in uniform's.",
        f"- At gripper-switch steps ({fmt_num(switch_steps, 0)} of the {fmt_num(steps, 0)} recorded steps of a "
        "run) the xyz "
        f"share is {fmt_num(share[(t, 'switch', 'switch')], 2)} against "
        f"{fmt_num(share[(t, 'switch', 'other')], 2)} at the other "
        f"steps in TAR's runs ({fmt_num(share[(u, 'switch', 'switch')], 2)} against "
        f"{fmt_num(share[(u, 'switch', 'other')], 2)} in "
        f"uniform's); the gripper dim's mean loss there is {fmt_num(gripper_ratio, 0)} times that at the other steps "
        "(TAR's runs).",
        f"- TAR's mean loss per dim at the end of training relative to uniform's (mean over seeds, TAR / uniform): "
        f"{dims_text}; the step loss {fmt_num(ratios['loss'], 2)} (TAR lower in {lower['loss']} of {seeds} pairs).",
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
        dims_means = " / ".join(fmt_num(part[c].mean(), 5) for c in DIM_COLUMNS)
        lines.append(
            f"| {objective} | {labels[(split, group)]} | {fmt_num(part['steps'].mean(), 0)} "
            f"| {fmt_num(part['mean_weight'].mean(), 2)} "
            f"| {fmt_num(part['xyz_share'].mean(), 3)} ({fmt_num(part['xyz_share'].std(), 3)}) "
            f"| {fmt_num(part['xyz_mass'].mean(), 3)} ({fmt_num(part['xyz_mass'].std(), 3)}) | {dims_means} |"
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
            f"| {decile} | {fmt_num(tar['mean_weight'], 2)} | {fmt_num(tar['xyz_share'], 3)} | "
            f"{fmt_num(uni['mean_weight'], 2)} "
            f"| {fmt_num(uni['xyz_share'], 3)} |"
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
            f"| {name} | {fmt_num(uni.mean(), 5)} ({fmt_num(uni.std(), 5)}) | {fmt_num(tar.mean(), 5)} "
            f"({fmt_num(tar.std(), 5)}) "
            f"| {fmt_num(tar.mean() / uni.mean(), 3)} | {int((tar < uni.reindex(tar.index)).sum())} of {len(tar)} |"
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
        "`python -m benchmarks.analysis dims --from DIR` rebuilds each run's policy and objective from its "
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


def dims_main(argv: list[str]) -> int:
    """``dims --from DIR [--data DIR] [--out FILE]``: record R3's final checkpoints per action dimension."""
    parser = checkpoint_parser(
        "dims", "Each action dim's loss along R3's recorded demonstrations.", "R3's runs", DEFAULT_DIMS
    )
    args = parser.parse_args(argv)
    import torch

    torch.set_num_threads(1)  # as R3's runs recorded their weights (threads=1)
    dims = record_all_dims(Path(args.runs), Path(args.data) if args.data else None)
    print(write_dims(dims, Path(args.out)))
    return 0
