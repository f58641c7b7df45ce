"""Speed of the TAR objective, as ratios measured side by side in one run.

Run from the repository root::

    .venv/bin/python -m benchmarks.bench_objective [--quick] [--out PATH] [--threads N]

Two sections, each timed round-robin (every repetition times every variant once, in a fresh
random order) so that machine noise hits all variants alike; medians and IQRs are reported.

* ``train_step``: one full training step (forward of the loss on a fixed ``[256, 16]`` batch
  already in memory, backward, ``AdamW.step()``, ``zero_grad()``) of the same 3 x 256 ReLU MLP
  policy, for ``bc_mean`` (torchrl's ``BCLoss`` with its mean reduction, the TorchRL
  baseline), ``uniform`` (``TARLoss(inner, "uniform")``), ``tar`` (``TARLoss(inner, "tar")``,
  paper cap), ``tar_exact`` (``cap="exact"``) and the baselines from the literature ``tilted``,
  ``truncate``, ``keyframe``, ``focal``, ``dro_time`` and TAR's element variants ``tar_arm``,
  ``tar_dimnorm`` (``TARLoss(inner, name)``, default parameters; ``dro_time`` updates its group weights every
  step). Every
  variant trains its own deep copy of one seeded network with its own optimizer. Besides the
  ratio of medians, the per-repetition ratio ``time_variant[r] / time_baseline[r]`` (both timed
  in the same round) is reported as ``train_step_paired``: it is less noisy.
* ``weighting``: the weighting function alone on ``[256, 16]`` float32 losses: a plain masked
  mean (the baseline), ``tar_weights`` with the paper and the exact cap, eager and under
  ``torch.compile`` (inductor), and the baselines' weight functions (``tilted_weights``,
  ``truncate_weights``, ``keyframe_weights``, ``focal_weights``; for ``dro_time`` the registered
  function as ``TARLoss`` calls it, from the steps' positions in their episodes: binning, the update
  of the group weights and the weights) and the element variants (``tar_arm_weights``,
  ``tar_dimnorm_weights``, on ``[256, 16, 4]`` per-element losses), eager. Each timing sample is the mean of
  ``--calls`` calls.

Output: a table on stdout and one tidy CSV (default ``benchmarks/results/objective.csv``), one
row per (section, variant, baseline) with columns ``section, variant, median, iqr, unit,
ratio_to_baseline, baseline, n, torch, threads, commit``. In ``train_step`` and ``weighting``
``median``/``iqr`` are times and ``ratio_to_baseline`` is the ratio of medians; in
``train_step_paired`` ``median``/``iqr`` are those of the per-repetition ratios. Rows of a
compiled variant that could not be compiled have ``median`` NaN and ``unit`` ``"unavailable"``.
"""

from __future__ import annotations

import argparse
import copy
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
from tensordict.nn import TensorDictModule
from torch import Tensor
from torchrl.objectives import BCLoss

from benchmarks.common import SUMMARY_COLUMNS, git_commit, interleaved, median_iqr
from tar_rl.io import write_csv_atomic
from tar_rl.objectives import (
    WEIGHTINGS,
    TARLoss,
    TARParams,
    focal_weights,
    keyframe_weights,
    tar_arm_weights,
    tar_dimnorm_weights,
    tar_weights,
    tilted_weights,
    truncate_weights,
)

REPO = Path(__file__).resolve().parent.parent
DEFAULT_OUT = REPO / "benchmarks" / "results" / "objective.csv"

BATCH, SLICE_LEN = 256, 16
OBS_DIM, N_TASKS, ACTION_DIM, HIDDEN, DEPTH = 39, 10, 4, 256, 3
PAD_SEGMENT_FRACTION = 0.25  # segments that end early; with lengths in [4, 15] ~10% of steps are padding

# the weightings from the literature, by registry name
BASELINES = ("tilted", "truncate", "keyframe", "focal", "dro_time")
ELEMENT = ("tar_arm", "tar_dimnorm")  # TAR's element variants, by registry name
STEP_VARIANTS = ("bc_mean", "uniform", "tar", "tar_exact", *BASELINES, *ELEMENT)
STEP_BASELINES = ("uniform", "bc_mean")
WEIGHT_BASELINE = "masked_mean"
COMPILED = {"tar_paper_compiled": "tar_paper", "tar_exact_compiled": "tar_exact"}
WEIGHT_VARIANTS = ("masked_mean", "tar_paper", "tar_exact", *COMPILED, *BASELINES, *ELEMENT)
COLUMNS = [
    "section",
    "variant",
    *SUMMARY_COLUMNS,
    "torch",
    "threads",
    "commit",
]

