"""Where does TAR help? The pre-registered regime study (``results/regimes/PLAN.md``) as commands.

Usage::

    python benchmarks/regimes.py COMMAND [--scale cpu|ci] [--out DIR] [--jobs N] [--seeds 0,1,..]
                                         [--data-root DIR] [--dry-run]

Commands (every run lands in ``<out>/runs/``, named by its settings: running a command again skips
finished runs and resumes interrupted ones):

* ``r1``: post-training from a pretrained policy. Trains the source (uniform, the 42 MT50 tasks
  outside the default eight, 25 demonstrations each) if it is not there, then the pairs (uniform,
  tar) on the default eight tasks from it, for each demonstration budget (3: primary; 10: secondary).
* ``r2-screen``: the screening run (uniform, MT50, evaluated on the tuning seed) and the list of the
  ten tasks with the lowest success (``<out>/screening.json``), refused once comparison runs started.
* ``r2``: the pairs on the screened tasks (``<out>/r2_started.json`` records the list they use).
* ``r3``: the pairs on MT50 with 50 demonstrations per task, about 20 passes over the data.
* ``r4``, ``r5``: the chunked-heads regimes, R3's data, schedule and evaluation with the ``act`` (R4) and
  ``flow`` (R5) heads, three arms per seed (:data:`ARMS`: ``uniform``, ``tar``, ``tar_gentle``), seed by seed.
  The plan's digest is recorded when its first run starts (``<out>/chunked_started.json``); a changed plan is
  refused by these commands and by ``table``.
* ``table``: the decision table, the per-group rows and Fig. 3 per regime from the finished runs
  (``decision.md``, ``decision.csv``, ``groups.csv``, ``fig3_regimes.png``, ``fig3_chunked.png``; provenance in
  ``provenance.json``). Pairs (a chunked-heads seed's three runs) trained at different commits or on different
  machines are refused; a chunked-heads regime is tabled over the seeds every arm has finished, and with
  ``--complete`` a missing run of its plan is refused, named.
* ``collect --from DIR``: copy the finished runs of a runs folder (e.g. a sweep trained in a separate
  worktree) into ``<out>/runs``: config, summary and the logs (compressed), ``weights.csv`` only for the runs
  an analysis reads (R3's, and seed 0 of each arm of R4 and R5), never checkpoints except the pretrained
  source's, which the R1 runs start from.

The ``ci`` scale runs the same commands on two or three tasks for a few steps (what the tests run).
"""

from __future__ import annotations

import argparse
import gzip
import hashlib
import io
import json
import math
import shutil
import sys
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import pandas as pd

from tar_rl import runs
from tar_rl.report import run_file

sys.path.insert(0, str(Path(__file__).resolve().parent))  # paper_experiments.py beside this script
from paper_analysis import fmt_p as _fmt_p
from paper_experiments import EIGHT_TASKS, Planner, Scale, Spec, execute, provenance

#: The repository's root: what the tracked copy of a run's config names its folders relative to.
REPO = Path(__file__).resolve().parent.parent
COMMANDS = ("r1", "r2-screen", "r2", "r3", "r4", "r5", "table", "collect")
BASELINE, TREATMENT = "uniform", "tar"
REGIMES = ("R1", "R1-10", "R2", "R3")
PRIMARY = ("R1", "R2", "R3")  # the comparisons the Holm correction runs over (R1: 3 demonstrations)
# The chunked-heads regimes' arms (objective options): uniform, TAR at tar-rl's defaults, the gentle preset. Their
# four TAR-vs-uniform comparisons (R4, R5 x tar, tar_gentle) are a second Holm family.
ARMS = ("uniform", "tar", "tar_gentle")
CHUNKED_STARTED_FILE = "chunked_started.json"
# MT50 without the default eight tasks, in MetaWorld's alphabetical order: R1's pretraining tasks.
SOURCE_TASKS = (
    "bin-picking,box-close,button-press-topdown-wall,button-press,button-press-wall,coffee-button,coffee-pull,"
    "coffee-push,dial-turn,disassemble,door-close,door-lock,door-open,door-unlock,drawer-close,drawer-open,"
    "faucet-close,faucet-open,hammer,hand-insert,handle-press-side,handle-press,handle-pull-side,handle-pull,"
    "lever-pull,peg-unplug-side,pick-place,plate-slide-back-side,plate-slide-back,plate-slide-side,plate-slide,"
    "push-back,push,push-wall,reach-wall,shelf-place,soccer,stick-push,sweep-into,sweep,window-close,window-open"
)
SCREENING_FILE, STARTED_FILE = "screening.json", "r2_started.json"
# Files of a run kept in the repository beside its config and summary, gzip-compressed.
PACKED = (runs.ROLLOUTS_FILE, runs.METRICS_FILE, runs.WEIGHTS_FILE)
# The rollout columns that must agree for a run trained again to stand in for a committed one.
REPRODUCED_COLUMNS = ("task", "variation_seed", "variation_index", "success", "steps")


