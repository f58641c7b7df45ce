"""How much of TAR's weighting a random draw decides: a head's per-step losses (or another ranking signal) computed
twice on the same segments.

Usage::

    python -m benchmarks.analysis noise --from DIR [--data DIR] [--out FILE] [--draws K,...]
                                        [--signals NAME,...|all] [--runs NAME,...]

A flow head's per-step loss depends on the time and noise it samples for that step, ACT's (in training) on the
latent it samples from its encoder; the MLP's is a function of the step alone. TAR z-scores the losses within a
segment, so what it up-weights is the within-segment order of the losses: where that order changes from one draw
to the next, the weights follow the draw rather than the step.

For every uniform run of ``--from`` trained to its last step with its ``checkpoint.pt``, evaluated or not (the policy
trained with uniform weights: the reference, as in the fit diagnostics; ``--runs`` names some of them), the command
rebuilds the policy and objective from the final checkpoint (:mod:`.rebuild`), computes the per-step losses along the
run's recorded demonstrations twice in training mode (as TAR sees them; no gradient; two disjoint sets of torch seeds,
:func:`draw_seeds`), cuts each demonstration into consecutive segments of the run's ``data.slice_len`` (the last one
shorter, masked) and writes one row per run and ``K`` of ``--draws`` (:data:`COLUMNS`, to ``--out``, default
``results/regimes/diagnosis/noise.csv``). With ``K = 1`` (the default) a draw is one pass, the loss TAR weighs in
training; with ``K > 1`` each draw is the mean of ``K`` passes, a lower-variance estimate of each step's loss that TAR
could weigh instead:

* ``loss_r``: the within-segment correlation of the two draws' losses
  (:func:`tar_rl.diagnostics.within_segment_correlation`): 1 for a deterministic loss;
* ``top_agree``: the fraction of segments whose highest-loss step is the same in both draws
  (:func:`tar_rl.diagnostics.top_step_agreement`), the step TAR weighs most; about ``1 / slice_len`` by chance;
* ``weight_r_tar`` and ``weight_r_tar_gentle``: the within-segment correlation of TAR's weights at full strength
  computed on each draw, at tar-rl's defaults and at the ``tar_gentle`` preset's settings;
* ``segments`` and ``steps``: how many segments (of at least two steps) and steps the numbers are over.

**Ranking signals** (``--signals``, default ``loss``; ``all``: every signal the run's head offers,
``objective.signal``, docs/objective.md "Ranking by a signal other than the loss"). A pass is one call of
``TARLoss.inspect_steps`` on an objective ranking by the signal (:meth:`.rebuild.Rebuilt.objective_with`), which
returns the step's loss and what the weighting would rank, the signal; the measures above are then computed on the
signal (``signal_r`` in place of ``loss_r``; ``top_agree`` and the weights are the signal's, what TAR would weigh
by it). Both draws of every signal use the same seeds, so a step's signal and loss come from the same draw. A head
that does not offer a signal asked for is refused before any run is computed, naming the head and its signals.

* ``time_normalized`` keeps a running mean of the loss per time bin (:class:`tar_rl.objectives.signals.TimeNormalizer`),
  which a run trained with another signal does not hold. Before the two draws it is warmed up on the same recorded
  segments, deterministically: :data:`WARMUP_PASSES` (20) passes over the run's recorded segments (the cut above),
  each pass in a fresh order (a ``torch.Generator`` seeded :data:`WARMUP_SEED`) and in batches of the run's
  ``data.batch_segments`` segments, training's batch shape, each batch one update of the running mean as a
  training step makes it (``inspect_steps`` with gradients on and the parameters frozen: nothing else changes),
  the flow times drawn after ``torch.manual_seed(WARMUP_SEED)``, a seed no draw uses (the draws' are ``0 .. 2K-1``).
  Why 20: on R5's recorded segments (757, ~12 batches a pass) that is 240 updates, so the bias-corrected moving
  average (decay 0.99) holds weight ``1 - 0.99 ** 240 = 0.91`` and weighs about the last hundred updates, some
  5,000 steps a bin in effective sample size against ~6,400 in a training run's final estimate (about 200 batches'
  worth of ~30 steps a bin), and a draw's own episode enters its estimate with about 1% of the weight, as a training
  batch does (the estimate always holds the call's own batch). Fewer passes leave the estimate noisier and its own
  batch heavier; each pass costs one more draw's forward passes. The draws themselves keep the warmed-up state (no
  gradient: not an update). A run trained with the signal keeps its own state from the checkpoint, as trained.
* **Per-segment times** (a run with ``policy.time_sampling=segment``): a segment's steps share one flow time and
  noise, so the head's three signals differ within a segment by one factor and TAR's weights from them agree (up
  to ``eps``): such a run is reported once, with ``loss`` (R7's candidate (d), benchmarks/results/regimes/PLAN.md),
  whatever ``--signals`` asks for among the head's signals. Its passes are drawn as training draws them, per
  segment: the recorded segments (the cut above; a demonstration's last one padded by repeating its last step and
  masked, as ``SliceSampler`` pads) in their recorded order, ``data.batch_segments`` to a batch, the times
  stratified across a batch's segments. A run with per-step times (``step``, the default) is drawn along each whole
  demonstration: each step draws its own time and noise whatever the batch, and the loss's numbers are those of the
  earlier versions of this command.

With only the loss on per-step draws the table has the columns above (:data:`COLUMNS`, what earlier versions
wrote, byte for byte); with another signal or a per-segment run it has :data:`SIGNAL_COLUMNS`: ``time_sampling``
and ``signal`` name what a row measures, ``signal_r`` the correlation of the signal. Beside the CSV it writes the
same numbers as markdown (``noise.md``: the mean per head, times, signal and passes, then each run), which
``docs/objective.md`` embeds, and prints them. It refuses a folder without such runs, a run whose checkpoint is
missing or not its last step, and a run ``--runs`` names that is not such a run.
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

__all__ = [
    "ALL",
    "COLUMNS",
    "MEASURES",
    "SIGNAL_COLUMNS",
    "SIGNAL_MEASURES",
    "WARMUP_PASSES",
    "WARMUP_SEED",
    "draw_losses",
    "draw_seeds",
    "head_signals",
    "noise_row",
    "noise_rows",
    "noise_table",
    "recorded_segments",
    "segments",
    "warm_up",
    "weight_presets",
    "write_noise",
]
#: What a run's row measures (module docstring), and the columns of ``noise.csv`` with the loss on per-step draws.
MEASURES = ("loss_r", "top_agree", "weight_r_tar", "weight_r_tar_gentle")
COLUMNS = ("run", "head", "seed", "draws", "segments", "steps", *MEASURES)
#: The same with a ranking signal or per-segment times: what a row measures, on the signal.
SIGNAL_MEASURES = ("signal_r", "top_agree", "weight_r_tar", "weight_r_tar_gentle")
SIGNAL_COLUMNS = ("run", "head", "seed", "time_sampling", "signal", "draws", "segments", "steps", *SIGNAL_MEASURES)
#: ``--signals all``: every signal a run's head offers.
ALL = "all"
#: A stateful signal's warm-up (module docstring): passes over the recorded segments, and its torch seed.
WARMUP_PASSES = 20
WARMUP_SEED = 1_000_000
DEFAULT_OUT = DEFAULT_RUNS.parent / "diagnosis" / "noise.csv"
WHO = "noise"
_VALID = ("collector", "mask")  # the validity mask TARLoss and the heads' losses read (tar_rl.data.VALID_KEY)
_TIMES = ("step", "segment")


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


def head_signals(head: str) -> tuple[str, ...]:
    """The ranking signals the head ``head`` offers: ``loss`` and its own (``objective.signal``)."""
    from tar_rl.policies import POLICIES

    return ("loss", *POLICIES[head].signals)


def run_signals(run: Run, wanted: Sequence[str]) -> tuple[str, ...]:
    """The signals to measure on ``run``: ``wanted`` (or every one its head offers with :data:`ALL`), refused
    naming the head and its signals where it does not offer one."""
    offered = head_signals(run.policy)
    if ALL in wanted:
        return offered
    missing = [s for s in wanted if s not in offered]
    if missing:
        raise SystemExit(
            f"{WHO}: {run.name}: the {run.policy} head offers the ranking signals {list(offered)}, not "
            f"{', '.join(map(repr, missing))}"
        )
    return tuple(wanted)


def time_sampling(cfg) -> str:
    """How a run drew its training times (``policy.time_sampling``; ``step`` for a head without the setting)."""
    return getattr(cfg.policy, "time_sampling", "step")


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


def recorded_segments(episodes: list, slice_len: int) -> list:
    """The recorded ``episodes`` (``(task, episode, TensorDict)``) cut as :func:`segments` cuts their values: one
    ``[slice_len]`` TensorDict per segment with its mask at ``("collector", "mask")``, an episode's last segment
    padded by repeating its last step (as ``SliceSampler`` pads a training batch) and masked there."""
    import torch

    if slice_len < 1:
        raise ValueError(f"slice_len must be at least 1, got {slice_len}")
    out = []
    for _, _, td in episodes:
        length = td.shape[0]
        for start in range(0, length, slice_len):
            steps = torch.arange(start, start + slice_len)
            piece = td[steps.clamp_max(length - 1)]
            piece.set(_VALID, steps < length)
            out.append(piece)
    return out


def draw_seeds(passes: int) -> tuple[range, range]:
    """The torch seeds of the two draws when each is the mean of ``passes`` passes: ``0 .. K-1`` and
    ``K .. 2K-1``."""
    if passes < 1:
        raise ValueError(f"a draw needs at least one pass, got {passes}")
    return range(passes), range(passes, 2 * passes)


def _pass(objective, batch) -> tuple[np.ndarray, np.ndarray]:
    """One pass of ``objective`` on ``batch``: its per-step losses and the values it ranks (``inspect_steps``)."""
    steps, _, ranked = objective.inspect_steps(batch)
    return steps.double().numpy(), ranked.double().numpy()


def _fill(objective, batches, seeds, cache: dict) -> None:
    """Compute the passes of ``seeds`` not in ``cache`` (seed -> one ``(losses, ranked)`` per batch), each after
    ``torch.manual_seed(seed)``, in training mode without gradient."""
    import torch

    missing = [seed for seed in seeds if seed not in cache]
    if not missing:
        return
    was_training = objective.training
    objective.train()
    try:
        with torch.no_grad():
            for seed in missing:
                torch.manual_seed(seed)
                cache[seed] = [_pass(objective, batch) for batch in batches]
    finally:
        objective.train(was_training)


def _mean(cache: dict, seeds, which: int) -> list[np.ndarray]:
    """The mean over the passes of ``seeds`` of each batch's losses (``which`` 0) or ranked values (1)."""
    return [sum(values) / len(seeds) for values in zip(*([p[which] for p in cache[s]] for s in seeds), strict=True)]


