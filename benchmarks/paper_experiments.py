"""The paper's experiments (Sec. III-IV) as commands: runs through the offline BC recipe, then tables and figures.

Usage::

    python benchmarks/paper_experiments.py COMMAND [--scale ci|cpu|paper] [--out DIR] [--jobs N]
                                           [--seeds 0,1,..] [--families mlp,..] [--set KEY=VALUE ...]
                                           [--dry-run] [--report-only] [--data-root DIR]

Commands (each runs what it needs, skipping finished runs, then writes its tables and figures into
``<out>/<command>/``; every run lands in ``<out>/runs/``):

* ``protocol``: policy families x {uniform, tar} x seeds at the scale's fixed demonstration budget
  and evaluation protocol (runs only).
* ``table``: the paper's Table I per family from the ``protocol`` runs: success per difficulty group
  and overall, 100 x Fast20, 100 x NEPS, baseline vs TAR, the paired difference over seeds, its 95%
  confidence interval (t quantile) and the paired t-test's p-value (``table_I.md``,
  ``table_I.csv``, ``paired.csv``); Fig. 3 (``fig3_success_vs_neps.png``: arrows uniform -> TAR per
  family; ``fig3c_group_deltas.png``: Δ success and Δ Fast20 per group) and Fig. 4 (``fig4_radar.png``).
* ``controls``: Table III for the scale's control family: the paper's weightings (uniform, tar,
  shuffle, random, invert, perturb_high, perturb_low; :data:`tar_rl.report.OBJECTIVE_ORDER`) on the
  control seeds (``table_III.md/.csv``). The baselines from the literature (``tilted``, ...) are
  not in the paper's table.
* ``critical_windows``: from the TAR runs' recorded weights (``weights.csv``, the last training
  step): per task, the share of TAR weight mass in approach / contact onset / transport / completion
  (anchored at the gripper-closing step, action[3] of the demonstration;
  :func:`tar_rl.report.phase_labels`), a table and a figure, and Fig. 5 for the scale's chosen
  tasks (``fig5_weights.png``).
* ``budget``: success vs demonstrations per task (the scale's list) for uniform and TAR
  (``budget.md/.csv``, ``budget.png``).
* ``sensitivity``: TAR over gamma x w_max x cap, and uniform, on a *tuning* evaluation seed set
  (``eval.seed`` = the scale's ``sens_eval_seed``, 2000 by default) that is not the final tables'
  (``eval.seed`` = 1000, the paper's); ``sensitivity.md/.csv``, ``sensitivity.png``.
* ``all``: protocol, table, controls, critical_windows, budget, sensitivity, in this order.

Scales (:data:`SCALES`): ``paper`` (MT50, the paper's 100K steps, TAR from 20K over 30K, 50
rollouts per task at seed 1000, the five families; a GPU machine), ``cpu`` (the MLP family on eight
tasks, two per difficulty group, sized to about an hour per command on 2 cores) and ``ci`` (two tasks,
2 steps, one short rollout: what the tests run). Baseline and TAR runs of a pair differ only in
``objective=``: same data, seeds, evaluation variations and every other setting.

Resuming: every run is a recipe run directory named by its settings, so running a command again
skips the finished runs and resumes an interrupted one from its checkpoint. ``--dry-run`` prints
the plan (runs to do and done) and a time estimate; ``--report-only`` writes the tables from the
finished runs without training (unfinished ones are listed).

Provenance: every output folder holds ``provenance.json`` (command, git commit, scale, machine:
hostname, cores, torch, device) and each markdown table and figure footer repeats it.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shlex
import socket
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))  # paper_analysis.py, paper_reports.py beside this script
from paper_reports import (
    BASELINE,
    TREATMENT,
    report_budget,
    report_controls,
    report_critical_windows,
    report_sensitivity,
    report_table,
    start_output,
)

COMMANDS = ("protocol", "table", "controls", "critical_windows", "budget", "sensitivity", "all")
# The paper's five families (ACT, Octo linear, Octo diffusion, a flow head, and the MLP reference).
PAPER_FAMILIES = ("mlp", "act", "octo_linear", "octo_diffusion", "flow")
# The eight tasks of the recipe's default job: two per difficulty group.
EIGHT_TASKS = (
    "[reach,button-press-topdown,basketball,peg-insert-side,assembly,pick-out-of-hole,stick-pull,pick-place-wall]"
)


@dataclass(frozen=True)
class Scale:
    """A named size of the experiments.

    Attributes:
        name: the scale's name.
        about: one line on what it is for.
        common: Hydra overrides shared by every run of every command.
        families: policy families of ``protocol`` / ``table``.
        seeds: training seeds of ``protocol``.
        control_family: the family of ``controls``, ``budget``, ``sensitivity``.
        control_seeds: seeds of ``controls``.
        budget_demos: demonstrations per task of ``budget``.
        budget_seeds: seeds of ``budget``.
        sens_gamma, sens_w_max, sens_cap: the ``sensitivity`` grid.
        sens_seeds: seeds of ``sensitivity``.
        sens_eval_seed: evaluation seed of ``sensitivity`` (the tuning set; the tables use ``eval.seed``).
        fig5_tasks: tasks drawn in Fig. 5.
        jobs: runs trained at once by default.
        step_seconds: the time model: seconds per training step of one run (one core).
        rollout_seconds: seconds per evaluation rollout (one core).
    """

    name: str
    about: str
    common: tuple[str, ...]
    families: tuple[str, ...]
    seeds: tuple[int, ...]
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
    jobs: int = 1
    step_seconds: float = 0.025
    rollout_seconds: float = 0.9

    def value(self, key: str, default=None):
        """The value the scale's overrides give ``key`` (as text), else ``default``."""
        for item in reversed(self.common):
            k, _, v = item.partition("=")
            if k == key:
                return v
        return default


