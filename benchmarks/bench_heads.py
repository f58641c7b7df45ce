"""Speed of every registered policy head: training throughput under uniform and TAR, inference latency.

Run from the repository root::

    .venv/bin/python -m benchmarks.bench_heads [--quick] [--device cpu|cuda] [--heads a,b] [--out PATH]

Every head in ``tar_rl.policies.POLICIES`` (a head registered later appears without change here)
is built from its config defaults with ``DataInfo(chunk_horizon=8, history=2)`` (the data
defaults) and measured in two sections, each timed round-robin (every round times every variant
once, in a fresh random order, so that machine noise hits all variants alike); medians and IQRs
over rounds are reported.

* ``train_step``: one training step (``TARLoss`` forward on a fixed synthetic ``[B, L]`` batch
  (default ``[64, 16]``) already on the device, backward, ``AdamW.step()``, ``zero_grad()``) for
  every head under ``uniform`` and ``tar`` (TAR at full strength from the first step); each
  (head, weighting) trains its own copy built from the same seed. On CUDA the step runs under
  bfloat16 autocast (as the recipe does; ``--no-amp`` to disable) and ends with a synchronise.
  Reported per head: ms per step and segments/s (``B / time``), their ratio to ``mlp``, and the TAR
  overhead ``tar / uniform`` (ratio of medians, and the median of the per-round ratio, "paired").
  ``tar`` uses ``TARLoss``'s default ``compile_weights="auto"`` (the weighting compiled on CUDA
  with triton, eager on the CPU; ``--compile-weights`` to choose); where that compiles, a third
  variant ``tar_eager`` (the weighting eager) is timed in the same rounds, so one run shows both.
* ``inference``: one batched environment step of ``N`` envs (default 16) through the head's
  actor (for chunked heads the ``ChunkedActor`` with its default execution), as the evaluator
  calls it: a fixed sequence of observations, the first call starting every rollout
  (``is_init``), the later ones continuing them; ms per call and the ratio to ``mlp``.

The synthetic batch carries every dataset entry (``observation``, ``task_id``, ``action``,
``action_chunk`` + ``action_chunk_valid``, ``observation_history`` + ``observation_history_valid``,
``("collector", "mask")``); a quarter of the segments end early (padding, chunks running past the
end, history before the start), as in ``benchmarks/bench_objective.py``; it and the training step are built by
:mod:`benchmarks.head_steps`, which the ``--against`` workers run.

Output: a table on stdout and one tidy CSV (default ``benchmarks/results/heads.csv``), one row per
(section, head, variant) with columns ``section, head, variant, median, iqr, unit,
ratio_to_baseline, baseline, n, batch, device, torch, threads, commit``. Sections:
``train_step`` (ms/step, baseline ``mlp``), ``throughput`` (segments/s, baseline ``mlp``),
``tar_overhead`` (``median``/``iqr``: the paired ratio tar / uniform; ``ratio_to_baseline``: the
ratio of medians; baseline ``uniform``), ``inference`` (ms per batched env step, baseline ``mlp``).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pandas as pd
import torch
from tensordict import TensorDict

from benchmarks.common import SUMMARY_COLUMNS, git_commit, interleaved, median_iqr
from benchmarks.head_steps import N_TASKS, OBS_DIM, build, make_batch, make_step, sync
from tar_rl.io import write_csv_atomic
from tar_rl.objectives import compiles_weights
from tar_rl.policies import POLICIES

REPO = Path(__file__).resolve().parent.parent
DEFAULT_OUT = REPO / "benchmarks" / "results" / "heads.csv"
DEFAULT_AGAINST_OUT = REPO / "benchmarks" / "results" / "heads_against.csv"
STEPS = REPO / "benchmarks" / "head_steps.py"  # run by its path by the --against workers (its docstring says why)

OBJECTIVES = ("uniform", "tar")
BASELINE_HEAD = "mlp"
TAR_TARGET = 1.02
COLUMNS = [
    "section",
    "head",
    "variant",
    *SUMMARY_COLUMNS,
    "batch",
    "device",
    "torch",
    "threads",
    "commit",
]


# ---------------------------------------------------------------------------------------------
# Inference (the training step: benchmarks.head_steps)
# ---------------------------------------------------------------------------------------------


def make_inference(head: str, n_envs: int, calls: int, device: torch.device, seed: int):
    """One batched env step per call of ``head``'s actor; rollouts restart every ``calls`` calls."""
    actor = build(head, seed).actor.to(device).eval()
    g = torch.Generator().manual_seed(seed + 1)
    obs = (torch.randn(calls, n_envs, OBS_DIM, generator=g).cumsum(0) * 0.1).to(device)
    task = torch.randint(N_TASKS, (n_envs,), generator=g).to(device)
    inputs = [
        TensorDict(
            {"observation": obs[i], "task_id": task, "is_init": torch.full((n_envs, 1), i == 0, device=device)},
            [n_envs],
        )
        for i in range(calls)
    ]
    state = {"i": 0}

    def call() -> None:
        td = inputs[state["i"] % calls].clone()
        state["i"] += 1
        with torch.no_grad():
            actor(td)
        sync(device)

    return call


