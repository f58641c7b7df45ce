"""Speed of demonstration collection and of segment sampling, as ratios measured in one run.

Run from the repository root::

    .venv/bin/python -m benchmarks.bench_data [--quick] [--tasks mt10] [--demos 10] [--workers N] [--out PATH]
    .venv/bin/python -m benchmarks.bench_data --sections startup [--root DIR] --out benchmarks/results/startup.csv

Sections:

* ``collect_per_step`` (one process, one thread): ``collect_task`` vs a bare expert rollout loop
  (``set_task``, ``reset``, ``step(clip(expert(obs)))`` until the first success or the horizon,
  nothing recorded) on the same tasks and variations, with the MT1 variations already built.
  Throughput in environment steps/s (rejected episodes included); the ratio isolates the cost
  of recording. Variants alternate per task in a random order, ``--reps`` times.
* ``collect_end_to_end``: ``demos.collect(tasks, workers=W)`` vs the same bare loop sharded over
  a ``spawn`` pool of ``W`` processes (one task per job, workers importing only MetaWorld), both
  timed from the call to the last result: process start, imports, MT1 construction included.
* ``segments``: drawing one ``[256, 16]`` batch from a dataset's ``segments()`` sampler (all
  entries, and the entries a BC step reads) vs one training step (forward, backward, AdamW) of
  a 3 x 256 ReLU MLP (observation + one-hot task -> action) with ``TARLoss(BCLoss)`` on a fixed
  batch. Round-robin, medians.

* ``startup`` (not run by default): the cost of checking a dataset's content on load beside the
  default job's start-up. ``job_startup``: a fresh ``tar-rl train`` process with the default
  config (``tar-rl train`` with no arguments, ``data.root`` the benchmark's, the dataset already
  collected) timed from its launch to the start of its training loop: interpreter, imports,
  Hydra, validation, the run folder, the dataset load with its content check, the policy, the
  objective and the optimiser. ``load_dataset`` (the whole load, check included) and
  ``check_content`` (the SHA-256 of every file of the folder against ``digest.json``) in this
  process, on the same dataset, its files in the page cache as in the job. ``--tasks``/``--demos``
  are not used: the dataset is the default job's (``--quick``: two tasks x two demonstrations).

Output: a table on stdout and one tidy CSV (default ``benchmarks/results/data.csv``, written to a
temporary file and renamed into place) with columns ``section, variant, median, iqr, unit,
ratio_to_baseline, baseline, n, workers, tasks, torch, commit``. Targets from the issue:
collection throughput >= 0.85 of the bare rollout rate; a segment batch <= 5% of a train step; the
content check <= 2% of the job's start-up.
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import random
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

from benchmarks.common import SUMMARY_COLUMNS, git_commit, interleaved, median_iqr
from tar_rl.io import write_csv_atomic

REPO = Path(__file__).resolve().parent.parent
DEFAULT_OUT = REPO / "benchmarks" / "results" / "data.csv"
COLUMNS = [
    "section",
    "variant",
    *SUMMARY_COLUMNS,
    "workers",
    "tasks",
    "torch",
    "commit",
]
HORIZON = 500
BATCH, SLICE_LEN, HIDDEN, N_TASKS = 256, 16, 256, 50
TRAIN_KEYS = ["observation", "action", "task_id", ("collector", "mask")]


# -- Bare rollouts (kept free of tar_rl imports so that pool workers only load MetaWorld) ----------


def _variation(task: str, seed: int, j: int, cache: dict):
    import metaworld

    s = seed + j // 50
    if (task, s) not in cache:
        cache[(task, s)] = metaworld.MT1(task, seed=s)
    return cache[(task, s)].train_tasks[j % 50]


def bare_rollouts(task: str, n_demos: int, seed: int, max_attempts: int, cache: dict | None = None) -> int:
    """Expert episodes until ``n_demos`` succeed (or ``max_attempts``); returns env steps taken."""
    from metaworld.env_dict import ALL_V3_ENVIRONMENTS
    from metaworld.policies import ENV_POLICY_MAP

    warnings.filterwarnings("ignore", message="Constant")
    cache = {} if cache is None else cache
    env = ALL_V3_ENVIRONMENTS[task]()
    policy = ENV_POLICY_MAP[task]()
    steps = kept = j = 0
    while kept < n_demos and j < max_attempts:
        env.set_task(_variation(task, seed, j, cache))
        obs, _ = env.reset()
        for _ in range(HORIZON):
            obs, _, _, truncated, info = env.step(np.clip(policy.get_action(obs), -1.0, 1.0))
            steps += 1
            if info["success"]:
                kept += 1
                break
            if truncated:
                break
        j += 1
    env.close()
    return steps


def _bare_job(args) -> int:
    return bare_rollouts(*args)


# -- Helpers ---------------------------------------------------------------------------------------


# -- Sections --------------------------------------------------------------------------------------


def bench_collect_per_step(names, n_demos, seed, reps) -> list[dict]:
    from tar_rl.collectors.metaworld import demos, tasks

    max_attempts = demos.default_max_attempts(n_demos)
    cache: dict = {}
    for task in names:  # build every MT1 once, outside the timings
        for j in range(max_attempts):
            tasks.variation(task, seed, j)
            _variation(task, seed, j, cache)
    times = {"bare": [], "collect": []}
    steps = {"bare": 0, "collect": 0}
    rng = random.Random(0)
    for _ in range(reps):
        for task in names:
            order = ["bare", "collect"]
            rng.shuffle(order)
            for variant in order:
                t0 = time.perf_counter()
                if variant == "bare":
                    n = bare_rollouts(task, n_demos, seed, max_attempts, cache)
                else:
                    n = demos.collect_task(task, n_demos, seed, max_attempts).env_steps
                times[variant].append(time.perf_counter() - t0)
                steps[variant] += n
    rates = {v: steps[v] / sum(times[v]) for v in times}
    # per-rep rates: total steps over total time within each repetition
    per_rep = {v: [] for v in times}
    k = len(names)
    for v in times:
        steps_per_rep = steps[v] / reps  # deterministic: every repetition takes the same steps
        for r in range(reps):
            per_rep[v].append(steps_per_rep / sum(times[v][r * k : (r + 1) * k]))
    rows = []
    for v in ("bare", "collect"):
        _, iqr = median_iqr(per_rep[v])
        rows.append(
            {
                "section": "collect_per_step",
                "variant": v,
                "median": rates[v],
                "iqr": iqr,
                "unit": "env_steps/s",
                "ratio_to_baseline": rates[v] / rates["bare"],
                "baseline": "bare",
                "n": reps,
                "workers": 1,
            }
        )
    return rows


def bench_collect_end_to_end(names, n_demos, seed, workers, reps) -> list[dict]:
    from tar_rl.collectors.metaworld import demos

    max_attempts = demos.default_max_attempts(n_demos)
    w = max(1, min(workers, len(names)))
    ctx = multiprocessing.get_context("spawn")

    def bare() -> int:
        with ctx.Pool(w) as pool:
            return sum(pool.map(_bare_job, [(t, n_demos, seed, max_attempts) for t in names], chunksize=1))

    def collect() -> int:
        out = demos.collect(names, n_demos, seed=seed, workers=w, max_attempts=max_attempts, progress=False)
        return sum(r.env_steps for r in out.values())

    variants = {"bare_pool": bare, "collect": collect}
    rates: dict[str, list[float]] = {v: [] for v in variants}
    steps: dict[str, set[int]] = {v: set() for v in variants}
    for r in range(reps):
        for v in variants if r % 2 == 0 else reversed(variants):
            t0 = time.perf_counter()
            n = variants[v]()
            rates[v].append(n / (time.perf_counter() - t0))
            steps[v].add(n)
    if steps["bare_pool"] != steps["collect"]:
        print(f"warning: env steps differ: {steps}", file=sys.stderr)
    base, _ = median_iqr(rates["bare_pool"])
    rows = []
    for v, rs in rates.items():
        med, iqr = median_iqr(rs)
        rows.append(
            {
                "section": "collect_end_to_end",
                "variant": v,
                "median": med,
                "iqr": iqr,
                "unit": "env_steps/s",
                "ratio_to_baseline": med / base,
                "baseline": "bare_pool",
                "n": reps,
                "workers": w,
            }
        )
    return rows


def bench_segments(names, n_demos, seed, workers, reps, root) -> list[dict]:
    import torch
    from tensordict import TensorDict
    from tensordict.nn import TensorDictModule
    from torchrl.objectives import BCLoss

    from tar_rl import TARLoss
    from tar_rl.collectors.metaworld.dataset import build_dataset

    ds = build_dataset(root, names, n_demos, seed=seed, workers=workers, progress=False, verbose=False)
    torch.manual_seed(0)
    samplers = {
        "sample_all_keys": ds.segments(BATCH, SLICE_LEN),
        "sample_train_keys": ds.segments(BATCH, SLICE_LEN, keys=[k for k in TRAIN_KEYS if k[0] != "collector"]),
    }

    class Policy(torch.nn.Module):
        def __init__(self):
            super().__init__()
            layers, d = [], 39 + N_TASKS
            for _ in range(3):
                layers += [torch.nn.Linear(d, HIDDEN), torch.nn.ReLU()]
                d = HIDDEN
            self.net = torch.nn.Sequential(*layers, torch.nn.Linear(d, 4))

        def forward(self, obs, task_id):
            return self.net(torch.cat([obs, torch.nn.functional.one_hot(task_id, N_TASKS).to(obs.dtype)], -1))

    actor = TensorDictModule(Policy(), ["observation", "task_id"], ["action"])
    loss = TARLoss(BCLoss(actor, loss_function="mse", reduction="none"))
    opt = torch.optim.AdamW(loss.parameters(), lr=3e-4)
    fixed = samplers["sample_train_keys"].sample()
    fixed = TensorDict({k: fixed.get(k).clone() for k in TRAIN_KEYS}, fixed.batch_size)

    def train_step():
        out = loss(fixed)
        out["loss_tar"].backward()
        opt.step()
        opt.zero_grad()

    variants = {"train_step": train_step, **{k: s.sample for k, s in samplers.items()}}
    for fn in variants.values():  # warm-up
        for _ in range(3):
            fn()
    times = {k: [] for k in variants}
    rng = random.Random(0)
    for _ in range(reps):
        order = list(variants)
        rng.shuffle(order)
        for k in order:
            t0 = time.perf_counter()
            variants[k]()
            times[k].append((time.perf_counter() - t0) * 1e3)
    base, _ = median_iqr(times["train_step"])
    rows = []
    for k, ts in times.items():
        med, iqr = median_iqr(ts)
        rows.append(
            {
                "section": "segments",
                "variant": k,
                "median": med,
                "iqr": iqr,
                "unit": "ms",
                "ratio_to_baseline": med / base,
                "baseline": "train_step",
                "n": reps,
                "workers": 1,
            }
        )
    return rows


# A `tar-rl train` process that stops where its training loop would start (after building everything).
_STARTUP = """
import os, sys
from tar_rl.recipes import offline_bc

