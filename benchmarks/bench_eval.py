"""Evaluation throughput vs raw MetaWorld simulation, measured side by side.

Run from the repository root::

    .venv/bin/python -m benchmarks.bench_eval [--quick] [--tasks T] [--rollouts R] [--workers W] [--out PATH]

The policy is a TRAINED small MLP (tar-rl's ``mlp`` head, 2 x 256, learned task embedding,
normalised observations), fitted by behaviour cloning (plain MSE, ``--train-steps`` AdamW steps)
to ``--demos`` expert demonstrations per task; dataset and weights are cached under ``--cache``
(the same settings load them again). It succeeds on part of the rollouts, which then stop at
their first success, so rollouts have realistic, varied lengths and slots are refilled often.

Both sides run the same (task, rollout) pairs on the same variations (``tasks.variation(task,
1000, k)``, built once in this process and handed to workers on both sides) and execute the same
number of env steps per rollout: the evaluator's rows of an untimed first run (deterministic)
fix, for each rollout, the steps the raw side replays.

* ``raw``: bare MetaWorld envs, uniform random actions, a plain ``env.step`` loop; one env
  per task per process (kept between rounds, as the evaluator keeps its envs), ``set_task`` +
  ``reset`` per rollout, then exactly the rollout's step count.
* ``raw_interleaved``: the same bare loop, but with the evaluator's schedule: its batch size, its
  shard order and its slot refills (``rollouts.interleave``, ``rollouts.Pending``), stepping the
  running envs of the batch in turn. Stepping several MuJoCo models in turn runs colder in the CPU
  caches than one env in a row, and a batch runs part-empty at the end of a shard; this side pays
  both, so ``eval / raw_interleaved`` is what the evaluator's own machinery (TorchRL env, policy
  call, bookkeeping) costs, and ``eval / raw`` is the whole price of batched evaluation.
* ``eval``: ``tar_rl.collectors.metaworld.evaluate.evaluate`` with the trained policy: batched TorchRL env,
  one policy call per batch step, refills, env construction, bookkeeping.

Throughput is executed env steps per second of wall time. Two sections, each repeated
``--reps`` times with raw and eval alternating (interleaved) so that machine noise hits both
alike, after ``--warmup`` untimed rounds (the first round pays one-off costs):

* ``one_process``: everything in this process (``workers=1``): the per-step overhead of the
  evaluator (TorchRL env, policy, bookkeeping, env construction) against the bare loop.
* ``all_cores``: ``--workers`` processes on both sides, over the same contiguous shards; wall
  time from submission to the last result. Both sides keep their worker processes between
  rounds (the evaluator's on one ``RolloutPool``, as in a training job that evaluates every few
  thousand steps), so the warm-up round pays their start-up and the timed rounds measure the
  steady state.

Output: a table on stdout and a tidy CSV (default ``benchmarks/results/eval.csv``, written
atomically), one row per (section, rep) with ``raw_steps_per_s``, ``eval_steps_per_s``, ``ratio``
and the settings, plus a ``median`` row per section (and the policy's success rate and mean
steps per rollout).
"""

from __future__ import annotations

import argparse
import functools
import itertools
import math
import tempfile
import time
import warnings
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import pandas as pd

from tar_rl.io import write_csv_atomic

DEFAULT_TASKS = "reach,drawer-close,button-press-topdown,door-open,pick-place,plate-slide"
COLUMNS = [
    "section",
    "rep",
    "raw_steps_per_s",
    "eval_steps_per_s",
    "ratio",
    "raw_interleaved_steps_per_s",
    "ratio_interleaved",
    "tasks",
    "rollouts_per_task",
    "horizon",
    "workers",
    "envs_per_worker",
    "success_rate",
    "mean_steps",
    "commit",
]
SEED = 1000


# The raw side's envs, one per task, kept in the process between rounds like the evaluator's.
_RAW_ENVS: dict = {}


def raw_shard(shard, variations=None, rng_seed=0) -> int:
    """Random-action rollouts on bare MetaWorld envs; ``shard``: (task, k, steps) triples. Returns the steps."""
    from tar_rl.collectors.metaworld import tasks

    tasks.add_variations(variations or {})
    envs = _RAW_ENVS
    rng = np.random.default_rng(rng_seed)
    executed = 0
    for task, k, steps in shard:
        if task not in envs:
            envs[task] = tasks.make_env(task)
        env = envs[task]
        env.set_task(tasks.variation(task, SEED, k))
        env.reset()
        for _ in range(steps):
            env.step(rng.uniform(-1.0, 1.0, 4).astype(np.float32))
        executed += steps
    return executed


_RAW_IDLE: dict[str, list] = {}  # the interleaved raw side's envs per task, kept between rounds