def draw_losses(objective, episodes: list, seeds, cache: dict | None = None, ranked: bool = False) -> list[np.ndarray]:
    """The per-step losses along each of ``episodes`` (``(task, episode, TensorDict)``), computed in training mode
    without gradient once after ``torch.manual_seed(s)`` for each ``s`` of ``seeds``, and averaged over those
    passes: with one seed, the losses TAR would weigh under one random draw (``ranked``: the values the objective
    ranks instead, its signal). ``cache`` (seed -> one pass) keeps the passes for other draws of the same objective
    and episodes, so no pass is computed twice."""
    cache = {} if cache is None else cache
    seeds = list(seeds)
    _fill(objective, [td.unsqueeze(0) for _, _, td in episodes], seeds, cache)
    return [v.squeeze(0) for v in _mean(cache, seeds, int(ranked))]


def draw_segments(objective, batches: list, seeds, cache: dict | None = None) -> np.ndarray:
    """The ranked values ``[N, L]`` of the segment ``batches`` (``[B, L]`` TensorDicts, their segments in order),
    each pass after ``torch.manual_seed(s)`` as :func:`draw_losses`, averaged over the passes of ``seeds``."""
    cache = {} if cache is None else cache
    seeds = list(seeds)
    _fill(objective, batches, seeds, cache)
    return np.concatenate(_mean(cache, seeds, 1))