# ---------------------------------------------------------------------------------------------
# Timing
# ---------------------------------------------------------------------------------------------


def bench_train(heads, args, device) -> list[dict]:
    batch = make_batch(args.batch, args.slice_len, args.seed).to(device)
    steps: dict[tuple[str, str], Callable[[], None]] = {}
    # uniform, tar and, where tar's weighting is compiled, tar_eager
    names = OBJECTIVES + (("tar_eager",) if compiles_weights(args.compile_weights, device) else ())
    for head in heads:
        for variant in names:
            objective, mode = ("tar", "never") if variant == "tar_eager" else (variant, args.compile_weights)
            steps[head, variant] = make_step(head, objective, batch, device, args.amp, args.seed, mode)
    for step in steps.values():
        for _ in range(args.warmup):
            step()
    times = interleaved(steps, args.reps, args.seed)

    base = BASELINE_HEAD if BASELINE_HEAD in heads else heads[0]
    ms = {k: median_iqr(t * 1e3) for k, t in times.items()}
    rate = {k: median_iqr(args.batch / t) for k, t in times.items()}
    rows = []
    for head in heads:
        for objective in names:
            key = (head, objective)
            common = dict(head=head, variant=objective, baseline=base, n=args.reps)
            med, iqr = ms[key]
            rows.append(
                dict(
                    section="train_step",
                    median=med,
                    iqr=iqr,
                    unit="ms/step",
                    ratio_to_baseline=med / ms[base, objective][0],
                    **common,
                )
            )
            med, iqr = rate[key]
            rows.append(
                dict(
                    section="throughput",
                    median=med,
                    iqr=iqr,
                    unit="segments/s",
                    ratio_to_baseline=med / rate[base, objective][0],
                    **common,
                )
            )
        for variant in names[1:]:
            med, iqr = median_iqr(times[head, variant] / times[head, "uniform"])
            rows.append(
                dict(
                    section="tar_overhead",
                    head=head,
                    variant=variant,
                    median=med,
                    iqr=iqr,
                    unit="ratio",
                    ratio_to_baseline=ms[head, variant][0] / ms[head, "uniform"][0],
                    baseline="uniform",
                    n=args.reps,
                )
            )
    return rows


def bench_inference(heads, args, device) -> list[dict]:
    calls = {head: make_inference(head, args.envs, args.calls, device, args.seed) for head in heads}
    for call in calls.values():
        for _ in range(min(args.calls, 5)):
            call()
    times = interleaved(calls, args.calls, args.seed + 1)
    base = BASELINE_HEAD if BASELINE_HEAD in heads else heads[0]
    ms = {k: median_iqr(t * 1e3) for k, t in times.items()}
    rows = []
    for head in heads:
        cfg = POLICIES[head].config()
        med, iqr = ms[head]
        rows.append(
            dict(
                section="inference",
                head=head,
                variant=getattr(cfg, "execution", "step"),
                median=med,
                iqr=iqr,
                unit="ms/env-step",
                ratio_to_baseline=med / ms[base][0],
                baseline=base,
                n=args.calls,
            )
        )
    return rows


