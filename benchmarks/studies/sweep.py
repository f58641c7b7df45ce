"""The sweep: train a stage's unfinished runs, one after another in this process or several at once as
``python -m tar_rl train`` subprocesses; finished runs are skipped and an interrupted one resumes from its
checkpoint, so a sweep is stopped and started again at will."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from benchmarks.studies.core import Scale, Spec

__all__ = ["check_tree", "estimate_seconds", "execute"]


def add_tree_option(parser, help_text: str) -> None:
    """The ``--tree DIR`` option of a study whose runs train with another checkout's code (:func:`check_tree`)."""
    parser.add_argument("--tree", type=Path, default=None, help=help_text)


def check_tree(tree: Path | None, who: str) -> Path | None:
    """The checkout ``--tree`` names (another checkout's code trains the runs), resolved; refused unless it holds
    tar-rl and its own ``.venv`` (``who`` names the study in the refusal)."""
    if tree is None:
        return None
    if not (tree / ".venv" / "bin" / "python").is_file() or not (tree / "tar_rl").is_dir():
        raise SystemExit(f"{who}: --tree {tree} is not a checkout of tar-rl with its own .venv (.venv/bin/python)")
    return tree.resolve()


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


def _train_here(todo: Sequence[Spec]) -> list[Spec]:
    """Train the runs one after another in this process; returns the ones that failed."""
    from tar_rl.recipes import train

    failed = []
    for i, spec in enumerate(todo, 1):
        print(f"[{i}/{len(todo)}] {spec.run_dir.name}", flush=True)
        try:
            train(spec.config)
        except Exception as err:  # one failed run must not stop a long sweep; reported at the end
            print(f"FAILED {spec.run_dir.name}: {type(err).__name__}: {err}", flush=True)
            failed.append(spec)
    return failed


def _stop(running: list) -> None:
    """Stop the runs in flight (they resume from their last checkpoint next time) and close their logs."""
    for _spec, proc, log in running:
        if proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
        log.close()


def _train_parallel(todo: Sequence[Spec], jobs: int, log_dir: Path, tree: Path | None = None) -> list[Spec]:
    """Train the runs as subprocesses, ``jobs`` at once, each with ``eval.workers`` set to its share of the cores
    (a setting outside the run's identity) and its output in ``log_dir``; returns the ones that failed.

    ``tree``: train with that checkout's code, its ``.venv/bin/python -m tar_rl train`` started in the checkout (a
    git worktree at a study's commit); a run that finishes in another folder than the one planned here failed."""
    log_dir.mkdir(parents=True, exist_ok=True)
    python, cwd = (sys.executable, None) if tree is None else (str(tree / ".venv" / "bin" / "python"), tree)
    workers = max(1, (os.cpu_count() or 1) // jobs)
    queue, running, failed = list(todo), [], []
    done = 0
    try:
        while queue or running:
            while queue and len(running) < jobs:
                spec = queue.pop(0)
                cmd = [python, "-m", "tar_rl", "train", *spec.overrides]
                cmd += [f"eval.workers={workers}", "data.workers=1"]
                log = open(log_dir / f"{spec.run_dir.name}.log", "a")
                proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, cwd=cwd)
                running.append((spec, proc, log))
            time.sleep(1.0)
            for item in list(running):
                spec, proc, log = item
                if proc.poll() is None:
                    continue
                running.remove(item)
                log.close()
                done += 1
                status = "done" if proc.returncode == 0 else f"FAILED (exit {proc.returncode}, see {log.name})"
                if proc.returncode == 0 and not spec.finished:
                    status = f"FAILED (finished, but not in {spec.run_dir}: the trained code names it otherwise)"
                print(f"[{done}/{len(todo)}] {spec.run_dir.name}: {status}", flush=True)
                if status != "done":
                    failed.append(spec)
    finally:  # interrupted: stop the runs in flight
        _stop(running)
    return failed


def execute(
    scale: Scale, specs: Sequence[Spec], jobs: int, dry_run: bool, log_dir: Path, tree: Path | None = None
) -> list[Spec]:
    """Train the unfinished runs of ``specs`` (finished ones are skipped); returns the runs that failed.

    With ``jobs == 1`` the runs are trained one after another in this process; with more, or with ``tree``, as
    subprocesses (:func:`_train_parallel`). ``dry_run`` prints the plan (runs to do and done) and the time estimate
    only. With ``tree`` the datasets are not collected here: the checkout's code reads (or collects) its own, so
    collect them there first when runs start at once.
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
    if tree is not None:
        return _train_parallel(todo, jobs, log_dir, tree)
    _collect_datasets(todo)
    return _train_here(todo) if jobs <= 1 else _train_parallel(todo, jobs, log_dir)
