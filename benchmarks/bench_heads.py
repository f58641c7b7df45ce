"""Speed of every registered policy head: training throughput under uniform and TAR, inference latency.

Run from the repository root::

    .venv/bin/python benchmarks/bench_heads.py [--quick] [--device cpu|cuda] [--heads a,b] [--out PATH]

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
end, history before the start), as in ``benchmarks/bench_objective.py``.

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
import warnings
from collections.abc import Callable
from pathlib import Path

import pandas as pd
import torch
from tensordict import TensorDict

from tar_rl.io import write_csv_atomic
from tar_rl.objectives import TARLoss, compiles_weights
from tar_rl.policies import POLICIES, DataInfo, build_policy

sys.path.insert(0, str(Path(__file__).resolve().parent))  # common.py beside this script
from common import SUMMARY_COLUMNS, git_commit, interleaved, median_iqr

REPO = Path(__file__).resolve().parent.parent
DEFAULT_OUT = REPO / "benchmarks" / "results" / "heads.csv"
DEFAULT_AGAINST_OUT = REPO / "benchmarks" / "results" / "heads_against.csv"

OBS_DIM, ACTION_DIM, N_TASKS = 39, 4, 50
CHUNK_HORIZON, HISTORY = 8, 2
PAD_SEGMENT_FRACTION = 0.25
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
# Data and variants
# ---------------------------------------------------------------------------------------------


def make_batch(batch: int, slice_len: int, seed: int = 0) -> TensorDict:
    """A ``[B, L]`` batch with every dataset entry, as the recipe's segment sampler returns it.

    Episodes are random walks; a quarter of the segments end early (padding repeats the last
    real step, ``("collector", "mask")`` False there); chunks and histories are cut from the
    episode with their validity flags (past the end: the last action repeated; before the start:
    the first observation repeated).
    """
    g = torch.Generator().manual_seed(seed)
    total = slice_len + CHUNK_HORIZON + HISTORY
    obs = torch.randn(batch, total, OBS_DIM, generator=g).cumsum(1) * 0.1
    act = (torch.rand(batch, total, ACTION_DIM, generator=g) * 2 - 1).clamp(-1, 1)
    task = torch.randint(N_TASKS, (batch,), generator=g)
    short = torch.rand(batch, generator=g) < PAD_SEGMENT_FRACTION
    length = torch.where(short, torch.randint(2, slice_len, (batch,), generator=g), slice_len)
    start = torch.where(torch.rand(batch, generator=g) < 0.25, 0, HISTORY - 1)  # some segments open an episode
    steps = torch.arange(slice_len)
    mask = steps[None] < length[:, None]
    last = torch.minimum(steps[None], (length - 1)[:, None])  # [B, L] padding repeats the last real step
    t = start[:, None] + last  # time index in the episode buffer
    extra = torch.where(short, 0, torch.randint(0, CHUNK_HORIZON + 1, (batch,), generator=g))
    end = start + length - 1 + extra  # the episode's last real step: short segments end with their episode

    def take(x, idx):
        return x[torch.arange(batch)[:, None, None], idx]

    h_idx = t[..., None] - torch.arange(HISTORY - 1, -1, -1)  # oldest first
    h_valid = h_idx >= 0
    history = take(obs, h_idx.clamp_min(0))
    c_idx = t[..., None] + torch.arange(CHUNK_HORIZON)
    c_valid = c_idx <= end[:, None, None]
    chunk = take(act, torch.minimum(c_idx, end[:, None, None]))
    return TensorDict(
        {
            "observation": take(obs, t[..., None])[:, :, 0],
            "task_id": task[:, None].expand(batch, slice_len).clone(),
            "action": take(act, t[..., None])[:, :, 0],
            "action_chunk": chunk,
            "action_chunk_valid": c_valid,
            "observation_history": history,
            "observation_history_valid": h_valid,
            ("collector", "mask"): mask,
        },
        [batch, slice_len],
    )


def data_info() -> DataInfo:
    return DataInfo(obs_dim=OBS_DIM, action_dim=ACTION_DIM, chunk_horizon=CHUNK_HORIZON, history=HISTORY)


def build(head: str, seed: int, compiled: bool = False):
    """``head`` at its config defaults (``compiled``: with ``compile=True``, the compiled attention)."""
    torch.manual_seed(seed)
    cfg = POLICIES[head].config()
    if compiled:
        cfg = dataclasses.replace(cfg, compile=True)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", "The name target_actor_network_params", UserWarning)
        return build_policy(cfg, data_info())


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def make_step(
    head: str,
    objective: str,
    batch: TensorDict,
    device: torch.device,
    amp: bool,
    seed: int,
    compile_weights: str = "auto",
    compiled: bool = False,
):
    """One training step of ``head`` under ``objective`` on its own copy and its own AdamW."""
    policy = build(head, seed, compiled)
    loss = TARLoss(policy.loss, objective, loss_key=policy.loss_key, compile_weights=compile_weights)
    if policy.event_valid is not None:
        loss.set_keys(event_valid=policy.event_valid)
    loss = loss.to(device)
    optimizer = torch.optim.AdamW(loss.parameters(), lr=1e-4)
    use_amp = amp and device.type == "cuda"

    def step() -> None:
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=use_amp):
            out = loss(batch)
        out["loss_tar"].backward()
        optimizer.step()
        optimizer.zero_grad(set_to_none=True)
        _sync(device)

    return step


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
        _sync(device)

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


def serve(args: argparse.Namespace) -> None:
    """Worker mode (``--serve``): time training steps on request, with whatever ``tar_rl`` this process imports.

    Reads one JSON request per line on stdin, ``{"head": ..., "compiled": bool, "calls": n}``, and
    answers one JSON line, ``{"seconds": s}``, the mean time of ``n`` uniform training steps of the
    head on its own copy (built, and warmed up ``args.warmup`` steps, at its first request). The
    first line it writes names the ``tar_rl`` package it imported.
    """
    import json

    import tar_rl

    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    batch = make_batch(args.batch, args.slice_len, args.seed).to(device)
    steps: dict[tuple[str, bool], Callable[[], None]] = {}
    print(json.dumps({"tar_rl": str(Path(tar_rl.__file__).resolve().parent)}), flush=True)
    for line in sys.stdin:
        request = json.loads(line)
        key = (request["head"], bool(request["compiled"]))
        if key not in steps:
            steps[key] = make_step(key[0], "uniform", batch, device, args.amp, args.seed, compiled=key[1])
            for _ in range(args.warmup):
                steps[key]()
        start = time.perf_counter()
        for _ in range(request["calls"]):
            steps[key]()
        print(json.dumps({"seconds": (time.perf_counter() - start) / request["calls"]}), flush=True)


class _Worker:
    """A ``--serve`` process importing the ``tar_rl`` of ``tree`` (a checkout of this repository)."""

    def __init__(self, tree: Path, args: argparse.Namespace):
        import json
        import subprocess

        self._json = json
        flags = ["--device", args.device, "--threads", str(args.threads), "--batch", str(args.batch)]
        flags += ["--slice-len", str(args.slice_len), "--seed", str(args.seed), "--warmup", str(args.warmup)]
        flags += [] if args.amp else ["--no-amp"]
        env = {**os.environ, "PYTHONPATH": str(tree)}
        self.proc = subprocess.Popen(
            [sys.executable, str(Path(__file__).resolve()), "--serve", *flags],
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
        if self.proc.poll() is None:
            self.proc.stdin.close()
            self.proc.wait()


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
        workers: dict[str, _Worker] = {}
        try:
            workers = {"against": _Worker(tree, args), "here": _Worker(REPO, args)}
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
    p.add_argument("--serve", action="store_true", help=argparse.SUPPRESS)  # a worker of --against
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
    if args.serve:
        serve(args)
        return pd.DataFrame()
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
