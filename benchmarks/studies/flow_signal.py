"""TAR for a sampled loss: R7 of the regime study (``results/regimes/PLAN.md``, "TAR for a sampled loss: R7") as a
study.

R5 found TAR 2.43 points below uniform on the ``flow`` head, whose per-step loss is a random draw of a flow time and
noise that TAR's weights follow. R7 picks, by a pre-registered rule on a pilot, a ranking signal (or per-segment
times) whose order follows the step, and compares TAR with it against uniform. The candidates (:data:`CANDIDATES`):
(a) ``loss`` with per-step times (R5 as it ran), (b) ``action_error``, (c) ``time_normalized``, (d) per-segment
times (``policy.time_sampling=segment``, with ``loss``; the three signals then rank alike). Stages (``python -m
benchmarks.studies flow_signal run STAGE``; runs land in ``<out>/runs``, ``<out>`` being ``results/regimes/r7`` by
default):

* ``pilot``: uniform ``flow`` at R5's settings (``regimes``' R5 overrides), seeds 0 and 1, on the tuning evaluation
  seed 2000, once with ``policy.time_sampling=step`` and once with ``segment``: four runs, seed by seed.
* ``select``: the noise analysis of the pilot's runs (``python -m benchmarks.analysis noise --signals all``: two
  draws on the same recorded segments of every candidate, a ``step`` candidate on the ``step`` runs, (d) on the
  ``segment`` runs, ``time_normalized``'s running mean warmed up first) into ``<out>/pilot_noise.csv`` and ``.md``.
  The plan commits that table before the selection, so a first ``select`` writes the table and stops; once it is
  committed, ``select`` again applies the rule (:func:`select_candidate`) to the table as written and records the
  selection beside R7's runs (``<out>/selection.json``, with the table's digest). Both are refused once R7's runs
  started. The pilot's runs need their checkpoints (in the folder they were trained in).
* ``r7``: R5 with the selected candidate, three arms (``uniform``, ``tar``, ``tar_gentle``) per seed, seeds 0-7 on
  evaluation seed 1000, seed by seed; planned once ``selection.json`` exists, and not at all when it selects (a)
  (R7 is then R5; the record says so).

Each training stage records its plan's digest when its first run starts (``<out>/started.json``); a changed plan is
refused by ``run`` and ``table``. ``--tree DIR`` trains the runs with another checkout's code (R7's commit's
worktree), and runs ``select``'s noise analysis there. ``table`` writes each TAR arm minus uniform over its paired
seeds (a pair trained at different commits, on different machines or devices is refused, naming the runs): mean, 95%
CI, p, Holm over the two, MDE, pairs higher, per group; the arms' fit and weights, the pilot and the selection, and
the per-seed differences (``paired.csv``, which the regime study's paired figure reads), and, exploratory, each R7
TAR arm minus R5's of the same seed over the seeds whose uniform runs roll out alike (``signal_alone.csv``: the
effect of the signal alone); with ``--complete`` a stage with a run of its plan missing is refused.
"""

from __future__ import annotations

import argparse
import hashlib
import math
import subprocess
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import pandas as pd
import yaml

from benchmarks.studies import sweep
from benchmarks.studies.cli import RESULTS, with_seeds
from benchmarks.studies.compare import (
    FINAL_SHARE,
    Comparison,
    check_pairs,
    contrasts,
    finished_runs,
    overall_success,
    stage_fits,
)
from benchmarks.studies.core import Arm, Grid, Scale, Spec, seed_major
from benchmarks.studies.protocol import CHUNKED_ARMS
from benchmarks.studies.records import provenance, read_json
from benchmarks.studies.regimes import SIZES as REGIME_SIZES
from benchmarks.studies.regimes import chunked_base
from benchmarks.studies.stages import Context, Digest, Gate, Stage, Study, named, stage_arms
from benchmarks.studies.writers import (
    comparison_lines,
    fmt_num,
    fmt_p,
    groups_and_fit_lines,
    pending_lines,
    write_outputs,
)