@dataclass(frozen=True)
class Study:
    """The sizes of the study's runs at one scale (overrides are Hydra's ``key=value``).

    Attributes:
        scale: the shared overrides, seeds and time model (``paper_experiments.Scale``).
        source: R1's pretraining run.
        r1: R1's post-training runs (without the budget, seed and objective).
        r1_budgets: demonstrations per task of R1 (the first is the primary budget).
        screen: R2's screening run.
        screen_keep: tasks R2 keeps.
        r2: R2's runs (without the tasks, seed and objective).
        r3: R3's runs (without seed and objective).
        chunked: the chunked-heads regimes' runs (R3's data, schedule and evaluation; without the head, seed and
            objective).
        chunked_heads: ``(regime, head, overrides of the head)`` for each chunked-heads regime (R4, R5).
    """

    scale: Scale
    source: tuple[str, ...]
    r1: tuple[str, ...]
    r1_budgets: tuple[int, ...]
    screen: tuple[str, ...]
    screen_keep: int
    r2: tuple[str, ...]
    r3: tuple[str, ...]
    chunked: tuple[str, ...] = ()
    chunked_heads: tuple[tuple[str, str, tuple[str, ...]], ...] = ()


_COMMON = ("logging=quiet", "logging.record_episodes=3", "threads=1")
_CPU = Study(
    scale=Scale(
        name="cpu",
        about="the pre-registered regime study (results/regimes/PLAN.md) on 2 CPU cores",
        common=_COMMON,
        families=("mlp",),
        seeds=(0, 1, 2, 3, 4, 5, 6, 7),
        jobs=2,
    ),
    source=(
        "policy=mlp",
        "policy.task_conditioning=instruction",
        "objective=uniform",
        "seed=0",
        f"data.tasks=[{SOURCE_TASKS}]",
        "data.n_demos=25",
        "data.seed=3000",
        "optim.steps=40000",
        "eval.rollouts=10",
        "eval.seed=2000",
        "logging.record_episodes=1",
    ),
    r1=(
        "policy=mlp",
        "policy.task_conditioning=instruction",
        f"data.tasks={EIGHT_TASKS}",
        "data.seed=0",
        "optim.steps=8000",
        "eval.rollouts=50",
        "eval.seed=1000",
        "logging.record_weights_at=[4000,-1]",
    ),
    r1_budgets=(3, 10),
    screen=(
        "policy=mlp",
        "objective=uniform",
        "seed=0",
        "data.tasks=[mt50]",
        "data.n_demos=10",
        "data.seed=0",
        "optim.steps=8000",
        "eval.rollouts=20",
        "eval.seed=2000",
    ),
    screen_keep=10,
    r2=(
        "policy=mlp",
        "data.n_demos=10",
        "data.seed=0",
        "optim.steps=20000",
        "eval.rollouts=50",
        "eval.seed=1000",
        "logging.record_weights_at=[10000,-1]",
    ),
    r3=(
        "policy=mlp",
        "data.tasks=[mt50]",
        "data.n_demos=50",
        "data.seed=0",
        "optim.steps=3743",  # 20 x 191,624 demonstration steps / (64 x 16) (results/regimes/PLAN.md)
        "eval.rollouts=20",
        "eval.seed=1000",
        "logging.record_weights_at=[1872,-1]",
    ),
    chunked=(
        "data.tasks=[mt50]",
        "data.n_demos=50",
        "data.seed=0",
        "optim.steps=3743",  # R3's schedule
        "eval.rollouts=20",
        "eval.seed=1000",
        "logging.record_weights_at=[1872,-1]",
        "policy.compile=true",  # the compiled attention: the same model, faster steps (tar_rl.policies.attention)
    ),
    chunked_heads=(("R4", "act", ()), ("R5", "flow", ())),  # each head at its defaults
)
_TINY = (
    "data.n_demos=2",
    "data.batch_segments=4",
    "data.slice_len=8",
    "data.workers=1",
    "optim.steps=4",
    "optim.warmup=1",
    "eval.rollouts=1",
    "eval.horizon=20",
    "eval.workers=1",
    "logging.every=1",
    "logging.checkpoint_every=2",
    "logging.record_weights_at=[-1]",
    "diagnostics.heldout_demos=1",
    "diagnostics.train_episodes=1",
)
_CI = Study(
    scale=Scale(
        name="ci",
        about="the regime study's commands on two or three tasks, a few steps (the tests' size; no meaningful numbers)",
        common=(*_COMMON, *_TINY),
        families=("mlp",),
        seeds=(0, 1),
        jobs=1,
    ),
    source=(
        "policy=mlp",
        "policy.hidden=[16,16]",
        "policy.task_conditioning=instruction",
        "objective=uniform",
        "seed=0",
        "data.tasks=[push,drawer-open]",
        "data.seed=3000",
        "eval.seed=2000",
    ),
    r1=(
        "policy=mlp",
        "policy.hidden=[16,16]",
        "policy.task_conditioning=instruction",
        "data.tasks=[reach,basketball]",
        "eval.seed=1000",
    ),
    r1_budgets=(1, 2),
    screen=(
        "policy=mlp",
        "policy.hidden=[16,16]",
        "objective=uniform",
        "seed=0",
        "data.tasks=[reach,basketball,push]",
        "eval.seed=2000",
        "eval.rollouts=2",
    ),
    screen_keep=2,
    r2=("policy=mlp", "policy.hidden=[16,16]", "eval.seed=1000"),
    r3=("policy=mlp", "policy.hidden=[16,16]", "data.tasks=[reach,push]", "eval.seed=1000"),
    chunked=("data.tasks=[reach,push]", "eval.seed=1000"),
    chunked_heads=(
        ("R4", "act", ("policy.dim=16", "policy.heads=2", "policy.ffn_dim=16", "policy.latent_dim=4")),
        ("R5", "flow", ("policy.dim=16", "policy.heads=2", "policy.layers=1", "policy.expert_dim=8")),
    ),
)
STUDIES = {"cpu": _CPU, "ci": _CI}