# ---------------------------------------------------------------------------------------------
# Against another commit: the same training step in two checkouts, side by side
# ---------------------------------------------------------------------------------------------


class Worker:
    """A worker process (:mod:`benchmarks.head_steps`) importing the ``tar_rl`` of ``tree`` (a checkout of this
    repository)."""

    def __init__(self, tree: Path, args: argparse.Namespace):
        import json
        import subprocess

        self._json = json
        flags = ["--device", args.device, "--threads", str(args.threads), "--batch", str(args.batch)]
        flags += ["--slice-len", str(args.slice_len), "--seed", str(args.seed), "--warmup", str(args.warmup)]
        flags += [] if args.amp else ["--no-amp"]
        env = {**os.environ, "PYTHONPATH": str(tree)}
        self.proc = subprocess.Popen(
            [sys.executable, "-P", str(STEPS), *flags],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
            env=env,
        )
        loaded = Path(self._read()["tar_rl"])
        if loaded != (tree / "tar_rl").resolve():
            self.close()
            raise RuntimeError(f"the worker for {tree} imported tar_rl from {loaded}")

    def _read(self) -> dict:
        line = self.proc.stdout.readline()
        if not line:
            raise RuntimeError(f"a benchmark worker exited with code {self.proc.wait()}")
        return self._json.loads(line)

    def time(self, head: str, compiled: bool, calls: int) -> float:
        self.proc.stdin.write(self._json.dumps({"head": head, "compiled": compiled, "calls": calls}) + "\n")
        self.proc.stdin.flush()
        return float(self._read()["seconds"])

    def close(self) -> None:
        """End the worker (it exits at the end of its input) and close its pipes."""
        self.proc.stdin.close()
        self.proc.wait()
        self.proc.stdout.close()


# variant -> (checkout, compiled attention): the commit measured against, this checkout, this checkout compiled
AGAINST_VARIANTS = {"before": ("against", False), "now": ("here", False), "now_compiled": ("here", True)}


def bench_against(heads, args) -> list[dict]:
    """Uniform training steps of every head at ``args.against`` and here (eager and compiled), interleaved.

    The commit is checked out into a temporary git worktree; one worker process per checkout
    builds each head from the same seed on the same batch. Every round times every (head,
    variant) once, in a fresh random order; each sample is the mean of ``args.inner`` steps.
    Rows: section ``against``, ms per step, ``ratio_to_baseline`` = ``before``'s median / this
    variant's (the speed-up), baseline ``before``.
    """
    import subprocess
    import tempfile

    import numpy as np

    compiled_heads = [h for h in heads if "compile" in {f.name for f in dataclasses.fields(POLICIES[h].config)}]
    keys = [(h, v) for h in heads for v in AGAINST_VARIANTS if v != "now_compiled" or h in compiled_heads]
    with tempfile.TemporaryDirectory() as tmp:
        tree = Path(tmp) / "tree"
        subprocess.run(
            ["git", "worktree", "add", "--detach", str(tree), args.against], cwd=REPO, check=True, capture_output=True
        )
        workers: dict[str, Worker] = {}
        try:
            workers = {"against": Worker(tree, args), "here": Worker(REPO, args)}
            for head, variant in keys:  # build, compile and warm up every variant before timing any
                where, compiled = AGAINST_VARIANTS[variant]
                workers[where].time(head, compiled, 1)
            rng = np.random.default_rng(args.seed)
            times = {key: np.empty(args.reps) for key in keys}
            for r in range(args.reps):
                for i in rng.permutation(len(keys)):
                    head, variant = keys[i]
                    where, compiled = AGAINST_VARIANTS[variant]
                    times[head, variant][r] = workers[where].time(head, compiled, args.inner)
        finally:
            for worker in workers.values():
                worker.close()
            subprocess.run(["git", "worktree", "remove", "--force", str(tree)], cwd=REPO, capture_output=True)
    rows = []
    for head, variant in keys:
        med, iqr = median_iqr(times[head, variant] * 1e3)
        before = median_iqr(times[head, "before"] * 1e3)[0]
        rows.append(
            dict(
                section="against",
                head=head,
                variant=variant,
                median=med,
                iqr=iqr,
                unit="ms/step",
                ratio_to_baseline=before / med,
                baseline=f"before ({args.against})",
                n=args.reps,
            )
        )
    return rows