__all__ = [
    "CANDIDATES",
    "COMPARISONS",
    "SIZES",
    "STAGES",
    "STUDY",
    "Candidate",
    "SignalSizes",
    "candidate_means",
    "select_candidate",
]

WHO = "flow_signal"
STARTED_FILE, SELECTION_FILE, NOISE_FILE = "started.json", "selection.json", "pilot_noise.csv"
TIMES = ("step", "segment")  # the pilot's arms: policy.time_sampling
#: The columns of the noise command's table with ranking signals (``benchmarks.analysis.noise.SIGNAL_COLUMNS``, a file
#: this study reads; the analysis sits above the studies, which run it as a command) and what each row measures.
NOISE_MEASURES = ("signal_r", "top_agree", "weight_r_tar", "weight_r_tar_gentle")
NOISE_COLUMNS = ("run", "head", "seed", "time_sampling", "signal", "draws", "segments", "steps", *NOISE_MEASURES)


@dataclass(frozen=True)
class Candidate:
    """A way of ranking the flow head's steps: ``key`` (PLAN.md's letter), ``objective.signal`` and
    ``policy.time_sampling``."""

    key: str
    signal: str
    time_sampling: str

    @property
    def about(self) -> str:
        return f"({self.key}) {self.signal}, {self.time_sampling} times"


#: PLAN.md's candidates in the order that changes training least (the order a tie goes by).
CANDIDATES = (
    Candidate("a", "loss", "step"),
    Candidate("b", "action_error", "step"),
    Candidate("c", "time_normalized", "step"),
    Candidate("d", "loss", "segment"),
)
BY_KEY = {c.key: c for c in CANDIDATES}


@dataclass(frozen=True)
class SignalSizes:
    """R7's sizes at one scale.

    Attributes:
        scale: the regime study's scale (shared overrides, R7's seeds, time model).
        base: the overrides of R5's runs (without seed and objective; evaluation seed 1000).
        pilot_seeds: the pilot's seeds.
        pilot_eval_seed: the pilot's evaluation seed (the tuning seed).
        margin: (d) is eligible when uniform's mean success with per-segment times is at most this many points
            below uniform's with per-step times (or above).
        tie: candidates within this much of the highest mean correlation of TAR's weights tie.
    """

    scale: Scale
    base: tuple[str, ...]
    pilot_seeds: tuple[int, ...]
    pilot_eval_seed: int
    margin: float
    tie: float


_RULE = dict(pilot_eval_seed=2000, margin=1.0, tie=0.02)
SIZES = {
    "cpu": SignalSizes(
        scale=REGIME_SIZES["cpu"].scale, base=chunked_base(REGIME_SIZES["cpu"], "R5"), pilot_seeds=(0, 1), **_RULE
    ),
    "ci": SignalSizes(
        scale=REGIME_SIZES["ci"].scale, base=chunked_base(REGIME_SIZES["ci"], "R5"), pilot_seeds=(0,), **_RULE
    ),
}
# Values compared with a margin are read from tables of six decimals: closer than this counts as equal.
_EPS = 1e-9


# -- The selection rule ------------------------------------------------------------------------------------


def select_candidate(weight_r: dict[str, float], success: dict[str, float], margin: float, tie: float) -> dict:
    """PLAN.md's rule: the candidate with the highest mean within-segment correlation of TAR's weights at tar-rl's
    defaults (``weight_r``, by candidate key); (d) only if uniform's mean success with per-segment times
    (``success["segment"]``, points) is within ``margin`` of uniform's with per-step times (``success["step"]``) or
    above; candidates within ``tie`` of the highest tie, and a tie goes to the first in the order (a), (b), (c), (d).
    A candidate without a finite correlation is not eligible.

    Returns ``candidate`` (its key), ``eligible`` (keys), ``segment_eligible``, ``tied`` (keys within ``tie`` of the
    highest, in order) and ``highest`` (the highest correlation)."""
    segment_eligible = success["segment"] >= success["step"] - margin - _EPS
    eligible = [
        c.key
        for c in CANDIDATES
        if c.key in weight_r and math.isfinite(weight_r[c.key]) and (c.key != "d" or segment_eligible)
    ]
    if not eligible:
        raise SystemExit(f"{WHO}: no candidate has a finite correlation of TAR's weights: {weight_r}")
    highest = max(weight_r[k] for k in eligible)
    tied = [k for k in eligible if weight_r[k] >= highest - tie - _EPS]
    return {
        "candidate": tied[0],
        "eligible": eligible,
        "segment_eligible": bool(segment_eligible),
        "tied": tied,
        "highest": highest,
    }