# -- Plans ---------------------------------------------------------------------------------------


def _pairs(planner: Planner, seeds: Sequence[int], *overrides: str) -> list[Spec]:
    return [planner.spec(*overrides, f"seed={s}", f"objective={o}") for s in seeds for o in (BASELINE, TREATMENT)]


def source_spec(study: Study, planner: Planner) -> Spec:
    """R1's pretraining run."""
    return planner.spec(*study.source)


def r1_specs(study: Study, planner: Planner, source: Spec, budgets: Sequence[int] | None = None) -> list[Spec]:
    """R1's pairs from ``source`` (which must have finished: its checkpoint is read)."""
    out = []
    for n in study.r1_budgets if budgets is None else budgets:
        out += _pairs(planner, planner.scale.seeds, *study.r1, f"data.n_demos={n}", f"init.from={source.run_dir}")
    return out


def screening(out: Path) -> list[str] | None:
    """The committed R2 task list, or None before screening."""
    path = out / SCREENING_FILE
    return json.loads(path.read_text())["tasks"] if path.is_file() else None


def r2_specs(study: Study, planner: Planner, tasks: Sequence[str]) -> list[Spec]:
    return _pairs(planner, planner.scale.seeds, *study.r2, f"data.tasks=[{','.join(tasks)}]")


def r3_specs(study: Study, planner: Planner) -> list[Spec]:
    return _pairs(planner, planner.scale.seeds, *study.r3)


def chunked_head(study: Study, label: str) -> tuple[str, tuple[str, ...]]:
    """The head and its overrides of the chunked-heads regime ``label`` (``R4``, ``R5``)."""
    for regime, head, extra in study.chunked_heads:
        if regime == label:
            return head, extra
    raise SystemExit(f"regimes: no chunked-heads regime {label!r} at this scale")


def chunked_specs(study: Study, planner: Planner, label: str) -> dict[str, list[Spec]]:
    """The runs of a chunked-heads regime per arm (:data:`ARMS`), seeds in order."""
    head, extra = chunked_head(study, label)
    seeds = planner.scale.seeds
    return {
        arm: [planner.spec(f"policy={head}", *extra, *study.chunked, f"seed={s}", f"objective={arm}") for s in seeds]
        for arm in ARMS
    }


def seed_major(specs: dict[str, list[Spec]]) -> list[Spec]:
    """Seed by seed (every setting of the first seed, then the next), so a sweep cut short leaves whole seeds."""
    groups = list(specs.values())
    return [group[i] for i in range(max(map(len, groups), default=0)) for group in groups if i < len(group)]


def plan_digest(specs: dict[str, list[Spec]]) -> str:
    """A digest of what the runs of a plan train (their overrides, without the machine's folders)."""
    local = ("runs_root=", "data.root=")
    plan = {arm: [[o for o in s.overrides if not o.startswith(local)] for s in group] for arm, group in specs.items()}
    return hashlib.sha256(json.dumps(plan, sort_keys=True).encode()).hexdigest()[:16]


def check_plan_started(out: Path, label: str, specs: dict[str, list[Spec]], record: bool) -> None:
    """Refuse a chunked-heads plan that differs from the one its runs started with (``chunked_started.json``);
    with ``record``, record the plan when it is the regime's first."""
    from tar_rl.io import write_json_atomic

    path = out / CHUNKED_STARTED_FILE
    started = json.loads(path.read_text()) if path.is_file() else {}
    digest = plan_digest(specs)
    if label in started and started[label] != digest:
        raise SystemExit(
            f"regimes: {label}'s plan changed after its runs started (recorded {started[label]} in {path}, now "
            f"{digest}); a plan may not change once its runs started: restore it, or remove {label}'s runs and its "
            "entry there"
        )
    if record and label not in started:
        write_json_atomic({**started, label: digest}, path)


def _digest(tasks: Sequence[str]) -> str:
    return hashlib.sha256(json.dumps(list(tasks)).encode()).hexdigest()[:16]


def pick_hardest(rollouts: pd.DataFrame, keep: int) -> list[str]:
    """The ``keep`` tasks with the lowest success rate; ties broken by task name (pre-registered)."""
    rates = rollouts.groupby("task")["success"].mean()
    order = sorted(rates.index, key=lambda t: (float(rates[t]), str(t)))
    return order[:keep]


def write_screening(study: Study, spec: Spec, out: Path) -> list[str]:
    """Pick R2's tasks from the finished screening run and write ``screening.json``.

    Raises:
        SystemExit: comparison runs started with another list (``r2_started.json``).
    """
    from tar_rl.io import write_json_atomic
    from tar_rl.report import load_run

    run = load_run(spec.run_dir)
    rollouts = pd.read_csv(run_file(spec.run_dir, runs.ROLLOUTS_FILE))
    tasks = pick_hardest(rollouts[rollouts["step"] == rollouts["step"].max()], study.screen_keep)
    started = out / STARTED_FILE
    if started.is_file() and json.loads(started.read_text())["tasks"] != tasks:
        raise SystemExit(
            f"regimes: R2's comparison runs started with the tasks in {started}; the screening now gives {tasks}. "
            "The list is fixed once comparison runs start: remove the R2 runs and that file to screen again."
        )
    rates = rollouts.groupby("task")["success"].mean()
    write_json_atomic(
        {
            "tasks": tasks,
            "digest": _digest(tasks),
            "rule": f"the {study.screen_keep} tasks with the lowest success of the screening run; ties by name",
            "screening_run": run.name,
            "success": {t: float(rates[t]) for t in sorted(rates.index)},
        },
        out / SCREENING_FILE,
    )
    return tasks