SCALES: dict[str, Scale] = {
    "paper": Scale(
        name="paper",
        about="the paper's protocol: MT50, 100K steps (TAR from 20K over 30K), 50 rollouts per task at seed 1000, "
        "five families; for a GPU machine",
        common=(
            "data=mt50",
            "data.n_demos=25",
            "optim=paper",
            "eval=paper",
            "logging=quiet",
            "logging.record_episodes=3",
        ),
        families=PAPER_FAMILIES,
        seeds=(0, 1, 2),
        control_seeds=(0, 1, 2),
        budget_demos=(1, 3, 10, 25),
        budget_seeds=(0, 1, 2),
        sens_seeds=(0,),
        jobs=1,
        step_seconds=0.02,
        rollout_seconds=0.06,  # 16 evaluation workers
    ),
    "cpu": Scale(
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
        families=("mlp",),
        seeds=(0, 1, 2, 3, 4, 5, 6, 7),
        jobs=2,
    ),
    "ci": Scale(
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
        families=("mlp",),
        seeds=(0, 1),
        control_seeds=(0,),
        budget_demos=(1, 2),
        budget_seeds=(0,),
        sens_gamma=(1.0, 2.0),
        sens_w_max=(3.0,),
        sens_cap=("paper",),
        sens_seeds=(0,),
        fig5_tasks=("reach", "basketball"),
        jobs=1,
    ),
}


# -- Plans: the runs of each command -------------------------------------------------------------


@dataclass
class Spec:
    """One training run: its Hydra overrides, resolved config and run directory."""

    overrides: tuple[str, ...]
    config: dict
    run_dir: Path

    @property
    def finished(self) -> bool:
        """The run directory holds a summary saying the run finished."""
        try:
            return bool(json.loads((self.run_dir / "summary.json").read_text()).get("finished"))
        except (OSError, ValueError):
            return False


def _compose(overrides: Sequence[str]) -> dict:
    from hydra import compose, initialize

    from tar_rl.recipes import resolve_config
    from tar_rl.recipes.config import register_configs

    register_configs()
    with initialize(version_base="1.3", config_path=None):
        return resolve_config(compose(config_name="train", overrides=list(overrides)))