def candidate_means(table: pd.DataFrame, seeds: Sequence[int]) -> dict[str, dict[str, float]]:
    """Each candidate's measures (:data:`NOISE_MEASURES`, one pass per draw) averaged over the pilot's ``seeds``, from
    the flow rows of a ``noise`` table; refused where a candidate lacks a seed's row."""
    out = {}
    flow = table[(table["head"] == "flow") & (table["draws"] == 1)]
    for c in CANDIDATES:
        rows = flow[(flow["time_sampling"] == c.time_sampling) & (flow["signal"] == c.signal)]
        if sorted(rows["seed"]) != sorted(seeds):
            raise SystemExit(
                f"{WHO}: the noise table has {c.about} for seeds {sorted(rows['seed'])}, not the pilot's {list(seeds)}"
            )
        out[c.key] = {m: float(rows[m].mean()) for m in NOISE_MEASURES}
    return out


# -- The stages ------------------------------------------------------------------------------------------


def pilot_grid(sizes: SignalSizes) -> Grid:
    """The pilot: uniform at R5's settings on the tuning evaluation seed, per time sampling, the pilot's seeds."""
    base = (*sizes.base, f"eval.seed={sizes.pilot_eval_seed}", "objective=uniform")
    arms = tuple(Arm(t, (f"policy.time_sampling={t}",)) for t in TIMES)
    return Grid("pilot", "uniform flow per time sampling", base, arms, sizes.pilot_seeds)


def selection(ctx: Context) -> dict | None:
    """The recorded selection (``selection.json``), or None before ``select`` wrote it."""
    return read_json(ctx.out / SELECTION_FILE)


def r7_grid(sizes: SignalSizes, key: str) -> Grid:
    """R7's runs with candidate ``key`` (not (a), with which R7 is R5): R5's settings with its time sampling and
    signal, the three arms, R7's seeds."""
    c = BY_KEY[key]
    base = (*sizes.base, *([f"policy.time_sampling={c.time_sampling}"] if c.time_sampling != "step" else []))
    signal = (f"objective.signal={c.signal}",) if c.signal != "loss" else ()
    arms = tuple(Arm(a, (f"objective={a}", *signal)) for a in CHUNKED_ARMS)
    return Grid("r7", f"R5 with {c.about}", base, arms, sizes.scale.seeds)


def pilot_success(specs: dict[str, list[Spec]]) -> dict[str, dict[int, float]]:
    """Uniform's overall success (%) per time sampling and seed, over the pilot's finished runs."""
    from tar_rl.report import load_run, run_percent

    return {
        arm: {s.config["seed"]: run_percent(load_run(s.run_dir))[("success", "overall")] for s in group if s.finished}
        for arm, group in specs.items()
    }


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def write_noise_table(ctx: Context, specs: dict[str, list[Spec]], tree: Path | None) -> Path:
    """The noise analysis of the pilot's runs, every candidate (module docstring), into ``<out>/pilot_noise.csv``
    (and ``.md``): ``python -m benchmarks.analysis noise`` run by this Python from the repository, or with ``tree``
    by that checkout's ``.venv`` in it."""
    from benchmarks.studies.records import REPO

    runs = seed_major(specs)
    folder = runs[0].run_dir.parent
    names = [s.run_dir.name for s in runs]
    path = ctx.out / NOISE_FILE
    data = Path(ctx.planner.data_root).resolve()
    python, where = (sys.executable, REPO) if tree is None else (str(tree / ".venv" / "bin" / "python"), tree)
    command = [python, "-m", "benchmarks.analysis", "noise"]
    command += ["--from", str(folder.resolve()), "--runs", ",".join(names), "--signals", "all"]
    command += ["--data", str(data), "--out", str(path.resolve())]
    print("$ " + " ".join(command), flush=True)
    if subprocess.run(command, cwd=where).returncode != 0:
        raise SystemExit(f"{WHO}: the noise analysis failed in {where} (its output above)")
    return path