# torchrl 0.14.1's BCLoss warns about its own annotations on every construction.
_BCLOSS_WARNING = "The name target_actor_network_params wasn't part of the annotations"


# ---------------------------------------------------------------------------------------------
# Data and models
# ---------------------------------------------------------------------------------------------


def make_batch(seed: int = 0) -> TensorDict:
    """A ``[256, 16]`` batch of segments as ``SliceSampler(pad_output=True)`` returns it, reshaped.

    Observations are 39 features plus a one-hot task id (constant within a segment); actions
    lie in ``[-1, 1]``. A quarter of the segments end early (length 4..15); their tail is
    padding that repeats the last real step, with ``("collector", "mask")`` False there. Each
    segment lies in an episode of 40..199 steps (``step``, ``episode_length``; a short segment
    ends with its episode), for ``dro_time``.
    """
    g = torch.Generator().manual_seed(seed)
    features = torch.randn(BATCH, SLICE_LEN, OBS_DIM, generator=g)
    task = torch.randint(N_TASKS, (BATCH,), generator=g)
    one_hot = torch.nn.functional.one_hot(task, N_TASKS).float()[:, None, :].expand(BATCH, SLICE_LEN, N_TASKS)
    observation = torch.cat([features, one_hot], dim=-1)
    action = torch.rand(BATCH, SLICE_LEN, ACTION_DIM, generator=g) * 2 - 1
    short = torch.rand(BATCH, generator=g) < PAD_SEGMENT_FRACTION
    length = torch.where(short, torch.randint(4, SLICE_LEN, (BATCH,), generator=g), SLICE_LEN)
    steps = torch.arange(SLICE_LEN)
    mask = steps[None, :] < length[:, None]
    last = torch.minimum(steps[None, :], (length - 1)[:, None])  # padding repeats the last real step
    observation = observation.gather(1, last[..., None].expand_as(observation))
    action = action.gather(1, last[..., None].expand_as(action))
    episode_length = torch.randint(40, 200, (BATCH,), generator=g)
    anywhere = (torch.rand(BATCH, generator=g) * (episode_length - SLICE_LEN + 1)).long()
    start = torch.where(short, episode_length - length, anywhere)
    return TensorDict(
        {
            "observation": observation.contiguous(),
            "action": action.contiguous(),
            "step": start[:, None] + last,
            "episode_length": episode_length[:, None].expand(BATCH, SLICE_LEN).clone(),
            ("collector", "mask"): mask,
        },
        batch_size=[BATCH, SLICE_LEN],
    )


def make_net(seed: int = 0) -> torch.nn.Module:
    torch.manual_seed(seed)
    layers: list[torch.nn.Module] = []
    width = OBS_DIM + N_TASKS
    for _ in range(DEPTH):
        layers += [torch.nn.Linear(width, HIDDEN), torch.nn.ReLU()]
        width = HIDDEN
    layers.append(torch.nn.Linear(width, ACTION_DIM))
    return torch.nn.Sequential(*layers)


def make_step(variant: str, net: torch.nn.Module, batch: TensorDict) -> Callable[[], None]:
    """One training step of ``variant`` on its own copy of ``net`` and its own AdamW."""
    actor = TensorDictModule(copy.deepcopy(net), in_keys=["observation"], out_keys=["action"])
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=_BCLOSS_WARNING, category=UserWarning)
        if variant == "bc_mean":
            loss_module, key = BCLoss(actor, loss_function="mse"), "loss_bc"
        else:
            inner = BCLoss(actor, loss_function="mse", reduction="none")
            if variant in ("uniform", "tar", *BASELINES, *ELEMENT):
                loss_module = TARLoss(inner, variant)
            elif variant == "tar_exact":
                loss_module = TARLoss(inner, "tar", params=TARParams(cap="exact"))
            else:
                raise ValueError(f"unknown variant {variant!r}")
            key = "loss_tar"
    optimizer = torch.optim.AdamW(loss_module.parameters(), lr=1e-4)

    def step() -> None:
        loss = loss_module(batch)[key]
        loss.backward()
        optimizer.step()
        optimizer.zero_grad()

    return step