# ---------------------------------------------------------------------------------------------
# Output
# ---------------------------------------------------------------------------------------------


def _fmt(x: float, digits: int = 2) -> str:
    return "n/a" if not math.isfinite(x) else f"{x:.{digits}f}"


def render(df: pd.DataFrame, header: list[str]) -> str:
    lines = [*header, ""]
    train = df[df.section == "train_step"].set_index(["head", "variant"])
    rate = df[df.section == "throughput"].set_index(["head", "variant"])
    over = df[(df.section == "tar_overhead") & (df.variant == "tar")].set_index("head")
    eager = df[(df.section == "tar_overhead") & (df.variant == "tar_eager")].set_index("head")
    infer = df[df.section == "inference"].set_index("head")
    heads = list(dict.fromkeys(df["head"]))
    lines.append(
        f"{'head':<16}{'uniform ms':>11}{'tar ms':>9}{'/mlp':>7}{'seg/s unif':>12}{'seg/s tar':>11}"
        f"{'tar/unif':>10}{'paired [IQR]':>18}{'infer ms':>10}{'/mlp':>7}"
    )
    for head in heads:
        u, t = train.loc[(head, "uniform")], train.loc[(head, "tar")]
        o, i = over.loc[head], infer.loc[head]
        paired = f"{o['median']:.4f} [{o['iqr']:.4f}]"
        lines.append(
            f"{head:<16}{_fmt(u['median']):>11}{_fmt(t['median']):>9}{_fmt(u['ratio_to_baseline']):>7}"
            f"{_fmt(rate.loc[(head, 'uniform'), 'median'], 0):>12}{_fmt(rate.loc[(head, 'tar'), 'median'], 0):>11}"
            f"{_fmt(o['ratio_to_baseline'], 4):>10}{paired:>18}{_fmt(i['median']):>10}{_fmt(i['ratio_to_baseline']):>7}"
        )
    lines.append("")
    for head in heads:
        if head == BASELINE_HEAD:
            continue
        p = over.loc[head, "median"]
        verdict = "meets" if p <= TAR_TARGET else "misses"
        without = f" (weighting eager: {eager.loc[head, 'median']:.4f})" if head in eager.index else ""
        lines.append(f"TAR overhead {head}: paired {p:.4f} -> {verdict} the target <= {TAR_TARGET}{without}")
    return "\n".join(lines)


