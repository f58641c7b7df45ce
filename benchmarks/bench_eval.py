"""Evaluation throughput vs raw MetaWorld simulation, measured side by side.

Run from the repository root::

    .venv/bin/python benchmarks/bench_eval.py [--quick] [--tasks T] [--rollouts R] [--workers W] [--out PATH]

Both sides run the same (task, rollout) pairs on the same variations (``tasks.variation(task,
1000, k)``), ``horizon`` steps each, and count executed env steps per second of wall time:

* ``raw``: bare MetaWorld envs, uniform random actions, a plain ``env.step`` loop; one env
  built per task per process, ``set_task`` + ``reset`` per rollout.
* ``eval``: ``tar_rl.collectors.evaluate.evaluate`` with a small MLP policy
  (39-256-256-4, tanh; random weights, so it rarely succeeds and rollouts run to the horizon),
  which builds its batched TorchRL envs, runs the policy once per batch step, etc.

Two sections, each repeated ``--reps`` times with raw and eval alternating (interleaved) so that
machine noise hits both alike, after ``--warmup`` untimed rounds (the first round pays one-off
costs, e.g. building ``metaworld.MT1`` objects that later rounds in this process find cached):

* ``one_process``: everything in this process (``workers=1``): the per-step overhead of the
  evaluator (TorchRL env, policy, bookkeeping, env construction) against the bare loop.
* ``all_cores``: ``--workers`` processes ('spawn') on both sides, over the same contiguous shards;
  wall time from submission to the last result, process start-up included on both sides.

Output: a table on stdout and a tidy CSV (default ``benchmarks/results/eval.csv``, written
atomically), one row per (section, rep) with ``raw_steps_per_s``, ``eval_steps_per_s``, ``ratio``
and the settings, plus a ``median`` row per section.
"""

from __future__ import annotations

import argparse
import itertools
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import pandas as pd

from tar_rl.io import write_csv_atomic

# Spawned workers import this module by name: keep its folder importable.
sys.path.insert(0, str(Path(__file__).resolve().parent))

DEFAULT_TASKS = "reach,drawer-close,button-press-topdown,door-open,pick-place,plate-slide"
COLUMNS = [
    "section",
    "rep",
    "raw_steps_per_s",
    "eval_steps_per_s",
    "ratio",
    "tasks",
    "rollouts_per_task",
    "horizon",
    "workers",
    "envs_per_worker",
]
SEED = 1000


def raw_shard(shard, horizon, rng_seed=0) -> int:
    """Random-action rollouts on bare MetaWorld envs; returns the executed steps."""
    from tar_rl.collectors import tasks

    envs = {}
    rng = np.random.default_rng(rng_seed)
    steps = 0
    for task, k in shard:
        if task not in envs:
            envs[task] = tasks.make_env(task)
        env = envs[task]
        env.set_task(tasks.variation(task, SEED, k))
        env.reset()
        for _ in range(horizon):
            env.step(rng.uniform(-1.0, 1.0, 4).astype(np.float32))
            steps += 1
    return steps


def _shards(names, rollouts, workers):
    jobs = [(t, k) for t in names for k in range(rollouts)]
    bounds = np.linspace(0, len(jobs), workers + 1).round().astype(int)
    return [jobs[a:b] for a, b in itertools.pairwise(bounds) if b > a]


def make_policy(seed=0):
    import torch
    from tensordict.nn import TensorDictModule
    from torch import nn

    torch.manual_seed(seed)
    net = nn.Sequential(nn.Linear(39, 256), nn.Tanh(), nn.Linear(256, 256), nn.Tanh(), nn.Linear(256, 4), nn.Tanh())
    return TensorDictModule(net, in_keys=["observation"], out_keys=["action"])


def run_raw(names, rollouts, horizon, workers) -> float:
    shards = _shards(names, rollouts, workers)
    start = time.perf_counter()
    if workers == 1:
        steps = raw_shard(shards[0], horizon)
    else:
        import multiprocessing as mp

        with ProcessPoolExecutor(len(shards), mp_context=mp.get_context("spawn")) as pool:
            steps = sum(pool.map(raw_shard, shards, [horizon] * len(shards)))
    return steps / (time.perf_counter() - start)