def run(self):
    print("ready", flush=True)
    os._exit(0)

offline_bc.Trainer.run = run
from tar_rl.cli import main
main(["train", *sys.argv[1:]])
"""


def _job_startup(overrides: list[str], cwd: str) -> float:
    """Seconds from launching ``tar-rl train OVERRIDES`` to the start of its training loop."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        [sys.executable, "-c", _STARTUP, *overrides], cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    for line in proc.stdout:
        if line.strip() == "ready":
            break
    seconds = time.perf_counter() - t0
    _, err = proc.communicate(timeout=120)
    if proc.returncode != 0:
        raise RuntimeError(f"the job did not start (exit {proc.returncode}): {err.strip()[-2000:]}")
    return seconds


def bench_startup(quick: bool, workers: int, reps: int, check_reps: int, root: str) -> list[dict]:
    from tar_rl.collectors.metaworld.dataset import build_dataset
    from tar_rl.data import check_content, load_dataset
    from tar_rl.recipes.config import DataConfig

    data = DataConfig()
    overrides = [f"data.root={root}", "logging.progress=false"]
    tasks, n_demos = list(data.tasks), data.n_demos
    if quick:
        tasks, n_demos = ["reach", "button-press-topdown"], 2
        overrides += [f"data.tasks=[{','.join(tasks)}]", f"data.n_demos={n_demos}"]
    ds = build_dataset(
        root,
        tasks,
        n_demos,
        seed=data.seed,
        chunk_horizon=data.chunk_horizon,
        history=data.history,
        workers=workers,
        progress=False,
        verbose=False,
    )
    size = sum(p.stat().st_size for p in ds.path.rglob("*") if p.is_file())
    print(f"dataset {ds.path}: {len(ds)} steps, {size / 1e6:.1f} MB in {sum(1 for _ in ds.path.rglob('*'))} entries")
    with tempfile.TemporaryDirectory(prefix="bench_startup_") as cwd:
        overrides.append(f"runs_root={Path(cwd) / 'runs'}")
        if not quick:
            _job_startup(overrides, cwd)  # warm-up: the page cache, Python's bytecode cache
        startup = [_job_startup(overrides, cwd) * 1e3 for _ in range(reps)]
    variants = {"load_dataset": lambda: load_dataset(ds.path), "check_content": lambda: check_content(ds.path)}
    times = {k: v * 1e3 for k, v in interleaved(variants, check_reps, seed=0).items()}
    base, _ = median_iqr(startup)
    rows = []
    for k, ts in {"job_startup": startup, **times}.items():
        med, iqr = median_iqr(ts)
        rows.append(
            {
                "section": "startup",
                "variant": k,
                "median": med,
                "iqr": iqr,
                "unit": "ms",
                "ratio_to_baseline": med / base,
                "baseline": "job_startup",
                "n": len(ts),
                "workers": 1,
                "tasks": ",".join(tasks) if quick else "default job",
            }
        )
    return rows


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tasks", default="mt10")
    parser.add_argument("--demos", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--reps", type=int, default=3, help="repetitions of collect_per_step")
    parser.add_argument("--e2e-reps", type=int, default=2, help="repetitions of collect_end_to_end (alternating)")
    parser.add_argument("--sample-reps", type=int, default=200, help="repetitions of the segments section")
    parser.add_argument("--startup-reps", type=int, default=5, help="job start-ups timed in the startup section")
    parser.add_argument("--check-reps", type=int, default=50, help="loads and content checks timed in startup")
    parser.add_argument(
        "--root", help="dataset cache of the startup section (default: a temporary folder, collected anew)"
    )
    parser.add_argument(
        "--sections",
        default="collect_per_step,collect_end_to_end,segments",
        help="comma-separated sections to run (default: the first three; startup runs only when named)",
    )
    parser.add_argument("--quick", action="store_true", help="2 tasks x 2 demos, few repetitions (smoke test)")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = parser.parse_args(argv)

    import pandas as pd
    import torch

    from tar_rl.collectors.metaworld import tasks

    torch.set_num_threads(1)
    warnings.filterwarnings("ignore", message="Constant")
    warnings.filterwarnings("ignore", message="The name target_actor_network_params")  # torchrl's BCLoss
    if args.quick:
        args.tasks, args.demos, args.reps, args.e2e_reps, args.sample_reps = "reach,button-press-topdown", 2, 1, 1, 20
        args.startup_reps, args.check_reps = 1, 3
    names = tasks.resolve_tasks(args.tasks)

    sections = args.sections.split(",")
    known = ("collect_per_step", "collect_end_to_end", "segments", "startup")
    if not sections or any(sec not in known for sec in sections):
        raise ValueError(f"--sections must name some of {', '.join(known)}, got {args.sections!r}")
    rows = []
    if "collect_per_step" in sections:
        rows += bench_collect_per_step(names, args.demos, args.seed, args.reps)
    if "collect_end_to_end" in sections:
        rows += bench_collect_end_to_end(names, args.demos, args.seed, args.workers, args.e2e_reps)
    if "segments" in sections:
        with tempfile.TemporaryDirectory(prefix="bench_data_") as root:
            rows += bench_segments(names, args.demos, args.seed, args.workers, args.sample_reps, root)
    if "startup" in sections:
        with tempfile.TemporaryDirectory(prefix="bench_data_") as scratch:
            root = args.root or scratch
            rows += bench_startup(args.quick, args.workers, args.startup_reps, args.check_reps, root)
    df = pd.DataFrame(rows)
    df["tasks"] = df["tasks"].fillna(args.tasks) if "tasks" in df else args.tasks
    df["torch"] = torch.__version__
    df["commit"] = git_commit()
    df = df[COLUMNS]
    with pd.option_context("display.width", 200, "display.max_columns", 20):
        print(df.drop(columns=["torch", "commit", "tasks"]).to_string(index=False))
    write_csv_atomic(df, args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