def render_against(df: pd.DataFrame, header: list[str]) -> str:
    lines = [*header, ""]
    table = df.set_index(["head", "variant"])
    variants = [v for v in AGAINST_VARIANTS if v in set(df.variant)]
    lines.append(f"{'head':<16}" + "".join(f"{v + ' ms':>18}{'speed-up':>10}" for v in variants))
    for head in dict.fromkeys(df["head"]):
        cells = ""
        for v in variants:
            if (head, v) in table.index:
                row = table.loc[(head, v)]
                cells += f"{_fmt(row['median']):>18}{_fmt(row['ratio_to_baseline']):>10}"
            else:
                cells += f"{'-':>18}{'-':>10}"
        lines.append(f"{head:<16}{cells}")
    return "\n".join(lines)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--quick", action="store_true", help="few repetitions: a smoke test")
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"], help="where to train and infer (default cpu)")
    p.add_argument("--heads", default="", help="comma-separated heads (default: every registered head)")
    p.add_argument("--out", type=Path, default=None, help=f"CSV path (default {DEFAULT_OUT})")
    p.add_argument("--threads", type=int, default=1, help="torch.set_num_threads (default 1, for stable timings)")
    p.add_argument("--batch", type=int, default=64, help="segments per training batch B (default 64)")
    p.add_argument("--slice-len", type=int, default=16, help="steps per segment L (default 16)")
    p.add_argument("--envs", type=int, default=16, help="envs N per inference call (default 16)")
    p.add_argument("--reps", type=int, default=None, help="interleaved training rounds (default 30; quick 3)")
    p.add_argument("--warmup", type=int, default=None, help="warm-up steps per variant (default 3; quick 1)")
    p.add_argument("--calls", type=int, default=None, help="interleaved inference rounds (default 200; quick 10)")
    p.add_argument("--amp", action=argparse.BooleanOptionalAction, default=True, help="bf16 autocast on CUDA")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--against",
        default=None,
        metavar="REV",
        help="instead of the sections above: uniform training steps at commit REV and here (eager and compiled "
        f"attention), side by side; CSV default {DEFAULT_AGAINST_OUT}",
    )
    p.add_argument("--inner", type=int, default=2, help="--against: training steps per sample (default 2)")
    p.add_argument(
        "--compile-weights",
        default="auto",
        choices=["auto", "always", "never"],
        help="TARLoss(compile_weights=...) of the tar variant (default auto: compiled on CUDA with triton)",
    )
    args = p.parse_args(argv)
    args.reps = args.reps if args.reps is not None else (3 if args.quick else 30)
    args.warmup = args.warmup if args.warmup is not None else (1 if args.quick else 3)
    args.calls = args.calls if args.calls is not None else (10 if args.quick else 200)
    sizes = (args.threads, args.batch, args.slice_len, args.envs, args.reps, args.calls, args.inner)
    if min(sizes) < 1 or args.warmup < 0:
        p.error("--threads, --batch, --slice-len, --envs, --reps, --calls and --inner must be >= 1, --warmup >= 0")
    args.out = args.out or (DEFAULT_AGAINST_OUT if args.against else DEFAULT_OUT)
    heads = [h.strip() for h in args.heads.split(",") if h.strip()] or list(POLICIES)
    unknown = [h for h in heads if h not in POLICIES]
    if unknown:
        p.error(f"unknown head(s) {unknown}; registered: {sorted(POLICIES)}")
    args.heads = heads
    if args.device == "cuda" and not torch.cuda.is_available():
        p.error("--device cuda: CUDA is not available here")
    return args


def main(argv: list[str] | None = None) -> pd.DataFrame:
    args = parse_args(argv)
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    commit = git_commit()
    started = time.perf_counter()

    if args.against:
        rows = bench_against(args.heads, args)
    else:
        rows = bench_train(args.heads, args, device) + bench_inference(args.heads, args, device)
    df = pd.DataFrame(rows)
    df["batch"] = f"[{args.batch}, {args.slice_len}]"
    df["device"] = torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"
    df["torch"] = torch.__version__
    df["threads"] = torch.get_num_threads()
    df["commit"] = commit
    df = df[COLUMNS]
    write_csv_atomic(df, args.out)

    amp = " bf16 autocast" if args.amp and device.type == "cuda" else ""
    header = [
        f"bench_heads: torch {torch.__version__}, device {df['device'].iloc[0]}{amp}, threads "
        f"{torch.get_num_threads()}, CPUs {os.cpu_count()}, commit {commit}{' (--quick)' if args.quick else ''}",
        f"training step: batch [{args.batch}, {args.slice_len}], {args.reps} interleaved rounds after {args.warmup} "
        f"warm-up steps; inference: N = {args.envs} envs, {args.calls} interleaved calls; medians over rounds",
        "paired = median over rounds of the within-round ratio tar / uniform",
    ]
    if args.against:
        header[1] = (
            f"uniform training step, batch [{args.batch}, {args.slice_len}], {args.reps} interleaved rounds of "
            f"{args.inner} steps after {args.warmup} warm-up steps, at {args.against} (before) and here (now)"
        )
        header[2] = "speed-up = before's median / the variant's"
    print(render_against(df, header) if args.against else render(df, header))
    print(f"\nwrote {args.out} ({len(df)} rows) in {time.perf_counter() - started:.0f} s")
    return df


if __name__ == "__main__":
    main()
