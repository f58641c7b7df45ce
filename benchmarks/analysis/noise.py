"""How much of TAR's weighting a random draw decides: a head's per-step losses computed twice on the same segments.

Usage::

    python -m benchmarks.analysis noise --from DIR [--data DIR] [--out FILE] [--draws K,...]

A flow head's per-step loss depends on the time and noise it samples for that step, ACT's (in training) on the
latent it samples from its encoder; the MLP's is a function of the step alone. TAR z-scores the losses within a
segment, so what it up-weights is the within-segment order of the losses: where that order changes from one draw
to the next, the weights follow the draw rather than the step.

For every finished uniform run of ``--from`` with its ``checkpoint.pt`` (the policy trained with uniform weights:
the reference, as in the fit diagnostics), the command rebuilds the policy and objective from the final checkpoint
(:mod:`.rebuild`), computes the per-step losses along the run's recorded demonstrations twice in training mode
(as TAR sees them; no gradient; two disjoint sets of torch seeds, :func:`draw_seeds`), cuts each demonstration into
consecutive segments of the run's ``data.slice_len`` (the last one shorter, masked) and writes one row per run and
``K`` of ``--draws`` (:data:`COLUMNS`, to ``--out``, default ``results/regimes/diagnosis/noise.csv``). With
``K = 1`` (the default) a draw is one pass, the loss TAR weighs in training; with ``K > 1`` each draw is the mean
of ``K`` passes, a lower-variance estimate of each step's loss that TAR could weigh instead:

* ``loss_r``: the within-segment correlation of the two draws' losses
  (:func:`tar_rl.diagnostics.within_segment_correlation`): 1 for a deterministic loss;
* ``top_agree``: the fraction of segments whose highest-loss step is the same in both draws
  (:func:`tar_rl.diagnostics.top_step_agreement`), the step TAR weighs most; about ``1 / slice_len`` by chance;
* ``weight_r_tar`` and ``weight_r_tar_gentle``: the within-segment correlation of TAR's weights at full strength
  computed on each draw, at tar-rl's defaults and at the ``tar_gentle`` preset's settings;
* ``segments`` and ``steps``: how many segments (of at least two steps) and steps the numbers are over.

Beside the CSV it writes the same numbers as markdown (``noise.md``: the mean per head, then each run), which
``docs/objective.md`` embeds, and prints them. It refuses a folder without such runs and a run whose checkpoint is
missing or not its last step.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from dataclasses import fields
from pathlib import Path

import numpy as np
import pandas as pd

from benchmarks.analysis.pairs import DEFAULT_RUNS
from benchmarks.analysis.rebuild import checkpoint_parser, rebuild_final
from benchmarks.studies.writers import fmt_num
from tar_rl.diagnostics import top_step_agreement, within_segment_correlation
from tar_rl.report import Run, load_run

__all__ = ["COLUMNS", "MEASURES", "draw_losses", "draw_seeds", "noise_row", "noise_table", "segments", "weight_presets"]
#: What a run's row measures (module docstring), and the columns of ``noise.csv``.
MEASURES = ("loss_r", "top_agree", "weight_r_tar", "weight_r_tar_gentle")
COLUMNS = ("run", "head", "seed", "draws", "segments", "steps", *MEASURES)
DEFAULT_OUT = DEFAULT_RUNS.parent / "diagnosis" / "noise.csv"
WHO = "noise"


def weight_presets() -> dict[str, dict]:
    """TAR's hyper-parameters (:func:`tar_rl.objectives.tar_weights` keywords) at tar-rl's defaults (``tar``) and
    at the ``tar_gentle`` preset's settings, read from the recipe's presets."""
    from tar_rl.objectives import TARParams
    from tar_rl.recipes.config import OBJECTIVE_PRESETS

    gentle = OBJECTIVE_PRESETS["tar_gentle"]
    return {
        "tar": TARParams().tar_kwargs(),
        "tar_gentle": TARParams(**{f.name: getattr(gentle, f.name) for f in fields(TARParams)}).tar_kwargs(),
    }


def segments(values: list[np.ndarray], slice_len: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-episode 1-d ``values`` cut into consecutive segments of ``slice_len`` steps: ``([N, slice_len] values,
    [N, slice_len] valid)``, an episode's last segment padded with 0 and masked (``valid`` is ``True`` on real
    steps)."""
    if slice_len < 1:
        raise ValueError(f"slice_len must be at least 1, got {slice_len}")
    rows, masks = [], []
    for episode in values:
        for start in range(0, len(episode), slice_len):
            part = np.asarray(episode[start : start + slice_len], dtype=np.float64)
            rows.append(np.pad(part, (0, slice_len - len(part))))
            masks.append(np.arange(slice_len) < len(part))
    return np.stack(rows), np.stack(masks)