def masked_mean(losses: Tensor, valid: Tensor) -> Tensor:
    """The baseline: a plain masked mean over the last axis."""
    m = valid.to(losses.dtype)
    return (losses * m).sum(-1) / m.sum(-1)


def tar_paper(losses: Tensor, valid: Tensor) -> Tensor:
    return tar_weights(losses, valid)


def tar_exact(losses: Tensor, valid: Tensor) -> Tensor:
    return tar_weights(losses, valid, cap="exact")


def make_dro_time(batch: TensorDict) -> Callable[[Tensor, Tensor], Tensor]:
    """``dro_time``'s registered function on the batch's steps, from uniform group weights (as ``TARLoss`` calls it)."""
    spec = WEIGHTINGS["dro_time"]
    params = spec.params()
    state = spec.initial_state(params)
    step, length = batch.get("step"), batch.get("episode_length")

    def dro_time(losses: Tensor, valid: Tensor) -> Tensor:
        return spec.weights(losses, valid, params, 1.0, None, step=step, episode_length=length, state=state)[0]

    return dro_time


# ---------------------------------------------------------------------------------------------
# Timing
# ---------------------------------------------------------------------------------------------


# ---------------------------------------------------------------------------------------------
# The two sections
# ---------------------------------------------------------------------------------------------


def bench_train_step(reps: int, warmup: int, seed: int) -> tuple[list[dict], list[str]]:
    batch = make_batch(seed)
    net = make_net(seed)
    steps = {v: make_step(v, net, batch) for v in STEP_VARIANTS}
    for step in steps.values():
        for _ in range(warmup):
            step()
    times = interleaved(steps, reps, seed=seed, collect_every=20)

    rows: list[dict] = []
    stats = {v: median_iqr(t * 1e3) for v, t in times.items()}
    for baseline in STEP_BASELINES:
        for v in STEP_VARIANTS:
            med, iqr = stats[v]
            rows.append(
                dict(
                    section="train_step",
                    variant=v,
                    median=med,
                    iqr=iqr,
                    unit="ms/step",
                    ratio_to_baseline=med / stats[baseline][0],
                    baseline=baseline,
                    n=reps,
                )
            )
    for baseline in STEP_BASELINES:
        for v in STEP_VARIANTS:
            if v == baseline:
                continue
            med, iqr = median_iqr(times[v] / times[baseline])
            rows.append(
                dict(
                    section="train_step_paired",
                    variant=v,
                    median=med,
                    iqr=iqr,
                    unit="ratio",
                    ratio_to_baseline=med,
                    baseline=baseline,
                    n=reps,
                )
            )

    padded = 1 - batch.get(("collector", "mask")).float().mean().item()
    notes = [
        f"batch [{BATCH}, {SLICE_LEN}], obs {OBS_DIM}+{N_TASKS} one-hot, MLP {DEPTH}x{HIDDEN} ReLU -> {ACTION_DIM}, "
        f"AdamW; {padded:.1%} of steps padded; {warmup} warm-up steps per variant, {reps} interleaved rounds"
    ]
    return rows, notes


def _compile(fn: Callable, name: str, losses: Tensor, valid: Tensor) -> tuple[Callable | None, str]:
    """``torch.compile(fn)``, compiled now and checked against eager; ``(None, reason)`` on failure."""
    try:
        compiled = torch.compile(fn)
        start = time.perf_counter()
        got = compiled(losses, valid)
        seconds = time.perf_counter() - start
        torch.testing.assert_close(got, fn(losses, valid))
        for _ in range(3):  # settle any recompilation before timing
            compiled(losses, valid)
    except Exception as exc:  # the benchmark reports unavailable rows rather than crashing
        reason = f"{type(exc).__name__}: {str(exc).strip().splitlines()[0] if str(exc).strip() else ''}"
        print(f"torch.compile of {name} unavailable: {reason}", file=sys.stderr)
        return None, reason
    return compiled, f"compiled in {seconds:.1f} s, matches eager"