def check_started(out: Path, tasks: Sequence[str]) -> None:
    """Record R2's task list when its comparison runs start; refuse a list that differs from the recorded one."""
    from tar_rl.io import write_json_atomic

    started = out / STARTED_FILE
    if started.is_file():
        recorded = json.loads(started.read_text())["tasks"]
        if list(recorded) != list(tasks):
            raise SystemExit(
                f"regimes: {out / SCREENING_FILE} lists {list(tasks)} but R2's comparison runs started with "
                f"{recorded} ({started}): a screening list may not change after comparison runs started"
            )
        return
    write_json_atomic({"tasks": list(tasks), "digest": _digest(tasks)}, started)


# -- Collecting raw results --------------------------------------------------------------------------


def weights_read(study: Study, planner: Planner) -> list[str]:
    """The runs of the study whose ``weights.csv`` an analysis reads: R3's, every seed (``r3_diagnosis.py``), and
    seed 0 of each arm of the chunked-heads regimes (R4, R5: the weights of each arm on one seed)."""
    names = [spec.run_dir.name for spec in r3_specs(study, planner)]
    for label, _, _ in study.chunked_heads:
        names += [group[0].run_dir.name for group in chunked_specs(study, planner, label).values() if group]
    return names


def collect(src: Path, out: Path, keep_checkpoint: Sequence[str] = (), keep_weights: Sequence[str] = ()) -> list[str]:
    """Copy the finished runs of ``src`` into ``out/runs`` (logs gzip-compressed; checkpoints only for
    the run names in ``keep_checkpoint``); returns the names copied. Runs already there are skipped.

    ``weights.csv`` (TAR's weights along training demonstrations, the largest file of a run) is kept only for
    the run names in ``keep_weights``, the runs an analysis reads (:func:`weights_read`); every run's summary
    (weight per episode-time bin) and ``metrics.csv`` (largest weight, ESS) keep its weight statistics. The
    machine's folders in the config (``data.root``, ``runs_root``, ``init.from``) and summary are written relative
    to the repository (:func:`tar_rl.runs.portable_summary`).

    Each copy is named by its identity as this code computes it from the run's config (a run trained
    by code that named runs otherwise gets its current name; its summary's ``run_name`` follows)."""
    import yaml

    from tar_rl.io import write_json_atomic
    from tar_rl.recipes import run_name

    copied = []
    for run in sorted(p for p in src.iterdir() if (p / "summary.json").is_file()):
        summary = json.loads((run / "summary.json").read_text())
        if not summary.get("finished"):
            continue
        name = run_name(yaml.safe_load((run / runs.CONFIG_FILE).read_text()))
        target = out / "runs" / name
        if (target / "summary.json").is_file():
            continue
        try:
            config = runs.portable_config(yaml.safe_load((run / runs.CONFIG_FILE).read_text()), REPO)
            summary = runs.portable_summary(summary, REPO)
        except ValueError as err:
            raise SystemExit(f"collect: {run.name}: {err}") from None
        tmp = target.with_name(f".{name}.tmp")
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
        (tmp / runs.CONFIG_FILE).write_text(yaml.safe_dump(config, sort_keys=False))
        write_json_atomic({**summary, "run_name": name}, tmp / runs.SUMMARY_FILE)
        for log in PACKED:
            if log == runs.WEIGHTS_FILE and name not in keep_weights:
                continue
            if (run / log).is_file():
                with open(run / log, "rb") as f_in, gzip.GzipFile(tmp / f"{log}.gz", "wb", mtime=0) as f_out:
                    shutil.copyfileobj(f_in, f_out)
        if name in keep_checkpoint:
            shutil.copy2(run / runs.CHECKPOINT, tmp / runs.CHECKPOINT)
        tmp.rename(target)
        copied.append(name)
    return copied


# -- The table -------------------------------------------------------------------------------------


def _fit(run) -> dict:
    return run.summary.get("fit") or {}


def check_pairs(runs: Sequence) -> None:
    """Refuse a pair (same regime setting and seed) whose two runs were trained at different commits or machines."""
    by_seed: dict[int, list] = {}
    for run in runs:
        by_seed.setdefault(run.seed, []).append(run)
    for seed, pair in sorted(by_seed.items()):
        commits = {r.summary.get("git_commit") for r in pair}
        hosts = {(r.summary.get("machine") or {}).get("hostname") for r in pair}
        if len(commits) > 1 or len(hosts) > 1:
            names = ", ".join(r.name for r in pair)
            what = "commits" if len(commits) > 1 else "machines"
            raise SystemExit(f"regimes: the pair of seed {seed} ({names}) was trained at different {what}; re-run one")


# The share of the last training steps over which a run's weight statistics are averaged (as the final train loss).
FINAL_SHARE = 0.05