def run_select(ctx: Context) -> list[Spec]:
    """``select`` (module docstring): the pilot's noise table if it is not there yet, else the selection."""
    from tar_rl.io import write_json_atomic
    from tar_rl.report import load_run

    dry = ctx.args.dry_run
    started = read_json(ctx.out / STARTED_FILE) or {}
    record_path, table_path = ctx.out / SELECTION_FILE, ctx.out / NOISE_FILE
    if "r7" in started:
        raise SystemExit(
            f"{WHO}: R7's runs started with the selection in {record_path} ({started['r7']} in "
            f"{ctx.out / STARTED_FILE}); the selection may not be written again once they started"
        )
    specs = stage_arms(ctx, STAGES["pilot"])
    missing = [s.run_dir.name for s in seed_major(specs) if not s.finished]
    if missing:
        raise SystemExit(f"{WHO}: the pilot's runs are not all finished ({', '.join(missing)}); run `pilot` first")
    check_pairs([load_run(s.run_dir) for s in seed_major(specs)])  # a seed's two runs: one commit and machine
    if not table_path.is_file():
        if dry:
            print(f"select would write the pilot's noise table {table_path}, then stop")
            return []
        write_noise_table(ctx, specs, ctx.tree)
        print(
            f"\nthe pilot's noise table is in {table_path} (and .md). The plan commits it before the selection: "
            f"commit it, then run `select` again, which applies the rule to it and writes {record_path}"
        )
        return []
    table = pd.read_csv(table_path)
    names = {s.run_dir.name for group in specs.values() for s in group}
    if list(table.columns) != list(NOISE_COLUMNS) or set(table["run"]) != names:
        raise SystemExit(
            f"{WHO}: {table_path} is not the pilot's noise table (runs {sorted(set(table.get('run', [])))}, the "
            f"pilot's {sorted(names)}); remove it and run `select` again to compute it"
        )
    record = selection_record(ctx, specs, table, table_path)
    if not dry:
        write_json_atomic(record, record_path)
    print(selection_text(record))
    return []


def selection_record(ctx: Context, specs: dict[str, list[Spec]], table: pd.DataFrame, table_path: Path) -> dict:
    """The selection by the rule (:func:`select_candidate`) from the pilot's noise table and success, as recorded."""
    sizes = ctx.sizes
    means = candidate_means(table, sizes.pilot_seeds)
    per_seed = pilot_success(specs)
    success = {t: sum(per_seed[t].values()) / len(per_seed[t]) for t in TIMES}
    chosen = select_candidate({k: m["weight_r_tar"] for k, m in means.items()}, success, sizes.margin, sizes.tie)
    c = BY_KEY[chosen["candidate"]]
    return {
        **chosen,
        "signal": c.signal,
        "time_sampling": c.time_sampling,
        "train_r7": c.key != "a",
        "note": "candidate (a) selected: R7 is R5 and no R7 run is trained"
        if c.key == "a"
        else f"R7 trains R5 with it, arms uniform, tar and tar_gentle, seeds {list(sizes.scale.seeds)}",
        "means": means,
        "success": {"mean": success, "per_seed": {t: {str(s): v for s, v in per_seed[t].items()} for t in TIMES}},
        "rule": (
            "the candidate with the highest mean within-segment correlation of TAR's weights at tar-rl's defaults "
            f"between the two draws (weight_r_tar, over seeds {list(sizes.pilot_seeds)}); (d) eligible only if "
            f"uniform's mean overall success with segment times is within {sizes.margin:g} point of (or above) "
            f"uniform's with step times on evaluation seed {sizes.pilot_eval_seed}; a tie within {sizes.tie:g} goes "
            "to the candidate that changes training least, in the order (a), (b), (c), (d)"
        ),
        "table": table_path.name,
        "table_sha256": _sha256(table_path),
        "pilot_runs": [s.run_dir.name for s in seed_major(specs)],
    }