def bench_weighting(reps: int, calls: int, seed: int) -> tuple[list[dict], list[str]]:
    batch = make_batch(seed)
    valid = batch.get(("collector", "mask"))
    g = torch.Generator().manual_seed(seed + 1)
    losses = torch.rand(BATCH, SLICE_LEN, generator=g, dtype=torch.float32).square()
    eager = {
        "masked_mean": masked_mean,
        "tar_paper": tar_paper,
        "tar_exact": tar_exact,
        "tilted": tilted_weights,
        "truncate": truncate_weights,
        "keyframe": keyframe_weights,
        "focal": focal_weights,
        "dro_time": make_dro_time(batch),
    }
    fns: dict[str, Callable] = dict(eager)
    notes = []
    with warnings.catch_warnings():
        # torch.compile / inductor may warn (e.g. about TF32 or deprecated config); this
        # benchmark must not turn them into errors under pytest's filterwarnings=error.
        warnings.simplefilter("ignore")
        for name, eager_name in COMPILED.items():
            compiled, note = _compile(eager[eager_name], eager_name, losses, valid)
            notes.append(f"{name}: {note}")
            if compiled is not None:
                fns[name] = compiled
        for fn in fns.values():
            for _ in range(max(calls, 20)):
                fn(losses, valid)
        calls_fns = {name: (lambda fn=fn: fn(losses, valid)) for name, fn in fns.items()}
        # the element variants score per-element losses [B, L, A] with the step mask broadcast over A
        elements = torch.rand(BATCH, SLICE_LEN, ACTION_DIM, generator=g, dtype=torch.float32).square()
        element_valid = valid[..., None].expand_as(elements)
        for name, fn in (("tar_arm", tar_arm_weights), ("tar_dimnorm", tar_dimnorm_weights)):
            for _ in range(max(calls, 20)):
                fn(elements, element_valid)
            calls_fns[name] = lambda fn=fn: fn(elements, element_valid)
        times = interleaved(calls_fns, reps, seed=seed, inner=calls, collect_every=20)

    stats = {v: median_iqr(t * 1e6) for v, t in times.items()}
    rows: list[dict] = []
    for v in WEIGHT_VARIANTS:
        baselines = [WEIGHT_BASELINE] + ([COMPILED[v]] if v in COMPILED else [])
        for baseline in baselines:
            if v in stats:
                med, iqr = stats[v]
                ratio, unit, n = med / stats[baseline][0], "us/call", reps
            else:
                med = iqr = ratio = math.nan
                unit, n = "unavailable", 0
            rows.append(
                dict(
                    section="weighting",
                    variant=v,
                    median=med,
                    iqr=iqr,
                    unit=unit,
                    ratio_to_baseline=ratio,
                    baseline=baseline,
                    n=n,
                )
            )
    notes.insert(0, f"losses [{BATCH}, {SLICE_LEN}] float32; {reps} interleaved rounds of {calls} calls per sample")
    return rows, notes


# ---------------------------------------------------------------------------------------------
# Output
# ---------------------------------------------------------------------------------------------


def _fmt(x: float, digits: int = 3) -> str:
    return "n/a" if not math.isfinite(x) else f"{x:.{digits}f}"