def final_train_mean(run, name: str) -> float | None:
    """The mean of a run's logged training metric ``name`` over its last :data:`FINAL_SHARE` of steps (``None``
    when it logged none there)."""
    m = run.metrics
    if m.empty or run.steps is None:
        return None
    rows = m[(m["phase"] == "train") & (m["name"] == name) & (m["step"] > (1 - FINAL_SHARE) * run.steps)]
    return float(rows["value"].mean()) if len(rows) else None


def fit_summary(runs: Sequence) -> dict[str, float]:
    """Means over ``runs``: the fit diagnostics of each run's summary (the final uniform training loss
    ``train_loss``, the held-out per-step loss ``heldout_loss``, the ``alignment``) and, over the last
    :data:`FINAL_SHARE` of training steps, the largest weight in a segment ``weight_max`` and the weights'
    effective-sample-size fraction ``weight_ess`` (from ``metrics.csv``); ``nan`` where none has it."""
    fit = fit_means(runs)
    out = {name: fit[name] for name in ("train_loss", "heldout_loss", "alignment")}
    for name in ("weight_max", "weight_ess"):
        out[name] = finite_mean(final_train_mean(r, name) for r in runs)
    return out


def fit_markdown(fit: pd.DataFrame, keys: Sequence[str]) -> list[str]:
    """A markdown table of :func:`fit_summary` rows: the columns ``keys`` as they are, then the five statistics."""
    head = [*keys, "final train loss", "held-out loss", "alignment", "largest weight", "ESS"]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for r in fit.to_dict("records"):
        cells = [str(r[k]) for k in keys]
        cells += [fmt_num(r["train_loss"], 4), fmt_num(r["heldout_loss"], 4), fmt_num(r["alignment"], 2, True)]
        cells += [fmt_num(r["weight_max"], 2), fmt_num(r["weight_ess"], 2)]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def final_rollouts(run_dir: Path) -> pd.DataFrame:
    """The final evaluation's rollouts of a run (:data:`REPRODUCED_COLUMNS`), in a fixed order."""
    path = run_file(run_dir, runs.ROLLOUTS_FILE)
    if not path.is_file():
        return pd.DataFrame(columns=list(REPRODUCED_COLUMNS))
    df = pd.read_csv(path)
    cols = list(REPRODUCED_COLUMNS)
    return df[df["step"] == df["step"].max()][cols].sort_values(cols[:3]).reset_index(drop=True)


def reproduces(run_dir: Path, committed_dir: Path) -> tuple[bool, str]:
    """Whether a reproduced run's final per-rollout results equal the committed run's, and how many differ."""
    mine, theirs = final_rollouts(run_dir), final_rollouts(committed_dir)
    if mine.empty or theirs.empty:
        return False, "one of the two runs has no evaluation"
    if mine.shape != theirs.shape:
        return False, f"{len(mine)} rollouts against {len(theirs)}"
    differ = int((mine != theirs).any(axis=1).sum())
    return differ == 0, f"{differ} of {len(theirs)} rollouts differ"


def finite_mean(values) -> float:
    """The mean of the finite values among ``values`` (``None`` left out); ``nan`` when there is none."""
    values = [float(v) for v in values if v is not None and math.isfinite(float(v))]
    return sum(values) / len(values) if values else math.nan


def fit_means(runs: Sequence) -> dict[str, float]:
    """Means over ``runs`` of their summaries' fit diagnostics: ``passes``, ``train_loss`` (the final uniform
    training loss), ``heldout_loss`` and ``alignment`` (its Spearman correlation); ``nan`` where none has it."""
    fits = [_fit(r) for r in runs]
    return {
        "passes": finite_mean(f.get("passes") for f in fits),
        "train_loss": finite_mean(f.get("final_uniform_loss") for f in fits),
        "heldout_loss": finite_mean((f.get("heldout") or {}).get("loss") for f in fits),
        "alignment": finite_mean((f.get("alignment") or {}).get("spearman") for f in fits),
    }


def tables_dir(args: argparse.Namespace, out: Path) -> Path:
    """Where ``table`` writes: ``--tables`` when given, else the results folder (created)."""
    dest = Path(args.tables) if args.tables else out
    dest.mkdir(parents=True, exist_ok=True)
    return dest


def regime_rows(label: str, runs: Sequence) -> tuple[dict, pd.DataFrame]:
    """One decision-table row (success, Fast20, NEPS statistics and fit diagnostics) and the per-group rows."""
    from tar_rl.report import min_detectable_effect, paired_table

    paired = paired_table(runs, objectives=[TREATMENT], file=io.StringIO())
    row: dict = {"regime": label}
    for metric in ("success", "fast20", "neps"):
        rec = paired[(paired["metric"] == metric) & (paired["level"] == "overall")].iloc[0]
        row[f"{metric}_uniform"] = rec["baseline_mean"]
        row[f"{metric}_tar"] = rec["objective_mean"]
        row[f"d_{metric}"] = rec["delta_mean"]
        row[f"d_{metric}_ci_low"], row[f"d_{metric}_ci_high"] = rec["ci_low"], rec["ci_high"]
        row[f"p_{metric}"] = rec["p_value"]
        if metric == "success":
            row["pairs"] = int(rec["n_pairs"])
            row["mde_success"] = min_detectable_effect(rec["delta_std"], int(rec["n_pairs"]))
    for obj in (BASELINE, TREATMENT):
        mine = [r for r in runs if r.objective == obj and r.finished]
        row.update({f"{name}_{obj}": value for name, value in fit_means(mine).items()})
    groups = paired[(paired["metric"] == "success") & (paired["level"] != "overall")].assign(regime=label)
    return row, groups