def selection_text(record: dict) -> str:
    """The selection in a few lines (printed by ``select``; the table's section on the pilot)."""
    c = BY_KEY[record["candidate"]]
    success = record["success"]["mean"]
    lines = [
        f"Selected: {c.about}; {record['note']}.",
        "",
        "| candidate | signal r | top step agrees | weight r (tar) | weight r (tar_gentle) | eligible |",
        "|---|---|---|---|---|---|",
    ]
    for cand in CANDIDATES:
        m = record["means"][cand.key]
        cells = " | ".join(fmt_num(m[k], 3) for k in ("signal_r", "top_agree", "weight_r_tar", "weight_r_tar_gentle"))
        lines.append(f"| {cand.about} | {cells} | {'yes' if cand.key in record['eligible'] else 'no'} |")
    lines += [
        "",
        f"Uniform's success on the tuning seed: {fmt_num(success['step'], 2)}% with step times, "
        f"{fmt_num(success['segment'], 2)}% with segment times ((d) "
        + ("eligible" if record["segment_eligible"] else "not eligible")
        + f"); tied within the margin: {', '.join(f'({k})' for k in record['tied'])}. Rule: {record['rule']}.",
    ]
    return "\n".join(lines)


# -- The tables --------------------------------------------------------------------------------------------

COMPARISONS = (
    Comparison("R7 tar - uniform", "r7", "tar", "uniform", True),
    Comparison("R7 tar_gentle - uniform", "r7", "tar_gentle", "uniform", True),
)


def stage_runs(ctx: Context, stage: str, complete: bool) -> tuple[dict[str, dict[int, object]], list[str]]:
    """A stage's finished runs per arm and seed and its planned runs not finished (:func:`finished_runs`).

    Raises:
        SystemExit: the plan changed after its runs started; with ``complete``, a run of the plan is missing, or R7
            has no selection yet.
    """
    specs = stage_arms(ctx, STAGES[stage])
    if specs is None:
        if complete and stage == "r7" and selection(ctx) is None:
            raise SystemExit(f"{WHO}: R7 has no selection yet ({ctx.out / SELECTION_FILE}): run `select` first")
        return {}, []
    return finished_runs(specs, WHO, stage, complete)


def paired_rows(r7: dict[str, dict[int, object]]) -> list[dict]:
    """Each TAR arm minus ``uniform`` per seed, in points of overall success: ``label`` (``R7 flow: <arm>``),
    ``group`` (``R7``), ``seed``, ``delta``; the regime study's paired-difference figure reads them
    (``paired.csv``)."""
    uniform = r7.get("uniform", {})
    return [
        {
            "label": f"R7 flow: {arm}",
            "group": "R7",
            "seed": seed,
            "delta": overall_success(run) - overall_success(uniform[seed]),
        }
        for arm in ("tar", "tar_gentle")
        for seed, run in sorted(r7.get(arm, {}).items())
        if seed in uniform
    ]


#: The regime study's committed runs, R5's among them.
R5_RUNS = RESULTS / "regimes" / "runs"
#: What makes a committed run one of R5's, beside its arm (:func:`.protocol.arm_of`) and seed: R7's uniform at R5's
#: settings agrees with it on each (dotted config keys).
R5_KEYS = ("policy.name", "data.tasks", "data.n_demos", "data.seed", "optim.steps", "eval.seed", "eval.rollouts")
#: The columns two runs' final rollouts must agree on, row by row, to count as the same rollouts.
SAME_ROLLOUTS = ("task", "variation_seed", "variation_index", "success", "steps")