def draw_seeds(passes: int) -> tuple[range, range]:
    """The torch seeds of the two draws when each is the mean of ``passes`` passes: ``0 .. K-1`` and
    ``K .. 2K-1``."""
    if passes < 1:
        raise ValueError(f"a draw needs at least one pass, got {passes}")
    return range(passes), range(passes, 2 * passes)


def draw_losses(objective, episodes: list, seeds, cache: dict | None = None) -> list[np.ndarray]:
    """The per-step losses along each of ``episodes`` (``(task, episode, TensorDict)``), computed in training mode
    without gradient once after ``torch.manual_seed(s)`` for each ``s`` of ``seeds``, and averaged over those
    passes: with one seed, the losses TAR would weigh under one random draw. ``cache`` (seed -> one pass's losses)
    keeps the passes for other draws of the same objective and episodes, so no pass is computed twice."""
    import torch

    cache = {} if cache is None else cache
    seeds = list(seeds)
    missing = [seed for seed in seeds if seed not in cache]
    if missing:
        was_training = objective.training
        objective.train()
        try:
            with torch.no_grad():
                for seed in missing:
                    torch.manual_seed(seed)
                    cache[seed] = [
                        objective.step_losses(td.unsqueeze(0)).squeeze(0).double().numpy() for _, _, td in episodes
                    ]
        finally:
            objective.train(was_training)
    return [sum(steps) / len(seeds) for steps in zip(*(cache[seed] for seed in seeds), strict=True)]


def noise_rows(run: Run, passes: Sequence[int] = (1,), data_root: Path | None = None, demos: dict | None = None):
    """The rows of :data:`COLUMNS` for the finished run ``run``, one per number of passes a draw averages (its
    final checkpoint rebuilt once; ``demos`` caches the datasets read, across runs)."""
    rebuilt = rebuild_final(run, data_root, {} if demos is None else demos, WHO)
    cache: dict = {}
    return [noise_row(run, rebuilt, k, cache) for k in passes]


def noise_row(run: Run, rebuilt, passes: int = 1, cache: dict | None = None) -> dict:
    """One row of :data:`COLUMNS`: two draws of ``rebuilt``'s per-step losses (:class:`.rebuild.Rebuilt`), each
    the mean of ``passes`` passes, compared (``cache`` as :func:`draw_losses`)."""
    import torch

    from tar_rl.objectives import tar_weights

    slice_len = rebuilt.cfg.data.slice_len
    draws = [
        segments(draw_losses(rebuilt.objective, rebuilt.episodes, seeds, cache), slice_len)
        for seeds in draw_seeds(passes)
    ]
    (a, valid), (b, _) = draws
    row = {
        "run": run.name,
        "head": run.policy,
        "seed": run.seed,
        "draws": passes,
        "segments": int((valid.sum(axis=1) >= 2).sum()),
        "steps": int(valid.sum()),
        "loss_r": within_segment_correlation(a, b, valid),
        "top_agree": top_step_agreement(a, b, valid),
    }
    mask = torch.from_numpy(valid)
    for name, kwargs in weight_presets().items():
        wa, wb = (tar_weights(torch.from_numpy(x), mask, **kwargs).numpy() for x in (a, b))
        row[f"weight_r_{name}"] = within_segment_correlation(wa, wb, valid)
    return row