def run_eval(policy, names, rollouts, horizon, workers, envs_per_worker) -> float:
    from tar_rl.collectors.evaluate import evaluate

    start = time.perf_counter()
    df = evaluate(
        policy,
        list(names),
        rollouts_per_task=rollouts,
        seed=SEED,
        horizon=horizon,
        workers=workers,
        envs_per_worker=envs_per_worker,
        progress=False,
    )
    return int(df["steps"].sum()) / (time.perf_counter() - start)


def main(argv=None) -> pd.DataFrame:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--tasks", default=DEFAULT_TASKS)
    parser.add_argument("--rollouts", type=int, default=10, help="rollouts per task")
    parser.add_argument("--horizon", type=int, default=500)
    parser.add_argument("--workers", type=int, default=None, help="processes in all_cores (default: all cores)")
    parser.add_argument("--envs-per-worker", type=int, default=None)
    parser.add_argument("--reps", type=int, default=3)
    parser.add_argument("--warmup", type=int, default=1, help="untimed rounds per section first (file caches, imports)")
    parser.add_argument("--sections", default="one_process,all_cores")
    parser.add_argument("--quick", action="store_true", help="a smoke run: 2 tasks, 2 rollouts, horizon 50, 1 rep")
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "results" / "eval.csv")
    args = parser.parse_args(argv)
    if args.quick:
        args.tasks, args.rollouts, args.horizon, args.reps = "reach,drawer-close", 2, 50, 1

    import torch

    from tar_rl.collectors import tasks
    from tar_rl.collectors.evaluate import _cpu_count

    torch.set_num_threads(1)
    names = tasks.resolve_tasks(args.tasks)
    workers = args.workers or _cpu_count()
    policy = make_policy()
    rows = []
    for section in args.sections.split(","):
        if section not in ("one_process", "all_cores"):
            raise ValueError(f"unknown section {section!r}: choose one_process and/or all_cores")
        w = 1 if section == "one_process" else workers
        for _ in range(0 if args.quick else args.warmup):
            run_raw(names, args.rollouts, args.horizon, w)
            run_eval(policy, names, args.rollouts, args.horizon, w, args.envs_per_worker)
        for rep in range(args.reps):
            raw = run_raw(names, args.rollouts, args.horizon, w)
            evl = run_eval(policy, names, args.rollouts, args.horizon, w, args.envs_per_worker)
            rows.append(
                {
                    "section": section,
                    "rep": rep,
                    "raw_steps_per_s": raw,
                    "eval_steps_per_s": evl,
                    "ratio": evl / raw,
                }
            )
            print(
                f"{section:12s} rep {rep}: raw {raw:8.0f}  eval {evl:8.0f} steps/s  ratio {evl / raw:.3f}", flush=True
            )
        sec = [r for r in rows if r["section"] == section and r["rep"] != "median"]
        rows.append(
            {
                "section": section,
                "rep": "median",
                "raw_steps_per_s": float(np.median([r["raw_steps_per_s"] for r in sec])),
                "eval_steps_per_s": float(np.median([r["eval_steps_per_s"] for r in sec])),
                "ratio": float(np.median([r["ratio"] for r in sec])),
            }
        )
        print(f"{section:12s} median ratio {rows[-1]['ratio']:.3f}", flush=True)
    for r in rows:
        r.update(
            tasks=",".join(names),
            rollouts_per_task=args.rollouts,
            horizon=args.horizon,
            workers=workers if r["section"] == "all_cores" else 1,
            envs_per_worker=args.envs_per_worker or "default",
        )
    df = pd.DataFrame(rows, columns=COLUMNS)
    write_csv_atomic(df, args.out)
    print(f"wrote {args.out}")
    return df


if __name__ == "__main__":
    main()