def _batches(pieces: list, size: int, order=None) -> list:
    """``pieces`` (``[L]`` TensorDicts) stacked ``size`` to a ``[B, L]`` batch, in ``order`` (default theirs)."""
    import torch

    order = range(len(pieces)) if order is None else [int(i) for i in order]
    order = list(order)
    return [torch.stack([pieces[i] for i in order[k : k + size]]) for k in range(0, len(order), size)]


def warm_up(objective, pieces: list, batch_segments: int, passes: int = WARMUP_PASSES, seed: int = WARMUP_SEED) -> int:
    """Move a ranking signal's state (a running mean) as training would on the recorded segments ``pieces``
    (module docstring): ``passes`` passes, each in a fresh order from a generator seeded ``seed`` and in batches of
    ``batch_segments``, one ``inspect_steps`` call a batch in training mode with gradients on (what keeps the
    state's update) and the parameters frozen (no graph, no change); torch's global seed ``seed`` first. Returns
    the number of updates."""
    import torch

    params = list(objective.parameters())
    grads = [p.requires_grad for p in params]
    was_training = objective.training
    generator = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    updates = 0
    try:
        for p in params:
            p.requires_grad_(False)
        objective.train()
        with torch.enable_grad():
            for _ in range(passes):
                order = torch.randperm(len(pieces), generator=generator)
                for batch in _batches(pieces, batch_segments, order):
                    objective.inspect_steps(batch)
                    updates += 1
    finally:
        for p, g in zip(params, grads, strict=True):
            p.requires_grad_(g)
        objective.train(was_training)
    return updates