class Planner:
    """Builds :class:`Spec` lists for a scale, an output folder and the user's extra overrides."""

    def __init__(self, scale: Scale, out: Path, data_root: str, extra: Sequence[str] = ()):
        self.scale, self.out, self.data_root, self.extra = scale, out, data_root, tuple(extra)

    def spec(self, *overrides: str) -> Spec:
        from tar_rl.recipes import ConfigError, run_name, validate
        from tar_rl.recipes.config import config_dict

        items = (
            *self.scale.common,
            f"runs_root={self.out / 'runs'}",
            f"data.root={self.data_root}",
            *self.extra,
            *overrides,
        )
        try:
            config = _compose(items)
            job = validate(config)
        except ConfigError as err:
            raise SystemExit(f"paper_experiments: {err}") from None
        except Exception as err:  # Hydra's composition errors name the bad override
            raise SystemExit(f"paper_experiments: bad settings {list(items)}: {err}") from None
        return Spec(items, config, Path(job.config.runs_root) / run_name(config_dict(job.config)))

    def protocol(self) -> list[Spec]:
        return [
            self.spec(f"policy={f}", f"objective={o}", f"seed={s}")
            for f in self.scale.families
            for s in self.scale.seeds
            for o in (BASELINE, TREATMENT)
        ]

    def controls(self) -> list[Spec]:
        from tar_rl.objectives import WEIGHTINGS
        from tar_rl.report import OBJECTIVE_ORDER

        names = [o for o in OBJECTIVE_ORDER if o in WEIGHTINGS]
        f = self.scale.control_family
        return [
            self.spec(f"policy={f}", f"objective={o}", f"seed={s}") for s in self.scale.control_seeds for o in names
        ]

    def budget(self) -> list[Spec]:
        f = self.scale.control_family
        return [
            self.spec(f"policy={f}", f"objective={o}", f"seed={s}", f"data.n_demos={n}")
            for n in self.scale.budget_demos
            for s in self.scale.budget_seeds
            for o in (BASELINE, TREATMENT)
        ]

    def sensitivity(self) -> list[Spec]:
        sc, f = self.scale, self.scale.control_family
        tune = f"eval.seed={sc.sens_eval_seed}"
        specs = []
        for s in sc.sens_seeds:
            specs.append(self.spec(f"policy={f}", f"objective={BASELINE}", f"seed={s}", tune))
            specs += [
                self.spec(
                    f"policy={f}",
                    f"objective={TREATMENT}",
                    f"seed={s}",
                    tune,
                    f"objective.gamma={g}",
                    f"objective.w_max={w}",
                    f"objective.cap={c}",
                )
                for g in sc.sens_gamma
                for w in sc.sens_w_max
                for c in sc.sens_cap
            ]
        return specs


def check_families(scale: Scale, families: Sequence[str]) -> None:
    """Refuse families that are not registered policy heads, naming the registered ones."""
    from tar_rl.policies import POLICIES

    unknown = [f for f in families if f not in POLICIES]
    if unknown:
        raise SystemExit(
            f"paper_experiments: the {scale.name!r} scale names policy families {unknown} that are not registered "
            f"policy heads; registered: {sorted(POLICIES)}. Choose others with --families."
        )


# -- Running -------------------------------------------------------------------------------------


def estimate_seconds(scale: Scale, specs: Sequence[Spec], jobs: int) -> float:
    """Wall-clock estimate of the runs: steps x step time + rollouts x rollout time, over ``jobs`` at once."""
    from tar_rl.collectors.metaworld.tasks import resolve_tasks

    total = 0.0
    for spec in specs:
        c = spec.config
        tasks = resolve_tasks(list(c["eval"]["tasks"] or c["data"]["tasks"]))
        total += c["optim"]["steps"] * scale.step_seconds + len(tasks) * c["eval"]["rollouts"] * scale.rollout_seconds
    return total / max(1, jobs)


def _collect_datasets(specs: Sequence[Spec]) -> None:
    """Collect (or load) each distinct dataset once, before runs start in parallel."""
    from tar_rl.recipes import make_dataset, validate

    seen = set()
    for spec in specs:
        d = spec.config["data"]
        key = json.dumps([d[k] for k in ("root", "tasks", "n_demos", "seed", "chunk_horizon", "history")])
        if key not in seen:
            seen.add(key)
            job = validate(spec.config)
            make_dataset(job.config.data, job.train_tasks, progress=False)