def raw_interleaved_shard(shard, variations=None, rng_seed=0, *, batch: int) -> int:
    """``raw_shard`` on the evaluator's schedule: ``batch`` slots stepped in turn, refilled as it refills them."""
    from tar_rl.collectors.metaworld import tasks
    from tar_rl.collectors.metaworld.rollouts import Pending, interleave

    tasks.add_variations(variations or {})
    rng = np.random.default_rng(rng_seed)
    length = {(task, k): steps for task, k, steps in shard}
    pending = Pending(interleave([(task, k) for task, k, _ in shard]))

    def start(i, task, k, env=None):
        if env is None:
            idle = _RAW_IDLE.setdefault(task, [])
            env = idle.pop() if idle else tasks.make_env(task)
        env.set_task(tasks.variation(task, SEED, k))
        env.reset()
        slots[i] = [task, k, env, length[(task, k)]]

    slots: list = [None] * min(batch, len(length))
    for i in range(len(slots)):
        start(i, *pending.pop())
    executed = 0
    while any(slots):
        for slot in slots:
            if slot is not None:
                slot[2].step(rng.uniform(-1.0, 1.0, 4).astype(np.float32))
                slot[3] -= 1
                executed += 1
        for i, slot in enumerate(slots):
            if slot is None or slot[3] > 0:
                continue
            task, _, env, _ = slot
            if pending and pending.has(task):
                start(i, *pending.pop(task), env=env)
                continue
            _RAW_IDLE.setdefault(task, []).append(env)
            slots[i] = None
            if pending:
                start(i, *pending.pop())
    return executed


def _shards(jobs, workers):
    """The evaluator's contiguous split of the (task, rollout) list over ``workers`` processes."""
    bounds = np.linspace(0, len(jobs), workers + 1).round().astype(int)
    return [jobs[a:b] for a, b in itertools.pairwise(bounds) if b > a]


def trained_policy(names, demos: int, train_steps: int, cache: Path, seed: int = 0):
    """tar-rl's MLP head (2 x 256, task embedding) behaviour-cloned on ``demos`` expert episodes per task.

    The dataset and the trained weights are cached under ``cache`` (keyed by the settings).
    """
    import torch

    from tar_rl.collectors.metaworld.dataset import build_dataset
    from tar_rl.policies import DataInfo, build_policy

    ds = build_dataset(cache, list(names), demos, seed=seed, workers=1, progress=False, verbose=False)
    info = DataInfo.from_metadata(ds.metadata)
    policy = build_policy({"name": "mlp", "hidden": [256, 256]}, info).actor
    weights = cache / f"mlp-{ds.path.name}-{train_steps}-s{seed}.pt"
    if weights.exists():
        policy.load_state_dict(torch.load(weights, weights_only=True))
        return policy
    data = ds.data
    obs = data["observation"].clone()
    target = data["action"].clone()
    task_id = data["task_id"].clone()
    gen = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    net = policy.module
    opt = torch.optim.AdamW(net.parameters(), lr=1e-3)
    for _ in range(train_steps):
        idx = torch.randint(len(obs), (256,), generator=gen)
        loss = torch.nn.functional.mse_loss(net(obs[idx], task_id[idx]), target[idx])
        opt.zero_grad()
        loss.backward()
        opt.step()
    tmp = weights.with_suffix(".tmp")
    torch.save(policy.state_dict(), tmp)
    tmp.replace(weights)
    return policy


_RAW_POOL: dict = {}


def _pool(workers):
    """The raw side's 'spawn' worker processes, kept between rounds as the evaluator keeps its own."""
    if workers not in _RAW_POOL:
        import multiprocessing as mp

        _RAW_POOL[workers] = ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn"))
    return _RAW_POOL[workers]