def noise_table(runs_dir: Path, data_root: Path | None = None, passes: Sequence[int] = (1,)) -> pd.DataFrame:
    """:func:`noise_rows` of every finished uniform run of ``runs_dir`` with its checkpoint, for each of ``passes``,
    by head, passes, seed and name.

    Raises:
        SystemExit: ``runs_dir`` is not a folder or holds no such run.
    """
    from tar_rl.runs import CHECKPOINT

    if not runs_dir.is_dir():
        raise SystemExit(f"{WHO}: {runs_dir} is not a folder")
    found = []
    for path in sorted(p for p in runs_dir.iterdir() if (p / CHECKPOINT).is_file()):
        run = load_run(path)
        if run.finished and run.objective == "uniform":
            found.append(run)
    if not found:
        raise SystemExit(f"{WHO}: no finished uniform run with its {CHECKPOINT} in {runs_dir}")
    demos: dict = {}
    rows = []
    for run in found:
        print(f"{WHO}: recording {run.name}", file=sys.stderr)
        rows += noise_rows(run, passes, data_root, demos)
    table = pd.DataFrame(rows, columns=list(COLUMNS))
    return table.sort_values(["head", "draws", "seed", "run"]).reset_index(drop=True)


def noise_markdown(table: pd.DataFrame) -> str:
    """``noise.md``: the mean per head and number of passes over its runs, then one row per run, and how they were
    computed."""

    def cells(r) -> str:
        return " | ".join(fmt_num(getattr(r, c), 3) for c in MEASURES)

    header = "loss r | top step agrees | weight r (tar) | weight r (tar_gentle) |"
    groups = table.groupby(["head", "draws"], sort=True)
    by_head = groups[list(MEASURES)].mean()
    runs = groups.size()
    lines = [
        "# Two draws of a head's per-step losses",
        "",
        "| head | passes per draw | runs | " + header,
        "|---|---|---|---|---|---|---|",
        *(f"| {r.Index[0]} | {r.Index[1]} | {runs[r.Index]} | {cells(r)} |" for r in by_head.itertuples()),
        "",
        "| run | seed | passes per draw | segments | " + header,
        "|---|---|---|---|---|---|---|---|",
        *(f"| {r.run} | {r.seed} | {r.draws} | {r.segments} | {cells(r)} |" for r in table.itertuples()),
        "",
        "Final checkpoints of the uniform runs; per-step losses along the recorded training demonstrations, "
        "computed twice in training mode (each draw the mean of its passes, the two draws from disjoint torch "
        "seeds), cut into segments of the run's `data.slice_len`. One pass per draw is the loss TAR weighs in "
        "training. Loss r and weight r: within-segment correlation of the two draws (each draw's segment mean "
        "removed); weight r of TAR's weights at full strength at tar-rl's defaults (`tar`) and at the `tar_gentle` "
        "preset's settings. Top step agrees: the share of segments whose highest-loss step is the same in both "
        "draws. Head rows: means over the head's runs. Command: `python -m benchmarks.analysis noise --from DIR "
        "--draws K,...` (the runs with their `checkpoint.pt`).",
    ]
    return "\n".join(lines) + "\n"


def _passes(text: str) -> list[int]:
    """``--draws``: passes per draw, comma-separated positive integers."""
    try:
        values = [int(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated whole numbers, got {text!r}") from None
    if not values or min(values) < 1 or len(set(values)) != len(values):
        raise argparse.ArgumentTypeError(f"each number of passes must be at least 1 and listed once, got {text!r}")
    return values


def noise_main(argv: list[str]) -> int:
    """``noise --from DIR [--data DIR] [--out FILE] [--draws K,...]``: the two-draw table of the uniform runs of
    ``DIR``."""
    parser = checkpoint_parser(
        "noise",
        "How alike two random draws of a head's per-step losses, and TAR's weights on them, are.",
        "the runs",
        DEFAULT_OUT,
    )
    parser.add_argument(
        "--draws", type=_passes, default=[1], help="passes averaged per draw, e.g. 1,8 (default: 1, what TAR weighs)"
    )
    args = parser.parse_args(argv)
    import torch

    from tar_rl.io import atomic_write, write_csv_atomic

    torch.set_num_threads(1)
    table = noise_table(Path(args.runs), Path(args.data) if args.data else None, args.draws)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_csv_atomic(table.round(6), out)
    text = noise_markdown(table)
    atomic_write(out.with_suffix(".md"), lambda f: f.write(text))
    print(text, end="")
    print(out)
    return 0