def execute(scale: Scale, specs: Sequence[Spec], jobs: int, dry_run: bool, log_dir: Path) -> list[Spec]:
    """Train the unfinished runs of ``specs`` (finished ones are skipped); returns the runs that failed.

    With ``jobs == 1`` the runs are trained one after another in this process; with more, as
    ``python -m tar_rl train`` subprocesses, ``jobs`` at once, each with ``eval.workers`` set to its
    share of the cores (a setting outside the run's identity) and its output in ``log_dir``.
    """
    unique = list({s.run_dir: s for s in specs}.values())
    todo = [s for s in unique if not s.finished]
    est = estimate_seconds(scale, todo, jobs)
    print(
        f"{len(unique)} runs: {len(unique) - len(todo)} finished (skipped), {len(todo)} to run "
        f"({jobs} at once; estimate {est / 3600:.2f} h at {scale.step_seconds * 1e3:.0f} ms/step, "
        f"{scale.rollout_seconds:.2f} s/rollout)"
    )
    for s in todo:
        print(f"  to run: {s.run_dir.name}  {' '.join(s.overrides[len(scale.common) + 2 :])}")
    if dry_run or not todo:
        return []
    _collect_datasets(todo)
    failed: list[Spec] = []
    if jobs <= 1:
        from tar_rl.recipes import train

        for i, spec in enumerate(todo, 1):
            print(f"[{i}/{len(todo)}] {spec.run_dir.name}", flush=True)
            try:
                train(spec.config)
            except Exception as err:  # one failed run must not stop a long sweep; reported at the end
                print(f"FAILED {spec.run_dir.name}: {type(err).__name__}: {err}", flush=True)
                failed.append(spec)
        return failed
    log_dir.mkdir(parents=True, exist_ok=True)
    workers = max(1, (os.cpu_count() or 1) // jobs)
    queue, running = list(todo), []
    done = 0
    try:
        while queue or running:
            while queue and len(running) < jobs:
                spec = queue.pop(0)
                cmd = [sys.executable, "-m", "tar_rl", "train", *spec.overrides]
                cmd += [f"eval.workers={workers}", "data.workers=1"]
                log = open(log_dir / f"{spec.run_dir.name}.log", "a")
                running.append((spec, subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT), log))
            time.sleep(1.0)
            for item in list(running):
                spec, proc, log = item
                if proc.poll() is None:
                    continue
                running.remove(item)
                log.close()
                done += 1
                status = "done" if proc.returncode == 0 else f"FAILED (exit {proc.returncode}, see {log.name})"
                print(f"[{done}/{len(todo)}] {spec.run_dir.name}: {status}", flush=True)
                if proc.returncode != 0:
                    failed.append(spec)
    finally:  # interrupted: stop the runs in flight (they resume from their last checkpoint next time)
        for _spec, proc, log in running:
            if proc.poll() is None:
                proc.terminate()
                try:
                    proc.wait(timeout=30)
                except subprocess.TimeoutExpired:
                    proc.kill()
            log.close()
    return failed


# -- Provenance ------------------------------------------------------------------------------------


def portable_argument(arg: str) -> str:
    """A command-line argument with the path it names (``PATH`` or ``KEY=PATH``) written relative to the repository
    (:func:`tar_rl.runs.portable_path`); a path outside the repository and its folders (an output that is not
    committed) is kept."""
    from tar_rl.runs import portable_path

    key, sep, value = arg.rpartition("=")
    try:
        return key + sep + portable_path(value, Path(__file__).resolve().parent.parent)
    except ValueError:
        return arg


def provenance(scale: Scale, argv: Sequence[str], script: str = "paper_experiments.py") -> dict:
    """Command (``script`` in ``benchmarks/`` with ``argv``, its paths relative to the repository), git commit,
    scale and machine of an output."""
    import torch

    from tar_rl.runs import git_commit

    command = " ".join(shlex.quote(portable_argument(a)) for a in argv)
    device = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "cpu"
    return {
        "command": f"python benchmarks/{script} {command}",
        "git_commit": git_commit() or "unknown",
        "scale": scale.name,
        "scale_about": scale.about,
        "hostname": socket.gethostname(),
        "cores": os.cpu_count(),
        "platform": platform.platform(),
        "torch": torch.__version__,
        "device": device,
        "written": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()),
    }