def _stateful(objective) -> bool:
    """Whether ``objective``'s ranking signal keeps a state (e.g. ``time_normalized``'s running mean)."""
    return getattr(objective.clean_inner, "signal_state", None) is not None


def noise_rows(
    run: Run,
    passes: Sequence[int] = (1,),
    data_root: Path | None = None,
    demos: dict | None = None,
    signals: Sequence[str] = ("loss",),
):
    """The rows of the finished run ``run``, one per signal of ``signals`` (:func:`run_signals`; a per-segment run
    once, with ``loss``) and number of passes a draw averages (its final checkpoint rebuilt once; ``demos`` caches
    the datasets read, across runs); each row holds the keys of :data:`SIGNAL_COLUMNS`."""
    wanted = run_signals(run, signals)
    rebuilt = rebuild_final(run, data_root, {} if demos is None else demos, WHO)
    rows = []
    for signal in ("loss",) if time_sampling(rebuilt.cfg) == "segment" else wanted:
        objective = rebuilt.objective_with(signal)
        if objective is not rebuilt.objective and _stateful(objective):
            pieces = recorded_segments(rebuilt.episodes, rebuilt.cfg.data.slice_len)
            warm_up(objective, pieces, rebuilt.cfg.data.batch_segments)
        cache: dict = {}
        rows += [noise_row(run, rebuilt, k, cache, objective, signal) for k in passes]
    return rows


def noise_row(run: Run, rebuilt, passes: int = 1, cache: dict | None = None, objective=None, signal="loss") -> dict:
    """One row (the keys of :data:`SIGNAL_COLUMNS`): two draws of the values ``objective`` ranks (default
    ``rebuilt``'s own objective, :class:`.rebuild.Rebuilt`, ranking by ``signal``), each the mean of ``passes``
    passes, compared (``cache`` as :func:`draw_losses`; per segment for a per-segment run, module docstring)."""
    import torch

    from tar_rl.objectives import tar_weights

    objective = rebuilt.objective if objective is None else objective
    cfg = rebuilt.cfg
    slice_len, sampling = cfg.data.slice_len, time_sampling(cfg)
    if sampling == "segment":
        pieces = recorded_segments(rebuilt.episodes, slice_len)
        batches = _batches(pieces, cfg.data.batch_segments)
        valid = torch.stack([p.get(_VALID) for p in pieces]).numpy()
        a, b = (draw_segments(objective, batches, seeds, cache) for seeds in draw_seeds(passes))
    else:
        (a, valid), (b, _) = (
            segments(draw_losses(objective, rebuilt.episodes, seeds, cache, ranked=True), slice_len)
            for seeds in draw_seeds(passes)
        )
    row = {
        "run": run.name,
        "head": run.policy,
        "seed": run.seed,
        "time_sampling": sampling,
        "signal": signal,
        "draws": passes,
        "segments": int((valid.sum(axis=1) >= 2).sum()),
        "steps": int(valid.sum()),
        "signal_r": within_segment_correlation(a, b, valid),
        "top_agree": top_step_agreement(a, b, valid),
    }
    mask = torch.from_numpy(valid)
    for name, kwargs in weight_presets().items():
        wa, wb = (tar_weights(torch.from_numpy(x), mask, **kwargs).numpy() for x in (a, b))
        row[f"weight_r_{name}"] = within_segment_correlation(wa, wb, valid)
    return row


def _loss_only(table: pd.DataFrame) -> bool:
    """Whether every row measures the loss on per-step draws (the table earlier versions wrote)."""
    return bool(((table["signal"] == "loss") & (table["time_sampling"] == "step")).all())


