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
* ``controls``: Table III for the scale's control family: every registered weighting (uniform, tar,
  shuffle, random, invert, perturb_high, perturb_low) on the control seeds (``table_III.md/.csv``).
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
import math
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

import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))  # paper_analysis.py beside this script

COMMANDS = ("protocol", "table", "controls", "critical_windows", "budget", "sensitivity", "all")
BASELINE, TREATMENT = "uniform", "tar"
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

        names = [o for o in OBJECTIVE_ORDER if o in WEIGHTINGS] + sorted(set(WEIGHTINGS) - set(OBJECTIVE_ORDER))
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
    from tar_rl.collectors.tasks import resolve_tasks

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


def provenance(scale: Scale, argv: Sequence[str]) -> dict:
    """Command, git commit, scale and machine of an output."""
    import torch

    from tar_rl.runs import git_commit

    device = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "cpu"
    return {
        "command": "python benchmarks/paper_experiments.py " + " ".join(shlex.quote(a) for a in argv),
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


def _caption(prov: dict) -> str:
    return (
        f"{prov['command']} | git {str(prov['git_commit'])[:10]} | scale {prov['scale']} | "
        f"{prov['hostname']}, {prov['cores']} cores, torch {prov['torch']}, {prov['device']}"
    )


def _prov_markdown(prov: dict) -> str:
    return (
        f"Command: `{prov['command']}`  \nGit commit: `{prov['git_commit']}`; scale: `{prov['scale']}` "
        f"({prov['scale_about']})  \nMachine: {prov['hostname']}, {prov['cores']} cores, {prov['platform']}, "
        f"torch {prov['torch']}, device {prov['device']}; written {prov['written']}"
    )


def _write_text(path: Path, text: str) -> Path:
    from tar_rl.io import atomic_write

    return atomic_write(path, lambda f: f.write(text))


def _start_output(folder: Path, prov: dict) -> None:
    from tar_rl.io import write_json_atomic

    folder.mkdir(parents=True, exist_ok=True)
    write_json_atomic(prov, folder / "provenance.json")


def _load(specs: Sequence[Spec]):
    """The finished runs of ``specs`` (loaded) and the names of the others."""
    from tar_rl.report import load_run

    runs, missing = [], []
    for spec in {s.run_dir: s for s in specs}.values():
        if spec.finished:
            runs.append(load_run(spec.run_dir))
        else:
            missing.append(spec.run_dir.name)
    return runs, missing


def _missing_note(missing: Sequence[str]) -> str:
    if not missing:
        return ""
    shown = ", ".join(missing[:10]) + (f" (+{len(missing) - 10} more)" if len(missing) > 10 else "")
    return f"\n\n**Incomplete**: {len(missing)} planned run(s) have not finished and are not included: {shown}."


# -- Reports ---------------------------------------------------------------------------------------


def report_table(specs: Sequence[Spec], folder: Path, prov: dict) -> dict[str, Path]:
    """Table I (markdown + CSV), the paired statistics, Fig. 3 and Fig. 4 from the protocol runs."""
    from paper_analysis import plot_group_deltas, plot_radar, table_one_markdown

    from tar_rl.io import write_csv_atomic
    from tar_rl.report import compare, paired_table, plot_success_vs_neps

    runs, missing = _load(specs)
    if not runs:
        raise SystemExit("paper_experiments: no finished protocol run yet; run the `protocol` command first")
    table = compare(runs)
    paired = paired_table(runs, objectives=[TREATMENT])
    out = {
        "table_I.csv": write_csv_atomic(table, folder / "table_I.csv"),
        "paired.csv": write_csv_atomic(paired, folder / "paired.csv"),
    }
    md = (
        "# Table I: uniform vs TAR per policy family\n\n"
        "Success % per difficulty group and overall; 100 x Fast20 and 100 x NEPS (lower is better). "
        "Rows: mean ± std over the paired seeds; Δ: mean paired difference (TAR - uniform) with its 95% CI "
        "(t quantile, n - 1 degrees of freedom); p: two-sided paired t-test. "
        f"Evaluation seed {runs[0].eval_settings.get('eval.seed')}, "
        f"{runs[0].eval_settings.get('eval.rollouts')} rollouts per task, "
        f"{len(runs[0].eval_settings.get('tasks', ()))} tasks.\n\n"
        + table_one_markdown(paired, TREATMENT)
        + _missing_note(missing)
        + "\n\n"
        + _prov_markdown(prov)
        + "\n"
    )
    out["table_I.md"] = _write_text(folder / "table_I.md", md)
    caption = _caption(prov)
    out["fig3"] = plot_success_vs_neps(
        table[table["objective"].isin([BASELINE, TREATMENT])], folder / "fig3_success_vs_neps.png", caption=caption
    )
    out["fig3c"] = plot_group_deltas(paired, folder / "fig3c_group_deltas.png", TREATMENT, caption=caption)
    try:
        out["fig4"] = plot_radar(table, folder / "fig4_radar.png", TREATMENT, caption=caption)
    except ValueError as err:
        print(f"note: Fig. 4 not drawn: {err}")
    print(md)
    return out


def report_controls(specs: Sequence[Spec], folder: Path, prov: dict, family: str) -> dict[str, Path]:
    """Table III for one family: every weighting, success per group, paired difference to uniform."""
    from paper_analysis import controls_markdown

    from tar_rl.io import write_csv_atomic
    from tar_rl.report import compare, paired_table

    runs, missing = _load(specs)
    if not runs:
        raise SystemExit("paper_experiments: no finished control run yet")
    table = compare(runs)
    paired = paired_table(runs)
    md = (
        f"# Table III: controls ({family})\n\n"
        "Success % (mean ± std over seeds) per difficulty group and overall, and the paired difference of the "
        "overall success to uniform (95% CI, paired t-test).\n\n"
        + controls_markdown(paired, table, family)
        + _missing_note(missing)
        + "\n\n"
        + _prov_markdown(prov)
        + "\n"
    )
    out = {
        "table_III.csv": write_csv_atomic(table, folder / "table_III.csv"),
        "paired.csv": write_csv_atomic(paired, folder / "paired.csv"),
        "table_III.md": _write_text(folder / "table_III.md", md),
    }
    print(md)
    return out


def report_critical_windows(specs: Sequence[Spec], folder: Path, prov: dict, tasks: Sequence[str]) -> dict[str, Path]:
    """Phase shares of TAR weight mass per task (table, figure) and Fig. 5, from the TAR runs' weights.csv."""
    from paper_analysis import critical_windows, phase_weight_mass, plot_critical_windows, plot_weight_phases

    from tar_rl.io import write_csv_atomic
    from tar_rl.report import PHASES

    runs, missing = _load([s for s in specs if s.config["objective"]["name"] == TREATMENT])
    runs = [r for r in runs if r.weights is not None]
    if not runs:
        raise SystemExit("paper_experiments: no finished TAR run with recorded weights (weights.csv) yet")
    frames = [r.weights.assign(run=r.name) for r in sorted(runs, key=lambda r: (r.policy, r.seed))]
    mass = phase_weight_mass(pd.concat(frames, ignore_index=True))
    windows = critical_windows(mass)
    header = "| task | demos | with grip | " + " | ".join(p.replace("_", " ") for p in PHASES) + " | peak |"
    lines = [header, "|" + "---|" * (4 + len(PHASES))]
    for rec in windows.to_dict("records"):
        cells = [
            "-" if rec[f"{p}_steps"] == 0 else f"{100 * rec[f'{p}_weight']:.0f}% / {100 * rec[f'{p}_steps']:.0f}%"
            for p in PHASES
        ]
        lines.append(
            f"| {rec['task']} | {rec['demos']} | {rec['with_anchor']} | " + " | ".join(cells) + f" | {rec['peak']} |"
        )
    md = (
        "# Critical windows: where TAR's weights concentrate\n\n"
        "Per task, over the recorded demonstrations of the TAR runs (weights at the last training step): share of "
        "the TAR weight mass / share of the steps in each phase. Phases from the gripper action (action[3]): "
        "contact onset = the steps within 10% of the demonstration's length of the first gripper-closing step, "
        "approach before it, completion = the last 15% of the steps, transport between. Tasks without a closing "
        "step have only approach and completion. peak: the phase with the largest weight/step ratio.\n\n"
        + "\n".join(lines)
        + _missing_note(missing)
        + "\n\n"
        + _prov_markdown(prov)
        + "\n"
    )
    caption = _caption(prov)
    out = {
        "critical_windows.csv": write_csv_atomic(windows, folder / "critical_windows.csv"),
        "phase_mass.csv": write_csv_atomic(mass, folder / "phase_mass.csv"),
        "critical_windows.md": _write_text(folder / "critical_windows.md", md),
        "critical_windows.png": plot_critical_windows(windows, folder / "critical_windows.png", caption=caption),
    }
    from tar_rl.collectors.tasks import resolve_tasks

    first = min(runs, key=lambda r: (r.policy, r.seed))
    wanted = [resolve_tasks([t])[0] for t in tasks]  # "reach" -> "reach-v3", in the order given
    recorded = sorted(set(first.weights["task"]))
    present = [t for t in wanted if t in recorded]
    if len(present) < min(3, len(wanted)):  # fill up with recorded tasks, so that the figure always shows some
        present += [t for t in recorded if t not in present][: min(3, len(wanted)) - len(present)]
    if present:
        out["fig5"] = plot_weight_phases(
            first.weights, folder / "fig5_weights.png", present, caption=f"run {first.name} | {caption}"
        )
    print(md)
    return out


def report_budget(specs: Sequence[Spec], folder: Path, prov: dict) -> dict[str, Path]:
    """Success vs demonstrations per task for uniform and TAR (mean ± std over seeds, paired difference)."""
    from paper_analysis import plot_lines

    from tar_rl.io import write_csv_atomic
    from tar_rl.report import paired_t, run_percent

    runs, missing = _load(specs)
    if not runs:
        raise SystemExit("paper_experiments: no finished budget run yet")
    rows = []
    by = {}
    for r in runs:
        by.setdefault(int(r.config["data"]["n_demos"]), {}).setdefault(r.objective, {})[r.seed] = r
    for n in sorted(by):
        for objective, seeds in by[n].items():
            vals = [run_percent(seeds[s])[("success", "overall")] for s in sorted(seeds)]
            rows.append(
                {
                    "n_demos": n,
                    "objective": objective,
                    "n_seeds": len(vals),
                    "mean": sum(vals) / len(vals),
                    "std": pd.Series(vals).std(ddof=1) if len(vals) > 1 else math.nan,
                }
            )
    df = pd.DataFrame(rows)
    lines = ["| demos per task | uniform | tar | Δ tar - uniform [95% CI] | p | pairs |", "|---|---|---|---|---|---|"]
    for n in sorted(by):
        b, t = by[n].get(BASELINE, {}), by[n].get(TREATMENT, {})
        shared = sorted(set(b) & set(t))
        d = [run_percent(t[s])[("success", "overall")] - run_percent(b[s])[("success", "overall")] for s in shared]
        st = paired_t(d)

        def mean_sd(obj, n=n):
            m = df[(df["n_demos"] == n) & (df["objective"] == obj)]
            if m.empty:
                return "-"
            sd = m["std"].iloc[0]
            return f"{m['mean'].iloc[0]:.1f}" + ("" if math.isnan(sd) else f" ± {sd:.1f}")

        ci = "" if math.isnan(st["ci_low"]) else f" [{st['ci_low']:+.2f}, {st['ci_high']:+.2f}]"
        delta = "-" if not shared else f"{st['mean']:+.2f}{ci}"
        p = "-" if math.isnan(st["p_value"]) else f"{st['p_value']:.3f}"
        lines.append(f"| {n} | {mean_sd(BASELINE)} | {mean_sd(TREATMENT)} | {delta} | {p} | {len(shared)} |")
    md = (
        "# Demonstration budget: overall success % vs demonstrations per task\n\n"
        + "\n".join(lines)
        + _missing_note(missing)
        + "\n\n"
        + _prov_markdown(prov)
        + "\n"
    )
    out = {
        "budget.csv": write_csv_atomic(df, folder / "budget.csv"),
        "budget.md": _write_text(folder / "budget.md", md),
        "budget.png": plot_lines(
            df,
            folder / "budget.png",
            "n_demos",
            "demonstrations per task",
            "overall success (%)",
            "Success vs demonstration budget (mean ± std over seeds)",
            caption=_caption(prov),
        ),
    }
    print(md)
    return out


def report_sensitivity(specs: Sequence[Spec], folder: Path, prov: dict, eval_seed: int) -> dict[str, Path]:
    """The gamma x w_max x cap grid: overall success and the paired difference to uniform per cell."""
    from paper_analysis import plot_heatmaps

    from tar_rl.io import write_csv_atomic
    from tar_rl.report import paired_t, run_percent

    runs, missing = _load(specs)
    if not runs:
        raise SystemExit("paper_experiments: no finished sensitivity run yet")
    base = {r.seed: run_percent(r)[("success", "overall")] for r in runs if r.objective == BASELINE}
    cells: dict[tuple, dict[int, float]] = {}
    for r in runs:
        if r.objective != TREATMENT:
            continue
        o = r.config["objective"]
        cells.setdefault((float(o["gamma"]), float(o["w_max"]), str(o["cap"])), {})[r.seed] = run_percent(r)[
            ("success", "overall")
        ]
    rows = []
    for (g, w, c), seeds in sorted(cells.items()):
        shared = sorted(set(seeds) & set(base))
        st = paired_t([seeds[s] - base[s] for s in shared])
        rows.append(
            {
                "gamma": g,
                "w_max": w,
                "cap": c,
                "n_seeds": len(seeds),
                "success": sum(seeds.values()) / len(seeds),
                "uniform": sum(base[s] for s in shared) / len(shared) if shared else math.nan,
                "n_pairs": len(shared),
                "delta": st["mean"],
                "ci_low": st["ci_low"],
                "ci_high": st["ci_high"],
                "p_value": st["p_value"],
            }
        )
    df = pd.DataFrame(rows)
    lines = ["| gamma | w_max | cap | success % | Δ vs uniform [95% CI] | pairs |", "|---|---|---|---|---|---|"]
    for rec in rows:
        ci = "" if math.isnan(rec["ci_low"]) else f" [{rec['ci_low']:+.2f}, {rec['ci_high']:+.2f}]"
        delta = "-" if not rec["n_pairs"] else f"{rec['delta']:+.2f}{ci}"
        lines.append(
            f"| {rec['gamma']:g} | {rec['w_max']:g} | {rec['cap']} | {rec['success']:.1f} | {delta} "
            f"| {rec['n_pairs']} |"
        )
    md = (
        "# Sensitivity of TAR to gamma, w_max and the cap mode\n\n"
        f"**Tuning set**: evaluated on eval.seed = {eval_seed} (variations not used by the final tables, which "
        "use eval.seed = 1000). Uniform (same seeds, same evaluation): "
        + (", ".join(f"seed {s}: {v:.1f}%" for s, v in sorted(base.items())) or "-")
        + ".\n\n"
        + "\n".join(lines)
        + _missing_note(missing)
        + "\n\n"
        + _prov_markdown(prov)
        + "\n"
    )
    out = {
        "sensitivity.csv": write_csv_atomic(df, folder / "sensitivity.csv"),
        "sensitivity.md": _write_text(folder / "sensitivity.md", md),
    }
    if len(df):
        out["sensitivity.png"] = plot_heatmaps(
            df,
            folder / "sensitivity.png",
            "gamma",
            "w_max",
            "cap",
            "delta",
            f"TAR - uniform, overall success (pp), tuning eval seed {eval_seed}",
            caption=_caption(prov),
        )
    print(md)
    return out


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
        _start_output(folder, prov)
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