def fmt_num(v: float, digits: int = 1, signed: bool = False) -> str:
    """``v`` with ``digits`` decimals (and its sign with ``signed``) for a markdown table; ``-`` when not finite."""
    if v is None or not math.isfinite(v):
        return "-"
    return f"{v:+.{digits}f}" if signed else f"{v:.{digits}f}"


def decision_markdown(rows: Sequence[dict], groups: pd.DataFrame, missing: dict[str, list[str]]) -> str:
    """The decision table, per-group rows and notes on missing runs, as markdown (no provenance: it is recomputed
    exactly from the committed runs)."""
    lines = [
        "| regime | pairs | success % U / T | Δ success [95% CI] | p | Holm p | MDE (80%) | Δ Fast20 | Δ NEPS "
        "| passes | final train loss U / T | held-out loss U / T | alignment U / T |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        ci = f"[{fmt_num(r['d_success_ci_low'], 2, True)}, {fmt_num(r['d_success_ci_high'], 2, True)}]"
        lines.append(
            f"| {r['regime']} | {r['pairs']} | {fmt_num(r['success_uniform'])} / {fmt_num(r['success_tar'])} "
            f"| {fmt_num(r['d_success'], 2, True)} {ci} | {_fmt_p(r['p_success'])} | {_fmt_p(r['holm_p'])} "
            f"| {fmt_num(r['mde_success'], 2)} | {fmt_num(r['d_fast20'], 2, True)} | {fmt_num(r['d_neps'], 2, True)} "
            f"| {fmt_num(r['passes_uniform'], 0)} "
            f"| {fmt_num(r['train_loss_uniform'], 4)} / {fmt_num(r['train_loss_tar'], 4)} "
            f"| {fmt_num(r['heldout_loss_uniform'], 4)} / {fmt_num(r['heldout_loss_tar'], 4)} "
            f"| {fmt_num(r['alignment_uniform'], 2, True)} / {fmt_num(r['alignment_tar'], 2, True)} |"
        )
    out = ["# Where does TAR help? Decision table", "", *lines, ""]
    out += [
        "Success, Fast20 and NEPS in 100 x units; Δ = TAR - uniform over paired seeds (lower Fast20/NEPS is better). "
        "Holm: over the primary comparisons (" + ", ".join(PRIMARY) + "), and separately over the chunked heads' "
        "four (R4 and R5, each arm against uniform; the row names the arm: `tar` at tar-rl's defaults, "
        "`tar_gentle` the gentle preset). MDE: the smallest true Δ success a paired "
        "t-test detects with 80% power at the observed spread. Alignment: Spearman correlation over ten bins of "
        "episode time between TAR's weight on training demonstrations and the held-out per-step loss.",
        "",
        "## Success per difficulty group",
        "",
        "| regime | group | pairs | uniform % | TAR % | Δ [95% CI] | p |",
        "|---|---|---|---|---|---|---|",
    ]
    for g in groups.to_dict("records"):
        ci = f"[{fmt_num(g['ci_low'], 2, True)}, {fmt_num(g['ci_high'], 2, True)}]"
        out.append(
            f"| {g['regime']} | {g['level']} | {g['n_pairs']} | {fmt_num(g['baseline_mean'])} "
            f"| {fmt_num(g['objective_mean'])} | {fmt_num(g['delta_mean'], 2, True)} {ci} | {_fmt_p(g['p_value'])} |"
        )
    pending = {k: v for k, v in missing.items() if v}
    if pending:
        out += ["", "## Not finished yet", ""]
        out += [
            f"- {k}: {len(v)} run(s) ({', '.join(v[:4])}{', ...' if len(v) > 4 else ''})" for k, v in pending.items()
        ]
    return "\n".join(out) + "\n"


def planned(study: Study, planner: Planner, out: Path) -> dict[str, list[Spec]]:
    """Every regime's planned runs (R1 needs its source to have finished, R2 its screening list)."""
    plans: dict[str, list[Spec]] = {}
    source = source_spec(study, planner)
    if source.finished:
        plans["R1"] = r1_specs(study, planner, source, study.r1_budgets[:1])
        plans["R1-10"] = r1_specs(study, planner, source, study.r1_budgets[1:])
    tasks = screening(out)
    if tasks is not None:
        plans["R2"] = r2_specs(study, planner, tasks)
    plans["R3"] = r3_specs(study, planner)
    return plans


def chunked_loaded(study: Study, planner: Planner, out: Path, label: str, complete: bool) -> tuple[dict, list[str]]:
    """The finished runs of a chunked-heads regime per arm, over the seeds every arm has finished, and the
    names of its runs not finished.

    Raises:
        SystemExit: the plan changed after its runs started; with ``complete``, an arm misses a seed (the
            runs named); a seed's runs trained at different commits or machines (:func:`check_pairs`).
    """
    from tar_rl.report import load_run

    specs = chunked_specs(study, planner, label)
    check_plan_started(out, label, specs, record=False)
    missing = [s.run_dir.name for s in seed_major(specs) if not s.finished]
    if complete and missing:
        raise SystemExit(f"regimes: {label} misses {len(missing)} run(s) of its plan: {', '.join(missing)}")
    done = {arm: {s.config["seed"]: s for s in group if s.finished} for arm, group in specs.items()}
    seeds = sorted(set.intersection(*(set(d) for d in done.values())))
    loaded = {arm: [load_run(done[arm][seed].run_dir) for seed in seeds] for arm in ARMS}
    if seeds:
        check_pairs([run for group in loaded.values() for run in group])
    return loaded, missing


def chunked_tables(study: Study, planner: Planner, out: Path, complete: bool) -> tuple[list, list, list, list, dict]:
    """Decision rows (one per regime and TAR arm, Holm over all of them), per-group rows, fit rows, the
    figure's compare rows and the missing runs of the chunked-heads regimes."""
    from tar_rl.report import compare, holm

    rows, groups, fits, figure, missing = [], [], [], [], {}
    for label, head, _ in study.chunked_heads:
        loaded, missing[label] = chunked_loaded(study, planner, out, label, complete)
        if not loaded[BASELINE]:
            continue
        for arm in ARMS:
            fits.append({"regime": label, "head": head, "arm": arm, **fit_summary(loaded[arm])})
            table = compare(loaded[arm], file=io.StringIO())
            figure.append(table.assign(policy=f"{label} {head}", objective=arm))
        for arm in ARMS[1:]:
            row, group = regime_rows(f"{label} {arm}", [*loaded[BASELINE], *loaded[arm]])
            rows.append(row)
            groups.append(group)
    for row, p in zip(rows, holm([r["p_success"] for r in rows])):
        row["holm_p"] = p
    return rows, groups, fits, figure, missing


def chunked_markdown(fits: Sequence[dict]) -> str:
    """The chunked heads' fit diagnostics and weight statistics per regime and arm."""
    if not fits:
        return ""
    lines = ["", "## Chunked heads: fit and weights", ""]
    lines += fit_markdown(pd.DataFrame(fits), ["regime", "head", "arm"])
    lines += [
        "",
        "Means over the paired seeds; largest weight and ESS (fraction of valid steps) over the last "
        f"{FINAL_SHARE:.0%} of training steps (a uniform run's weights are all 1).",
    ]
    return "\n".join(lines) + "\n"


def write_tables(
    study: Study, planner: Planner, out: Path, prov: dict, dest: Path | None = None, complete: bool = False
) -> str:
    """The decision table (markdown + CSV), per-group CSV, Fig. 3 per regime and per chunked head from the
    finished runs of ``out``, written into ``dest`` (default ``out``); returns the markdown.

    ``complete``: refuse a chunked-heads regime with a run of its plan missing (the final table)."""
    dest = out if dest is None else dest
    from tar_rl.io import atomic_write, write_csv_atomic, write_json_atomic
    from tar_rl.report import compare, holm, load_run, plot_success_vs_neps

    rows, groups, figure, missing = [], [], [], {}
    screened = screening(out)
    for label, specs in planned(study, planner, out).items():
        done = [s for s in specs if s.finished]
        missing[label] = [s.run_dir.name for s in specs if not s.finished]
        runs = [load_run(s.run_dir) for s in done]
        if label == "R2" and screened is not None:
            for run in runs:
                if list(run.config["data"]["tasks"]) != list(screened):
                    raise SystemExit(f"regimes: {run.name} trained on tasks other than {out / SCREENING_FILE}'s")
        seeds = {r.seed for r in runs if r.objective == BASELINE} & {r.seed for r in runs if r.objective == TREATMENT}
        runs = [r for r in runs if r.seed in seeds]
        if not seeds:
            continue
        check_pairs(runs)
        row, group = regime_rows(label, runs)
        rows.append(row)
        groups.append(group)
        table = compare(runs, file=io.StringIO())
        figure.append(table[table["objective"].isin([BASELINE, TREATMENT])].assign(policy=label))
    primary = [i for i, r in enumerate(rows) if r["regime"] in PRIMARY]
    adjusted = holm([rows[i]["p_success"] for i in primary])
    for r in rows:
        r["holm_p"] = math.nan
    for i, p in zip(primary, adjusted):
        rows[i]["holm_p"] = p
    c_rows, c_groups, c_fits, c_figure, c_missing = chunked_tables(study, planner, out, complete)
    rows, groups = rows + c_rows, groups + c_groups
    missing.update(c_missing)
    group_df = pd.concat(groups, ignore_index=True) if groups else pd.DataFrame()
    md = decision_markdown(rows, group_df, missing) + chunked_markdown(c_fits)
    atomic_write(dest / "decision.md", lambda f: f.write(md))
    write_csv_atomic(pd.DataFrame(rows).round(6), dest / "decision.csv")
    if len(group_df):
        write_csv_atomic(group_df.round(6), dest / "groups.csv")
    write_json_atomic(prov, dest / "provenance.json")
    if figure:
        fig_table = pd.concat(figure, ignore_index=True)
        plot_success_vs_neps(fig_table, dest / "fig3_regimes.png", caption="regimes as families: uniform -> TAR")
    if c_figure:
        fig_table = pd.concat(c_figure, ignore_index=True)
        caption = "chunked heads (R4 act, R5 flow): uniform -> tar, tar_gentle"
        plot_success_vs_neps(fig_table, dest / "fig3_chunked.png", caption=caption)
    return md


# -- Command line ----------------------------------------------------------------------------------


def _ints(text: str) -> tuple[int, ...]:
    try:
        return tuple(int(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None


def study_parser(
    prog: str, description: str, commands: Sequence[str], default_out: str, seeds: bool = True
) -> argparse.ArgumentParser:
    """The command line the study's scripts share: COMMAND, ``--scale``, ``--out``, ``--data-root``, ``--jobs``,
    ``--from`` (for ``collect``), ``--tables`` (for ``table``), ``--dry-run`` and, with ``seeds``, ``--seeds``
    (read by :func:`study_of`); a script adds its own options."""
    p = argparse.ArgumentParser(prog=prog, description=description)
    if seeds:
        p.add_argument("--seeds", type=_ints, default=None, help="override the seeds (default: the scale's)")
    p.add_argument("command", choices=commands)
    p.add_argument("--scale", default="cpu", choices=sorted(STUDIES))
    p.add_argument("--out", default=None, help=f"results folder (default: {default_out}; with --scale ci: required)")
    p.add_argument("--data-root", default="datasets", help="dataset cache folder (default: ./datasets)")
    p.add_argument("--jobs", type=int, default=None, help="runs trained at once (default: the scale's)")
    p.add_argument("--from", dest="source", default=None, help="collect: the runs folder to copy finished runs from")
    p.add_argument("--tables", default=None, help="table: write the tables here instead of into --out")
    p.add_argument("--dry-run", action="store_true", help="print the plan; run nothing")
    return p


def study_of(args: argparse.Namespace) -> Study:
    """The study at ``--scale``, with ``--seeds`` in place of its seeds when given."""
    study = STUDIES[args.scale]
    if args.seeds is not None:
        study = replace(study, scale=replace(study.scale, seeds=args.seeds))
    return study


def jobs_and_out(args: argparse.Namespace, scale: Scale, prog: str, default_out: Path) -> tuple[int, Path]:
    """The runs trained at once and the results folder of a :func:`study_parser` command line, checked."""
    jobs = scale.jobs if args.jobs is None else args.jobs
    if jobs < 1:
        raise SystemExit(f"{prog}: --jobs must be >= 1, got {jobs}")
    if args.out is None and args.scale != "cpu":
        raise SystemExit(f"{prog}: --out is required with --scale {args.scale} (the default folder holds the results)")
    return jobs, Path(args.out) if args.out else default_out


def exit_code(failed: Sequence[Spec]) -> int:
    """0, or 1 after naming the runs that failed."""
    if failed:
        print(f"\n{len(failed)} run(s) failed: " + ", ".join(s.run_dir.name for s in failed))
        return 1
    return 0


def _parser() -> argparse.ArgumentParser:
    p = study_parser(
        "regimes.py", "The pre-registered regime study: runs and tables.", COMMANDS, "benchmarks/results/regimes"
    )
    p.add_argument("--budgets", type=_ints, default=None, help="r1: only these demonstration budgets")
    p.add_argument(
        "--complete", action="store_true", help="table: refuse a chunked-heads regime with a run of its plan missing"
    )
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point (module docstring). Returns 0, or 1 when a run failed (the others still ran)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    args = _parser().parse_args(argv)
    study = study_of(args)
    jobs, out = jobs_and_out(args, study.scale, "regimes", Path(__file__).resolve().parent / "results" / "regimes")
    planner = Planner(study.scale, out, args.data_root)
    logs = out / "logs"
    failed: list[Spec] = []
    if args.command == "collect":
        if not args.source:
            raise SystemExit("regimes: collect needs --from DIR (a runs folder)")
        keep = [source_spec(study, planner).run_dir.name]
        names = collect(Path(args.source), out, keep_checkpoint=keep, keep_weights=weights_read(study, planner))
        print(f"copied {len(names)} finished run(s) into {out / 'runs'}: " + ", ".join(names))
        return 0
    if args.command == "r1":
        source = source_spec(study, planner)
        failed += execute(study.scale, [source], 1, args.dry_run, logs)
        if not source.finished:
            print("R1's source has not finished: its post-training runs are planned once it has")
        else:
            failed += execute(study.scale, r1_specs(study, planner, source, args.budgets), jobs, args.dry_run, logs)
    elif args.command == "r2-screen":
        spec = planner.spec(*study.screen)
        failed += execute(study.scale, [spec], 1, args.dry_run, logs)
        if spec.finished:
            print(f"R2's tasks: {write_screening(study, spec, out)} ({out / SCREENING_FILE})")
    elif args.command == "r2":
        tasks = screening(out)
        if tasks is None:
            raise SystemExit(f"regimes: no {out / SCREENING_FILE} yet; run `r2-screen` first")
        specs = r2_specs(study, planner, tasks)
        if not args.dry_run:
            check_started(out, tasks)
        failed += execute(study.scale, specs, jobs, args.dry_run, logs)
    elif args.command == "r3":
        failed += execute(study.scale, r3_specs(study, planner), jobs, args.dry_run, logs)
    elif args.command in ("r4", "r5"):
        specs = chunked_specs(study, planner, args.command.upper())
        check_plan_started(out, args.command.upper(), specs, record=not args.dry_run)
        failed += execute(study.scale, seed_major(specs), jobs, args.dry_run, logs)
    elif args.command == "table":
        prov = provenance(study.scale, argv, "regimes.py")
        print(write_tables(study, planner, out, prov, tables_dir(args, out), complete=args.complete))
    return exit_code(failed)


if __name__ == "__main__":
    raise SystemExit(main())