def _ordered(table: pd.DataFrame) -> pd.DataFrame:
    """``table`` (rows of :data:`SIGNAL_COLUMNS`) as written: with only the loss on per-step draws the columns
    :data:`COLUMNS` by head, passes, seed and name (earlier versions' table); else :data:`SIGNAL_COLUMNS` by head,
    times (``step`` first), signal (``loss``, then the head's own in its order), passes, seed and name."""
    if _loss_only(table):
        table = table.rename(columns={"signal_r": "loss_r"})[list(COLUMNS)]
        return table.sort_values(["head", "draws", "seed", "run"]).reset_index(drop=True)
    rank = {"time_sampling": {t: i for i, t in enumerate(_TIMES)}}
    rank["signal"] = {s: i for head in table["head"].unique() for i, s in enumerate(head_signals(head))}
    keyed = table.assign(**{f"_{k}": table[k].map(v) for k, v in rank.items()})
    keyed = keyed.sort_values(["head", "_time_sampling", "_signal", "draws", "seed", "run"])
    return keyed[list(SIGNAL_COLUMNS)].reset_index(drop=True)


def noise_table(
    runs_dir: Path,
    data_root: Path | None = None,
    passes: Sequence[int] = (1,),
    signals: Sequence[str] = ("loss",),
    names: Sequence[str] | None = None,
) -> pd.DataFrame:
    """:func:`noise_rows` of every trained uniform run of ``runs_dir`` with its checkpoint (finished, or trained
    with ``eval.rollouts=0``: the command reads the trained policy only; ``names``: only these), for each of
    ``signals`` and ``passes``, ordered as written (:func:`_ordered`).

    Raises:
        SystemExit: ``runs_dir`` is not a folder or holds no such run; a run of ``names`` is not such a run; a
            run's head does not offer a signal of ``signals`` (before any run is computed).
    """
    from tar_rl.runs import CHECKPOINT

    if not runs_dir.is_dir():
        raise SystemExit(f"{WHO}: {runs_dir} is not a folder")
    found = []
    for path in sorted(p for p in runs_dir.iterdir() if (p / CHECKPOINT).is_file()):
        if names is not None and path.name not in names:
            continue
        run = load_run(path)
        if (run.finished or run.not_evaluated) and run.objective == "uniform":
            found.append(run)
    if names is not None:
        absent = sorted(set(names) - {run.path.name for run in found})
        if absent:
            raise SystemExit(
                f"{WHO}: {', '.join(absent)}: not a trained uniform run with its {CHECKPOINT} in {runs_dir}"
            )
    if not found:
        raise SystemExit(f"{WHO}: no trained uniform run with its {CHECKPOINT} in {runs_dir}")
    for run in found:
        run_signals(run, signals)  # refuse before computing anything
    demos: dict = {}
    rows = []
    for run in found:
        print(f"{WHO}: recording {run.name}", file=sys.stderr)
        rows += noise_rows(run, passes, data_root, demos, signals)
    return _ordered(pd.DataFrame(rows, columns=list(SIGNAL_COLUMNS)))


_EXPLAINED = (
    "Final checkpoints of the uniform runs; per-step losses along the recorded training demonstrations, "
    "computed twice in training mode (each draw the mean of its passes, the two draws from disjoint torch "
    "seeds), cut into segments of the run's `data.slice_len`. One pass per draw is the loss TAR weighs in "
    "training. Loss r and weight r: within-segment correlation of the two draws (each draw's segment mean "
    "removed); weight r of TAR's weights at full strength at tar-rl's defaults (`tar`) and at the `tar_gentle` "
    "preset's settings. Top step agrees: the share of segments whose highest-loss step is the same in both "
    "draws. Head rows: means over the head's runs. Command: `python -m benchmarks.analysis noise --from DIR "
    "--draws K,...` (the runs with their `checkpoint.pt`)."
)
_SIGNAL_EXPLAINED = (
    "Final checkpoints of the uniform runs; the values TAR ranks (the ranking signal: the loss, or "
    "`objective.signal`) along the recorded training demonstrations, computed twice in training mode (each draw "
    "the mean of its passes, the two draws from disjoint torch seeds), cut into segments of the run's "
    "`data.slice_len`; times `step`: each step drew its own flow time and noise, along whole demonstrations; "
    "`segment`: one per segment (`policy.time_sampling=segment`), drawn per segment as in training, where the "
    "head's signals rank alike (reported once, with `loss`). `time_normalized`'s running mean warmed up first on "
    "the same segments (20 passes, a fixed seed, as `benchmarks/analysis/noise.py` documents). Signal r "
    "and weight r: within-segment correlation of the two draws (each draw's segment mean removed); weight r of "
    "TAR's weights on the signal at full strength at tar-rl's defaults (`tar`) and at the `tar_gentle` preset's "
    "settings. Top step agrees: the share of segments whose highest-ranked step is the same in both draws. Head "
    "rows: means over the runs. Command: `python -m benchmarks.analysis noise --from DIR --signals all` (the runs "
    "with their `checkpoint.pt`)."
)