def _dotted(config: dict, key: str):
    for part in key.split("."):
        config = config.get(part) if isinstance(config, dict) else None
    return config


def final_rollouts(run_dir: Path) -> pd.DataFrame:
    """A run's final evaluation: its ``eval_rollouts.csv`` (or ``.csv.gz``) rows at the largest training step."""
    from tar_rl.report.load import run_file

    rows = pd.read_csv(run_file(run_dir, "eval_rollouts.csv"))
    return rows[rows["step"] == rows["step"].max()].reset_index(drop=True)


def same_rollouts(a: pd.DataFrame, b: pd.DataFrame) -> bool:
    """Whether two final evaluations are the same rollouts: as many rows, equal on :data:`SAME_ROLLOUTS`."""
    return len(a) == len(b) and all(a[c].equals(b[c]) for c in SAME_ROLLOUTS)


def r5_runs(ctx: Context, runs_dir: Path) -> dict[str, dict[int, object]]:
    """R5's finished runs in ``runs_dir`` (the regime study's committed runs) per arm and seed: the runs that agree
    with R7's uniform at R5's settings on :data:`R5_KEYS` (R7's ranking signal is not among them)."""
    from benchmarks.studies.protocol import arm_of
    from tar_rl.report import load_run

    wanted = ctx.planner.spec(*ctx.sizes.base, "seed=0", "objective=uniform").config
    found: dict[str, dict[int, object]] = {}
    for path in sorted(p for p in runs_dir.glob("*") if (p / "config.yaml").is_file()) if runs_dir.is_dir() else ():
        config = yaml.safe_load((path / "config.yaml").read_text())
        if all(_dotted(config, k) == _dotted(wanted, k) for k in R5_KEYS):  # only R5's runs are loaded
            run = load_run(path)
            if run.finished:
                found.setdefault(arm_of(run.config), {})[run.seed] = run
    return found


def signal_alone(r7: dict[str, dict[int, object]], r5: dict[str, dict[int, object]]) -> tuple[list[dict], list[int]]:
    """Each R7 TAR arm minus R5's of the same arm and seed (exploratory): the one difference is the signal TAR ranks
    by. R5 trained at another commit, so a seed is paired only where R7's uniform run rolls out exactly as R5's
    (:func:`same_rollouts`). Returns one row per arm with paired seeds (``comparison``, ``pairs``, the arms' mean
    success, ``d_success`` with its 95% CI, ``p``, ``mde``, ``higher``) and the seeds left unpaired because their
    uniform runs differ."""
    from tar_rl.report import min_detectable_effect, paired_t

    common = sorted(set(r7.get("uniform", {})) & set(r5.get("uniform", {})))
    alike = {s: same_rollouts(*(final_rollouts(runs["uniform"][s].path) for runs in (r7, r5))) for s in common}
    rows = []
    for arm in ("tar", "tar_gentle"):
        seeds = [s for s in sorted(set(r7.get(arm, {})) & set(r5.get(arm, {}))) if alike.get(s)]
        if not seeds:
            continue
        new, old = [overall_success(r7[arm][s]) for s in seeds], [overall_success(r5[arm][s]) for s in seeds]
        stats = paired_t([a - b for a, b in zip(new, old, strict=True)])
        rows.append(
            {
                "comparison": f"R7 {arm} - R5 {arm}",
                "pairs": len(seeds),
                "success_r7": sum(new) / len(new),
                "success_r5": sum(old) / len(old),
                "d_success": stats["mean"],
                "d_success_ci_low": stats["ci_low"],
                "d_success_ci_high": stats["ci_high"],
                "p_success": stats["p_value"],
                "mde_success": min_detectable_effect(stats["std"], len(seeds)),
                "higher": sum(a > b for a, b in zip(new, old, strict=True)),
            }
        )
    return rows, [s for s in common if not alike[s]]