def run_raw(jobs, workers, batch=None) -> float:
    """``jobs``: (task, k, steps) triples, in the evaluator's order; returns env steps/s.

    ``batch``: run each shard on the evaluator's schedule with that many slots (``raw_interleaved_shard``);
    ``None``: one env in a row (``raw_shard``).
    """
    from tar_rl.collectors.metaworld import tasks

    shards = _shards(jobs, workers)
    run = raw_shard if batch is None else functools.partial(raw_interleaved_shard, batch=batch)
    start = time.perf_counter()
    if workers == 1:
        steps = run(shards[0])
    else:
        keys = [{(task, SEED + k // tasks.VARIATIONS_PER_SEED) for task, k, _ in sh} for sh in shards]
        steps = sum(_pool(len(shards)).map(run, shards, [tasks.cached_variations(k) for k in keys]))
    return steps / (time.perf_counter() - start)


def eval_batch(n_jobs, workers, horizon, envs_per_worker) -> int:
    """The batch size ``evaluate`` gives each worker (its own rule, called here)."""
    from tar_rl.collectors.metaworld.evaluate import default_envs_per_worker

    return envs_per_worker or default_envs_per_worker(math.ceil(n_jobs / workers), horizon)


def run_eval(policy, names, rollouts, horizon, workers, envs_per_worker, pool) -> tuple[float, pd.DataFrame]:
    from tar_rl.collectors.metaworld.evaluate import evaluate

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
        pool=pool,
    )
    return int(df["steps"].sum()) / (time.perf_counter() - start), df


def run_section(section: str, args, names, workers: int, policy, pool) -> list[dict]:
    """The rows of one section: ``--reps`` rounds of raw, raw interleaved and eval, and their median."""
    if section not in ("one_process", "all_cores"):
        raise ValueError(f"unknown section {section!r}: choose one_process and/or all_cores")
    rows = []
    w = 1 if section == "one_process" else workers
    # The rows are deterministic for a given split into workers and batches (another split
    # batches the policy's matmuls differently: last-bit differences): one untimed run per
    # section fixes the steps of every rollout for the raw side (and builds the variations in
    # this process, for both sides).
    _, first = run_eval(policy, names, args.rollouts, args.horizon, w, args.envs_per_worker, pool)
    steps = {(r.task, r.variation_index): int(r.steps) for r in first.itertuples()}
    jobs = [(t, k, steps[(t, k)]) for t in names for k in range(args.rollouts)]
    success, mean_steps = float(first["success"].mean()), float(first["steps"].mean())
    print(f"{section}: policy success {success:.2f}, {mean_steps:.0f} steps per rollout on average", flush=True)
    batch = eval_batch(len(jobs), min(w, len(jobs)), args.horizon, args.envs_per_worker)
    for _ in range(0 if args.quick else args.warmup):
        run_raw(jobs, w)
        run_raw(jobs, w, batch)
        run_eval(policy, names, args.rollouts, args.horizon, w, args.envs_per_worker, pool)
    for rep in range(args.reps):
        raw = run_raw(jobs, w)
        raw_il = run_raw(jobs, w, batch)
        evl, df = run_eval(policy, names, args.rollouts, args.horizon, w, args.envs_per_worker, pool)
        if not df[["steps", "success"]].equals(first[["steps", "success"]]):
            raise RuntimeError(f"{section}: the evaluator's rollouts differ from the first run's")
        rows.append(
            {
                "section": section,
                "rep": rep,
                "raw_steps_per_s": raw,
                "eval_steps_per_s": evl,
                "ratio": evl / raw,
                "raw_interleaved_steps_per_s": raw_il,
                "ratio_interleaved": evl / raw_il,
                "success_rate": success,
                "mean_steps": mean_steps,
            }
        )
        print(
            f"{section:12s} rep {rep}: raw {raw:8.0f}  raw interleaved {raw_il:8.0f}  eval {evl:8.0f} steps/s  "
            f"eval/raw {evl / raw:.3f}  eval/raw interleaved {evl / raw_il:.3f}",
            flush=True,
        )
    sec = [r for r in rows if r["section"] == section and r["rep"] != "median"]
    rows.append(
        {
            "section": section,
            "rep": "median",
            "raw_steps_per_s": float(np.median([r["raw_steps_per_s"] for r in sec])),
            "eval_steps_per_s": float(np.median([r["eval_steps_per_s"] for r in sec])),
            "ratio": float(np.median([r["ratio"] for r in sec])),
            "raw_interleaved_steps_per_s": float(np.median([r["raw_interleaved_steps_per_s"] for r in sec])),
            "ratio_interleaved": float(np.median([r["ratio_interleaved"] for r in sec])),
            "success_rate": success,
            "mean_steps": mean_steps,
        }
    )
    med = rows[-1]
    print(
        f"{section:12s} median eval/raw {med['ratio']:.3f}  eval/raw interleaved {med['ratio_interleaved']:.3f}",
        flush=True,
    )
    return rows


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
    parser.add_argument("--demos", type=int, default=10, help="expert demonstrations per task to train the policy on")
    parser.add_argument("--train-steps", type=int, default=3000, help="AdamW steps of behaviour cloning")
    parser.add_argument(
        "--cache",
        type=Path,
        default=Path(tempfile.gettempdir()) / "tar-rl-bench-eval",
        help="folder for the demonstrations and the trained policy",
    )
    parser.add_argument("--quick", action="store_true", help="a smoke run: 2 tasks, 2 rollouts, horizon 50, 1 rep")
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "results" / "eval.csv")
    args = parser.parse_args(argv)
    if args.quick:
        args.tasks, args.rollouts, args.horizon, args.reps = "reach,drawer-close", 2, 50, 1
        args.demos, args.train_steps = 2, 50

    import torch

    from benchmarks.common import git_commit
    from tar_rl.collectors.metaworld import tasks
    from tar_rl.collectors.metaworld.evaluate import RolloutPool, available_cores

    torch.set_num_threads(1)
    warnings.filterwarnings("ignore", message="The name target_actor_network_params")  # torchrl's BCLoss
    names = tasks.resolve_tasks(args.tasks)
    workers = args.workers or available_cores()
    policy = trained_policy(names, args.demos, args.train_steps, args.cache)
    rows = []
    with RolloutPool() as pool:  # the evaluator's workers and envs, kept between rounds as in a training job
        for section in args.sections.split(","):
            rows += run_section(section, args, names, workers, policy, pool)
    for r in rows:
        r.update(
            tasks=",".join(names),
            rollouts_per_task=args.rollouts,
            horizon=args.horizon,
            workers=workers if r["section"] == "all_cores" else 1,
            envs_per_worker=args.envs_per_worker or "default",
            commit=git_commit(),
        )
    df = pd.DataFrame(rows, columns=COLUMNS)
    write_csv_atomic(df, args.out)
    print(f"wrote {args.out}")
    return df


if __name__ == "__main__":
    main()