def noise_markdown(table: pd.DataFrame) -> str:
    """``noise.md``: the mean per head and number of passes over its runs (with times and signal where the table
    has them), then one row per run, and how they were computed."""
    if "signal" in table.columns:
        return _signal_markdown(table)

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
        _EXPLAINED,
    ]
    return "\n".join(lines) + "\n"


def _signal_markdown(table: pd.DataFrame) -> str:
    def cells(r) -> str:
        return " | ".join(fmt_num(getattr(r, c), 3) for c in SIGNAL_MEASURES)

    header = "signal r | top step agrees | weight r (tar) | weight r (tar_gentle) |"
    keys = ["head", "time_sampling", "signal", "draws"]
    groups = table.groupby(keys, sort=False)  # in the table's order
    by_head = groups[list(SIGNAL_MEASURES)].mean()
    runs = groups.size()
    lines = [
        "# Two draws of a head's per-step ranking signals",
        "",
        "| head | times | signal | passes per draw | runs | " + header,
        "|---|---|---|---|---|---|---|---|---|",
        *(f"| {' | '.join(map(str, r.Index))} | {runs[r.Index]} | {cells(r)} |" for r in by_head.itertuples()),
        "",
        "| run | seed | times | signal | passes per draw | segments | " + header,
        "|---|---|---|---|---|---|---|---|---|---|",
        *(
            f"| {r.run} | {r.seed} | {r.time_sampling} | {r.signal} | {r.draws} | {r.segments} | {cells(r)} |"
            for r in table.itertuples()
        ),
        "",
        _SIGNAL_EXPLAINED,
    ]
    return "\n".join(lines) + "\n"


def write_noise(table: pd.DataFrame, out: Path) -> str:
    """Write ``table`` to ``out`` (CSV, six decimals) and its markdown beside it (``.md``); returns the markdown."""
    from tar_rl.io import atomic_write, write_csv_atomic

    out.parent.mkdir(parents=True, exist_ok=True)
    write_csv_atomic(table.round(6), out)
    text = noise_markdown(table)
    atomic_write(out.with_suffix(".md"), lambda f: f.write(text))
    return text


def _passes(text: str) -> list[int]:
    """``--draws``: passes per draw, comma-separated positive integers."""
    try:
        values = [int(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated whole numbers, got {text!r}") from None
    if not values or min(values) < 1 or len(set(values)) != len(values):
        raise argparse.ArgumentTypeError(f"each number of passes must be at least 1 and listed once, got {text!r}")
    return values


def _names(text: str) -> list[str]:
    """Comma-separated names, each once."""
    values = [v.strip() for v in text.split(",") if v.strip()]
    if not values or len(set(values)) != len(values):
        raise argparse.ArgumentTypeError(f"expected comma-separated names, each once, got {text!r}")
    return values


def noise_main(argv: list[str]) -> int:
    """``noise --from DIR [--data DIR] [--out FILE] [--draws K,...] [--signals NAME,...|all] [--runs NAME,...]``:
    the two-draw table of the uniform runs of ``DIR``."""
    parser = checkpoint_parser(
        "noise",
        "How alike two random draws of a head's per-step losses (or ranking signal), and TAR's weights on them, are.",
        "the runs",
        DEFAULT_OUT,
    )
    parser.add_argument(
        "--draws", type=_passes, default=[1], help="passes averaged per draw, e.g. 1,8 (default: 1, what TAR weighs)"
    )
    parser.add_argument(
        "--signals",
        type=_names,
        default=["loss"],
        help="the ranking signals measured, e.g. loss,action_error, or all (every one a run's head offers); "
        "default: loss",
    )
    parser.add_argument(
        "--runs", dest="names", type=_names, default=None, help="only these runs of the folder (their names)"
    )
    args = parser.parse_args(argv)
    import torch

    torch.set_num_threads(1)
    table = noise_table(Path(args.runs), Path(args.data) if args.data else None, args.draws, args.signals, args.names)
    out = Path(args.out)
    text = write_noise(table, out)
    print(text, end="")
    print(out)
    return 0
