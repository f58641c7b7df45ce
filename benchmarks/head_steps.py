"""The heads' synthetic batch and training step, shared by ``benchmarks.bench_heads`` and its ``--against`` workers.

A worker (:func:`serve`) times training steps with whatever ``tar_rl`` its process imports: ``bench_heads --against
REV`` runs this file by its path once per checkout, with that checkout first on ``PYTHONPATH``::

    PYTHONPATH=CHECKOUT python -P benchmarks/head_steps.py [--device cpu|cuda] [--threads 1] [--batch 64] ...

so it imports nothing from ``benchmarks`` (the other checkout's ``benchmarks`` would shadow this one's), only
``tar_rl`` and the libraries.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
import warnings
from collections.abc import Callable
from pathlib import Path

import torch
from tensordict import TensorDict

from tar_rl.objectives import TARLoss
from tar_rl.policies import POLICIES, DataInfo, build_policy

__all__ = ["CHUNK_HORIZON", "HISTORY", "N_TASKS", "OBS_DIM", "build", "make_batch", "make_step", "serve", "sync"]

OBS_DIM, ACTION_DIM, N_TASKS = 39, 4, 50
CHUNK_HORIZON, HISTORY = 8, 2
PAD_SEGMENT_FRACTION = 0.25


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


def sync(device: torch.device) -> None:
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
        sync(device)

    return step


def serve(args: argparse.Namespace) -> None:
    """Time training steps on request, with whatever ``tar_rl`` this process imports (``args``: :func:`main`'s).

    Reads one JSON request per line on stdin, ``{"head": ..., "compiled": bool, "calls": n}``, and
    answers one JSON line, ``{"seconds": s}``, the mean time of ``n`` uniform training steps of the
    head on its own copy (built, and warmed up ``args.warmup`` steps, at its first request). The
    first line it writes names the ``tar_rl`` package it imported.
    """
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


def main(argv: list[str] | None = None) -> None:
    """A worker: the training step's settings as options, the requests on stdin (:func:`serve`)."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--slice-len", type=int, default=16)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--warmup", type=int, default=3)
    p.add_argument("--amp", action=argparse.BooleanOptionalAction, default=True)
    serve(p.parse_args(argv))


if __name__ == "__main__":
    main()