def render(df: pd.DataFrame, header: list[str], notes: dict[str, list[str]]) -> str:
    lines = [*header, ""]

    step = df[df.section == "train_step"]
    if len(step):
        lines.append("A. Training step (loss forward + backward + AdamW step + zero_grad)")
        lines += [f"   {n}" for n in notes["train_step"]]
        by_base = {b: step[step.baseline == b].set_index("variant") for b in STEP_BASELINES}
        paired = df[df.section == "train_step_paired"]
        lines.append(
            f"   {'variant':<12}{'median ms':>11}{'IQR ms':>9}{'/uniform':>10}{'/bc_mean':>10}"
            f"{'paired /uniform [IQR]':>24}{'paired /bc_mean':>17}"
        )
        for v in STEP_VARIANTS:
            u, b = by_base["uniform"].loc[v], by_base["bc_mean"].loc[v]
            cells = []
            for base in STEP_BASELINES:
                p = paired[(paired.variant == v) & (paired.baseline == base)]
                if len(p):
                    cells.append(f"{p['median'].iloc[0]:.4f} [{p['iqr'].iloc[0]:.4f}]")
                else:
                    cells.append("-")
            lines.append(
                f"   {v:<12}{_fmt(u['median'], 2):>11}{_fmt(u['iqr'], 2):>9}{_fmt(u['ratio_to_baseline'], 4):>10}"
                f"{_fmt(b['ratio_to_baseline'], 4):>10}{cells[0]:>24}{cells[1]:>17}"
            )
        tar_u = by_base["uniform"].loc["tar", "ratio_to_baseline"]
        tar_p = paired[(paired.variant == "tar") & (paired.baseline == "uniform")]["median"].iloc[0]
        verdict = "meets" if tar_p <= 1.03 else "misses"
        lines.append(
            f"   key figure tar/uniform: {tar_u:.4f} (ratio of medians), {tar_p:.4f} (median paired ratio)"
            f" -> {verdict} the target <= 1.03"
        )
        lines.append(
            f"   tar/bc_mean: {by_base['bc_mean'].loc['tar', 'ratio_to_baseline']:.4f} (ratio of medians), "
            f"{paired[(paired.variant == 'tar') & (paired.baseline == 'bc_mean')]['median'].iloc[0]:.4f} (paired)"
        )
        lines.append("")

    weight = df[df.section == "weighting"]
    if len(weight):
        lines.append("B. Weighting function alone")
        lines += [f"   {n}" for n in notes["weighting"]]
        lines.append(f"   {'variant':<20}{'median us':>11}{'IQR us':>9}{'/masked_mean':>14}{'/eager':>9}")
        base = weight[weight.baseline == WEIGHT_BASELINE].set_index("variant")
        for v in WEIGHT_VARIANTS:
            row = base.loc[v]
            vs_eager = "-"
            if v in COMPILED:
                e = weight[(weight.variant == v) & (weight.baseline == COMPILED[v])]
                vs_eager = _fmt(e["ratio_to_baseline"].iloc[0], 3)
            if row["unit"] == "unavailable":
                lines.append(f"   {v:<20}{'unavailable':>11}")
                continue
            lines.append(
                f"   {v:<20}{_fmt(row['median'], 1):>11}{_fmt(row['iqr'], 1):>9}"
                f"{_fmt(row['ratio_to_baseline'], 2):>14}{vs_eager:>9}"
            )
    return "\n".join(lines)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--quick", action="store_true", help="few repetitions: a smoke test (< 30 s)")
    p.add_argument("--out", type=Path, default=DEFAULT_OUT, help=f"CSV path (default {DEFAULT_OUT})")
    p.add_argument("--threads", type=int, default=1, help="torch.set_num_threads (default 1, for stable timings)")
    p.add_argument("--step-reps", type=int, default=None, help="interleaved rounds in A (default 500; quick 20)")
    p.add_argument("--weight-reps", type=int, default=None, help="interleaved rounds in B (default 200; quick 20)")
    p.add_argument("--calls", type=int, default=50, help="calls per timing sample in B (default 50)")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    if args.step_reps is None:
        args.step_reps = 20 if args.quick else 500
    if args.weight_reps is None:
        args.weight_reps = 20 if args.quick else 200
    if args.threads < 1 or args.step_reps < 1 or args.weight_reps < 1 or args.calls < 1:
        p.error("--threads, --step-reps, --weight-reps and --calls must be >= 1")
    return args


def main(argv: list[str] | None = None) -> pd.DataFrame:
    args = parse_args(argv)
    torch.set_num_threads(args.threads)
    commit = git_commit()
    started = time.perf_counter()

    step_rows, step_notes = bench_train_step(args.step_reps, warmup=5 if args.quick else 20, seed=args.seed)
    weight_rows, weight_notes = bench_weighting(args.weight_reps, args.calls, seed=args.seed)

    df = pd.DataFrame(step_rows + weight_rows)
    df["torch"] = torch.__version__
    df["threads"] = torch.get_num_threads()
    df["commit"] = commit
    df = df[COLUMNS]
    write_csv_atomic(df, args.out)

    header = [
        f"bench_objective: torch {torch.__version__}, threads {torch.get_num_threads()}, "
        f"CPUs {os.cpu_count()}, commit {commit}{' (--quick)' if args.quick else ''}",
        "timings interleaved round-robin in shuffled order; median and IQR over rounds; "
        "'paired' = median over rounds of the within-round ratio",
    ]
    print(render(df, header, {"train_step": step_notes, "weighting": weight_notes}))
    print(f"\nwrote {args.out} ({len(df)} rows) in {time.perf_counter() - started:.0f} s")
    return df


if __name__ == "__main__":
    main()
