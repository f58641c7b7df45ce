"""Scaling efficiency: training from 1 to N processes (DDP, gloo) and evaluation from 1 to all cores.

Run from the repository root::

    .venv/bin/python -m benchmarks.bench_scale [--quick] [--procs N] [--out PATH]

* ``train``: the default MLP head under ``TARLoss("tar")`` on synthetic ``[B, L] = [64, 16]``
  batches (the default job's global batch), forward + backward + AdamW, one torch thread per
  process. With 1 process it takes the whole batch; with N processes (``torch.multiprocessing`` +
  gloo, ``DistributedDataParallel``, as under ``torchrun``) each takes ``64 / N`` segments of the
  same global batch. Throughput = global segments per second; efficiency = throughput(N) /
  (N x throughput(1)), 1 being linear scaling. The two settings alternate over ``--reps`` rounds.
* ``eval``: ``tar_rl.collectors.metaworld.evaluate.evaluate`` of the expert policy on the same tasks and
  variations with 1 worker process and with N; environment steps per second; efficiency as above.

Output: a table on stdout and ``benchmarks/results/scale.csv`` (one row per section and round, and
a median row per section).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from datetime import timedelta
from pathlib import Path

import pandas as pd
import torch

from benchmarks.common import git_commit
from tar_rl.io import write_csv_atomic

B, L = 64, 16
EVAL_TASKS = ["reach", "drawer-close", "button-press-topdown", "door-open"]


def _objective():
    from tar_rl import TARLoss
    from tar_rl.policies import DataInfo, MLPConfig, build_policy

    torch.manual_seed(0)
    policy = build_policy(MLPConfig(), DataInfo())
    return TARLoss(policy.loss, "tar")


def _batch(n: int, seed: int):
    from tensordict import TensorDict

    g = torch.Generator().manual_seed(seed)
    return TensorDict(
        {
            "observation": torch.randn(n, L, 39, generator=g),
            "task_id": torch.randint(0, 50, (n, L), generator=g),
            "action": torch.rand(n, L, 4, generator=g) * 2 - 1,
            ("collector", "mask"): torch.ones(n, L, dtype=torch.bool),
        },
        [n, L],
    )


def _train_rank(rank: int, world: int, steps: int, store: str, out: str) -> None:
    torch.set_num_threads(1)
    objective = _objective()
    model = objective
    if world > 1:
        import torch.distributed as dist

        from tar_rl.distributed import data_parallel

        dist.init_process_group(
            "gloo", store=dist.FileStore(store, world), rank=rank, world_size=world, timeout=timedelta(minutes=5)
        )
        model = data_parallel(objective)
    optimizer = torch.optim.AdamW(objective.parameters(), lr=1e-4)
    share = B // world
    batches = [_batch(B, s)[rank * share : (rank + 1) * share] for s in range(4)]

    def step(i: int) -> None:
        out = model(batches[i % 4])
        optimizer.zero_grad(set_to_none=True)
        out["loss_tar"].backward()
        optimizer.step()

    for i in range(10):  # warm-up
        step(i)
    if world > 1:
        torch.distributed.barrier()
    start = time.perf_counter()
    for i in range(steps):
        step(i)
    if world > 1:
        torch.distributed.barrier()
    seconds = time.perf_counter() - start
    if rank == 0:
        Path(out).write_text(str(seconds))
    if world > 1:
        from tar_rl.distributed import close_group

        del model
        close_group()


def train_throughput(world: int, steps: int) -> float:
    """Global segments per second of ``steps`` DDP steps over ``world`` processes (1: no DDP)."""
    import torch.multiprocessing as mp

    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, "seconds")
        if world == 1:
            _train_rank(0, 1, steps, "", out)
        else:
            mp.spawn(_train_rank, args=(world, steps, os.path.join(tmp, "store"), out), nprocs=world, join=True)
        return steps * B / float(Path(out).read_text())


def eval_throughput(workers: int, rollouts: int, horizon: int, pool) -> float:
    """Environment steps per second of the expert policy through the evaluator, on ``pool`` (a ``RolloutPool``)."""
    from tar_rl.collectors.metaworld.evaluate import ExpertPolicy, evaluate

    start = time.perf_counter()
    rows = evaluate(
        ExpertPolicy(),
        EVAL_TASKS,
        rollouts_per_task=rollouts,
        horizon=horizon,
        workers=workers,
        progress=False,
        pool=pool,
    )
    return float(rows["steps"].sum()) / (time.perf_counter() - start)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--procs", type=int, default=os.cpu_count() or 2, help="N processes (default: every core)")
    parser.add_argument("--reps", type=int, default=5)
    parser.add_argument("--steps", type=int, default=100, help="timed training steps per round")
    parser.add_argument("--rollouts", type=int, default=10, help="evaluation rollouts per task")
    parser.add_argument("--quick", action="store_true", help="a few seconds: check that it runs")
    parser.add_argument("--out", default=str(Path(__file__).resolve().parent / "results" / "scale.csv"))
    args = parser.parse_args(argv)
    if args.quick:
        args.reps, args.steps, args.rollouts = 1, 5, 1
    n = args.procs
    rows = []
    from tar_rl.collectors.metaworld.evaluate import RolloutPool

    with RolloutPool() as pool:  # the evaluator's workers and envs, kept between rounds as in a training job
        for rep in range(args.reps):
            one, many = train_throughput(1, args.steps), train_throughput(n, args.steps)
            rows.append(("train", rep, "segments/s", one, many, many / (n * one)))
            horizon = 50 if args.quick else 500
            one = eval_throughput(1, args.rollouts, horizon, pool)
            many = eval_throughput(n, args.rollouts, horizon, pool)
            rows.append(("eval", rep, "env steps/s", one, many, many / (n * one)))
    df = pd.DataFrame(rows, columns=["section", "rep", "unit", "one_process", "n_processes", "efficiency"])
    medians = df.groupby("section", sort=False)[["one_process", "n_processes", "efficiency"]].median().reset_index()
    medians.insert(1, "rep", "median")
    medians.insert(2, "unit", df.groupby("section", sort=False)["unit"].first().to_numpy())
    df = pd.concat([df, medians], ignore_index=True)
    df["procs"], df["commit"], df["torch"] = n, git_commit(), torch.__version__
    write_csv_atomic(df, args.out)
    print(f"Scaling from 1 to {n} processes (efficiency 1 = linear), {args.reps} rounds, commit {git_commit()}:")
    for rec in df[df["rep"] == "median"].itertuples():
        print(
            f"  {rec.section:<6} 1 process {rec.one_process:10.1f} {rec.unit}   {n} processes {rec.n_processes:10.1f}"
            f"   efficiency {rec.efficiency:.2f}"
        )
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