def signal_alone_lines(rows: Sequence[dict], unpaired: Sequence[int]) -> list[str]:
    """The exploratory section of ``decision.md`` (:func:`signal_alone`)."""
    out = [
        "## The signal alone (exploratory, not pre-registered)",
        "",
        "| comparison | pairs | success % R7 / R5 | Δ success [95% CI] | p | MDE (80%) | R7 higher |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        ci = f"[{fmt_num(r['d_success_ci_low'], 2, True)}, {fmt_num(r['d_success_ci_high'], 2, True)}]"
        out.append(
            f"| {r['comparison']} | {r['pairs']} | {fmt_num(r['success_r7'])} / {fmt_num(r['success_r5'])} "
            f"| {fmt_num(r['d_success'], 2, True)} {ci} | {fmt_p(r['p_success'])} | {fmt_num(r['mde_success'], 2)} "
            f"| {r['higher']} of {r['pairs']} |"
        )
    out += [
        "",
        "Each R7 TAR arm minus R5's of the same arm and seed: the same training but for the signal TAR ranks the steps "
        "by (R7's against the loss). R5 trained at another commit, so a seed is paired only where R7's uniform run "
        "rolls out exactly as R5's (every final rollout's task, variation, success and steps). Not one of R7's "
        "pre-registered comparisons: no Holm.",
    ]
    if unpaired:
        out += ["", f"Seeds left unpaired (their uniform runs roll out differently): {', '.join(map(str, unpaired))}."]
    return out


def pilot_rows(ctx: Context) -> list[dict]:
    """The pilot's finished runs: uniform's overall success per time sampling and seed on the tuning seed."""
    return [
        {"time_sampling": t, "seed": seed, "success": v}
        for t, by_seed in pilot_success(pilot_grid(ctx.sizes).specs(ctx.planner)).items()
        for seed, v in sorted(by_seed.items())
    ]


def decision_markdown(rows, groups: pd.DataFrame, fits, pilot: Sequence[dict], record, missing, alone=((), ())) -> str:
    """R7's comparisons, per-group rows, fit and weights, the pilot and the selection, the signal alone
    (``alone``: :func:`signal_alone`'s rows and unpaired seeds) and the missing runs."""
    out = ["# TAR for a sampled loss: R7's comparisons", ""]
    if record is not None and not record["train_r7"]:
        out += [f"{record['note']} (R5's rows of the regime study's decision table are R7's).", ""]
    out += [*comparison_lines(rows), ""]
    chosen = BY_KEY[record["candidate"]].about if record else "not selected yet"
    out += [
        f"R7 = R5 (the flow head) with the selected candidate, {chosen}. Success, Fast20 and NEPS in 100 x units; "
        "Δ = T - B over the seeds both arms have (lower Fast20/NEPS is better). Holm over R7's two comparisons. "
        "MDE: the smallest true Δ success a paired t-test detects with 80% power at the observed spread. T higher: "
        "pairs where T's success is higher.",
        "",
        *groups_and_fit_lines(groups, fits, FINAL_SHARE),
    ]
    if pilot:
        out += ["", "## The pilot: uniform per time sampling (tuning evaluation seed)", ""]
        out += ["| times | seeds | success % per seed | mean |", "|---|---|---|---|"]
        frame = pd.DataFrame(pilot)
        for t in TIMES:
            g = frame[frame["time_sampling"] == t]
            if len(g):
                per_seed = ", ".join(f"{s}: {fmt_num(v)}" for s, v in zip(g["seed"], g["success"], strict=True))
                out.append(f"| {t} | {len(g)} | {per_seed} | {fmt_num(g['success'].mean(), 2)} |")
    if record is not None:
        out += ["", "## The selection", "", selection_text(record)]
    if alone[0]:
        out += ["", *signal_alone_lines(*alone)]
    out += pending_lines(missing)
    return "\n".join(out) + "\n"


def write_tables(ctx: Context, prov: dict, dest: Path, complete: bool = False) -> str:
    """R7's tables (markdown + CSV) from the finished runs of ``ctx.out``, written into ``dest``; returns the
    markdown. ``complete``: refuse a planned stage with a run missing (the final table)."""
    loaded, missing = {}, {}
    for stage in ("pilot", "r7"):
        loaded[stage], missing[stage] = stage_runs(ctx, stage, complete)
    rows, groups = contrasts(COMPARISONS, loaded)
    fits = stage_fits({"r7": loaded["r7"]})
    pilot = pilot_rows(ctx)
    group_df = pd.concat(groups, ignore_index=True) if groups else pd.DataFrame()
    alone = signal_alone(loaded["r7"], r5_runs(ctx, R5_RUNS))
    md = decision_markdown(rows, group_df, fits, pilot, selection(ctx), missing, alone)
    tables = {"decision.csv": pd.DataFrame(rows)}
    if alone[0]:
        tables["signal_alone.csv"] = pd.DataFrame(alone[0])
    if len(group_df):
        tables["groups.csv"] = group_df
    if pilot:
        tables["pilot.csv"] = pd.DataFrame(pilot)
    paired = paired_rows(loaded["r7"])
    if paired:
        tables["paired.csv"] = pd.DataFrame(paired)
    write_outputs(dest, {"decision.md": md}, tables, prov)
    return md


# -- The study -------------------------------------------------------------------------------------------


def _trains_r7(ctx: Context) -> dict | None:
    record = selection(ctx)
    return record if record is not None and record["train_r7"] else None


SELECTED = Gate(
    "the selection record",
    read=selection,
    missing=lambda ctx: (
        f"{WHO}: R7's runs are planned once the selection is recorded ({ctx.out / SELECTION_FILE}); run `select` first"
    ),
)
TRAINS_R7 = Gate(
    "a selection other than (a) (with (a), R7 is R5)",
    read=_trains_r7,
    missing=lambda ctx: f"{selection(ctx)['note']} ({ctx.out / SELECTION_FILE}): nothing to run",
    stop=True,
)
STAGES = named(
    Stage(
        "pilot",
        "uniform flow at R5's settings per time sampling, on the tuning evaluation seed",
        grids=lambda ctx: [pilot_grid(ctx.sizes)],
        records=Digest(STARTED_FILE),
    ),
    Stage("select", "the pilot's noise table, then the selection by the rule", action=run_select),
    Stage(
        "r7",
        "R5 with the selected candidate: uniform, tar, tar_gentle",
        grids=lambda ctx, _, record: [r7_grid(ctx.sizes, record["candidate"])],
        gates=(SELECTED, TRAINS_R7),
        records=Digest(STARTED_FILE),
    ),
)


def table(ctx: Context) -> None:
    """R7's comparisons (:func:`write_tables`)."""
    prov = provenance(ctx.scale, ctx.study.name, ctx.argv[1:])
    print(write_tables(ctx, prov, ctx.tables, complete=ctx.args.complete))


def _options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--complete", action="store_true", help="table: refuse a stage with a run of its plan missing")
    sweep.add_tree_option(
        p,
        "run: train (and select: analyse) with this checkout's code (a git worktree at R7's commit, with its "
        "own .venv)",
    )


def keep_weights(ctx: Context) -> list[str]:
    """Seed 0's runs of every R7 arm (the weights of each arm on one seed)."""
    specs = stage_arms(ctx, STAGES["r7"], check=False) or {}
    return [group[0].run_dir.name for group in specs.values() if group]


STUDY = Study(
    name=WHO,
    about="TAR for a sampled loss: R7, a ranking signal for the flow head chosen on a pilot, against uniform.",
    scales=SIZES,
    stages=STAGES,
    table=table,
    results=lambda scale: "regimes/r7" if scale == "cpu" else None,
    options=_options,
    with_options=with_seeds,
    keep_weights=keep_weights,
)