# -- Command line ----------------------------------------------------------------------------------


def _ints(text: str) -> tuple[int, ...]:
    try:
        values = tuple(int(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None
    if not values:
        raise argparse.ArgumentTypeError("expected at least one integer")
    return values


def _names(text: str) -> tuple[str, ...]:
    values = tuple(v.strip() for v in text.split(",") if v.strip())
    if not values:
        raise argparse.ArgumentTypeError("expected at least one name")
    return values


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="paper_experiments.py",
        description="The paper's experiments: runs via the offline BC recipe, then tables and figures.",
    )
    p.add_argument("command", choices=COMMANDS)
    p.add_argument("--scale", default="cpu", help=f"one of {sorted(SCALES)} (default: cpu)")
    p.add_argument("--out", default=None, help="results folder (default: benchmarks/results/paper-<scale>)")
    p.add_argument("--data-root", default="datasets", help="dataset cache folder (default: ./datasets)")
    p.add_argument("--jobs", type=int, default=None, help="runs trained at once (default: the scale's)")
    p.add_argument("--seeds", type=_ints, default=None, help="override the scale's seeds (every command)")
    p.add_argument("--families", type=_names, default=None, help="override the scale's policy families")
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="extra Hydra override for every run (repeatable)",
    )
    p.add_argument("--fig5-tasks", type=_names, default=None, help="tasks drawn in Fig. 5 (default: the scale's)")
    p.add_argument("--dry-run", action="store_true", help="print the plan and the time estimate; run nothing")
    p.add_argument("--report-only", action="store_true", help="write the tables from finished runs; train nothing")
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point; see the module docstring. Returns 0, or 1 when a run failed (the others still ran)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    args = _parser().parse_args(argv)
    if args.scale not in SCALES:
        raise SystemExit(f"paper_experiments: --scale={args.scale!r} is not valid; choose one of {sorted(SCALES)}")
    scale = SCALES[args.scale]
    if args.seeds is not None:
        s = args.seeds
        scale = replace(scale, seeds=s, control_seeds=s, budget_seeds=s, sens_seeds=s)
    if args.fig5_tasks is not None:
        scale = replace(scale, fig5_tasks=args.fig5_tasks)
    if args.families is not None:
        scale = replace(scale, families=args.families, control_family=args.families[0])
    jobs = scale.jobs if args.jobs is None else args.jobs
    if jobs < 1:
        raise SystemExit(f"paper_experiments: --jobs must be >= 1, got {jobs}")
    out = Path(args.out) if args.out else Path(__file__).resolve().parent / "results" / f"paper-{scale.name}"
    planner = Planner(scale, out, args.data_root, args.set)
    prov = provenance(scale, argv)
    commands = COMMANDS[:-1] if args.command == "all" else (args.command,)
    needs = {
        "protocol": planner.protocol,
        "table": planner.protocol,
        "critical_windows": planner.protocol,
        "controls": planner.controls,
        "budget": planner.budget,
        "sensitivity": planner.sensitivity,
    }
    trains = {"protocol", "controls", "budget", "sensitivity"}
    if any(c in ("protocol", "table", "critical_windows") for c in commands):
        check_families(scale, scale.families)
    if any(c in ("controls", "budget", "sensitivity") for c in commands):
        check_families(scale, (scale.control_family,))
    failed: list[Spec] = []
    for command in commands:
        print(f"\n== {command} (scale {scale.name}: {scale.about})")
        specs = needs[command]()
        if command in trains and not args.report_only:
            failed += execute(scale, specs, jobs, args.dry_run, out / "logs")
        if args.dry_run or command == "protocol":
            continue
        folder = out / command
        start_output(folder, prov)
        if command == "table":
            report_table(specs, folder, prov)
        elif command == "controls":
            report_controls(specs, folder, prov, scale.control_family)
        elif command == "critical_windows":
            report_critical_windows(specs, folder, prov, scale.fig5_tasks)
        elif command == "budget":
            report_budget(specs, folder, prov)
        elif command == "sensitivity":
            report_sensitivity(specs, folder, prov, scale.sens_eval_seed)
    if failed:
        print(f"\n{len(failed)} run(s) failed: " + ", ".join(s.run_dir.name for s in failed))
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
