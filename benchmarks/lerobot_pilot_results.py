"""The first LeRobot pair's results (issue 38, item 6): what is committed of each run, and the pair's table.

``record``: each finished part of the pilot's folder (the plan's ``--root``: ``runs/<arm>-seed<seed>``, the training
logs ``<arm>.log``, ``eval/<arm>-seed<seed>``) written under ``benchmarks/results/lerobot_pilot/<arm>-seed<seed>``:

| file | what it holds |
|---|---|
| ``train_config.json`` | LeRobot's resolved training config of the run |
| ``training.json`` | the log's segments (each start or resumption: its first step, last checkpoint, seconds) |
| ``train_log.csv`` | the log's step lines (every 100 steps: losses, gradient norm, learning rate, time per update) |
| ``summary.json``, ``eval_rollouts.csv.gz`` | the evaluation by ``benchmarks.lerobot_pilot evaluate`` |

Paths are written relative to the repository (the pilot's folder as ``pilot``); no checkpoint is copied. Running it
again rewrites what it finds, so a run is recorded once trained and again once evaluated.

``report``: the pair's table from what is recorded (``report.md``): each run's success, Fast20 and NEPS, its
training time and where it resumed, its evaluation time, and what a study of eight pairs costs at those times; and,
once recorded, the exploratory third run beside the pair (``act_tar`` with TAR never on, registered in PLAN.md after
the pair: TAR on the same segments, and segments against independent frames), checked to log what ``act_tar`` logs
before TAR's start.

    python -m benchmarks.lerobot_pilot_results record --root DIR [--seed 0] [--out benchmarks/results/lerobot_pilot]
    python -m benchmarks.lerobot_pilot_results report [--results benchmarks/results/lerobot_pilot]
"""

from __future__ import annotations

import argparse
import gzip
import json
import re
import sys
from collections.abc import Sequence
from datetime import datetime
from pathlib import Path

import pandas as pd

from benchmarks.lerobot_pilot import ARMS, R4_STEPS, REPO, TAR_START
from benchmarks.relative_paths import rewrite
from tar_rl.io import atomic_write, write_csv_atomic, write_json_atomic
from tar_rl.runs import ROLLOUTS_FILE, SUMMARY_FILE

__all__ = ["main", "pilot_report", "record_pilot", "same_before", "training_record", "training_segments"]

#: A line of ``lerobot-train``'s log: its time and message (the progress bar shares lines with it, split by ``\r``).
LOG_LINE = re.compile(r"INFO (\d{4}-\d\d-\d\d \d\d:\d\d:\d\d) \S+ (.*)$")
CHECKPOINT_LINE = re.compile(r"Checkpoint policy after step (\d+)")
SUFFIXES = "KMBTQ"  # thousands, millions, ...: LeRobot's ``format_big_number``
START = "Start offline training"
#: Where ``record`` writes, from the repository root, and the names of what it writes.
RESULTS = Path("benchmarks") / "results" / "lerobot_pilot"
TRAINING_FILE, LOG_FILE, REPORT_FILE = "training.json", "train_log.csv", "report.md"
#: The pilot's runs: the pair, then ``act_tar`` with TAR never on (``--policy.tar.start`` at the last step: the uniform
#: mean over the same segments), an exploratory run registered in PLAN.md after the pair.
EXPLORATORY = "act_tar_uniform"
RUNS = (*ARMS, EXPLORATORY)
#: The step lines' timings, which differ between runs that compute the same values.
TIMINGS = ("time", "updt_s", "data_s", "smp/s")


def logged_number(text: str) -> tuple[float, float]:
    """A number as ``lerobot-train`` logs it (LeRobot's ``format_big_number``: ``512``, ``1K``, ``2M``) and the unit
    its digits are rounded to (1, 1000, ...)."""
    power = SUFFIXES.index(text[-1]) + 1 if text[-1] in SUFFIXES else 0
    unit = 1000.0**power
    return float(text[:-1] if power else text) * unit, unit


def training_segments(log: str, log_freq: int) -> list[dict]:
    """The segments of one run's ``lerobot-train`` log (each start and resumption appends to the same file).

    Each segment: its start (the line ``Start offline training``), the step it started from (the previous segment's
    last checkpoint, which ``--resume`` loads as ``checkpoints/last``), its last checkpoint and that line's time (the
    work kept: steps after the last checkpoint are lost and done again by the next segment), and its step lines as
    ``key:value`` fields. The lines before a segment's start (its config, dataset and policy) are not read.

    A step line is logged at every multiple of ``log_freq`` (the run's ``log_freq``), its step rounded past 999
    (``1K``): the line's exact step is counted from the segment's first step, and must round to the logged one.

    Raises:
        ValueError: a step line whose logged step is not the counted one (a line missing or out of place).
    """
    segments: list[dict] = []
    for part in re.split(r"[\r\n]", log):
        match = LOG_LINE.search(part)
        if match is None:
            continue
        when, message = datetime.strptime(match.group(1), "%Y-%m-%d %H:%M:%S"), match.group(2)
        if message.startswith(START):
            start = segments[-1]["checkpoint"] if segments else 0
            segments.append({"started": when, "from_step": start, "checkpoint": start, "kept_until": when, "steps": []})
            continue
        if not segments:
            continue
        segment = segments[-1]
        saved = CHECKPOINT_LINE.search(message)
        if saved:
            segment["checkpoint"], segment["kept_until"] = int(saved.group(1)), when
        elif message.startswith("step:"):
            fields = dict(token.split(":", 1) for token in message.split() if ":" in token)
            step = (segment["from_step"] // log_freq + 1 + len(segment["steps"])) * log_freq
            logged = fields.pop("step")
            value, unit = logged_number(logged)
            if abs(value - step) > unit / 2:
                raise ValueError(
                    f"the step line at {when} logs step {logged}, where counting from step "
                    f"{segment['from_step']} every {log_freq} gives {step}"
                )
            segment["steps"].append({"time": when.isoformat(sep=" "), "step": step, **fields})
    return segments


def training_record(arm: str, log: str, log_freq: int, steps: int = R4_STEPS) -> tuple[dict, pd.DataFrame]:
    """One run's ``training.json`` (its segments, the steps it resumed at, the seconds of work kept) and its step
    lines, from its ``lerobot-train`` log (:func:`training_segments`)."""
    try:
        segments = training_segments(log, log_freq)
    except ValueError as error:
        raise ValueError(f"{arm}: {error}") from None
    if not segments:
        raise ValueError(f"{arm}: its log holds no '{START}' line")
    rows = []
    for segment in segments:
        kept = (segment["kept_until"] - segment["started"]).total_seconds()
        done = segment["checkpoint"] - segment["from_step"]
        rows.append(
            {
                "started": segment["started"].isoformat(sep=" "),
                "from_step": segment["from_step"],
                "to_checkpoint": segment["checkpoint"],
                "kept_seconds": kept,
                "seconds_per_step": kept / done if done > 0 else None,
            }
        )
    record = {
        "arm": arm,
        "steps": steps,
        "finished": segments[-1]["checkpoint"] == steps,
        "resumed_at": [segment["from_step"] for segment in segments[1:]],
        "train_seconds": sum(row["kept_seconds"] for row in rows),
        "segments": rows,
    }
    return record, pd.DataFrame([line for segment in segments for line in segment["steps"]])


def portable_text(text: str, root: Path) -> str:
    """``text`` with the pilot's folder ``root`` written as ``pilot`` (the plan's ``--root``) and any other absolute
    path relative to the repository (:func:`benchmarks.relative_paths.rewrite`).

    Raises:
        ValueError: a path that cannot be written relative to the repository, named.
    """
    text, unplaced = rewrite(text.replace(str(root.resolve()), "pilot"), REPO)
    if unplaced:
        raise ValueError(f"cannot write {', '.join(sorted(set(unplaced)))} relative to the repository")
    return text


def _write_text(path: Path, text: str) -> None:
    atomic_write(path, lambda f: f.write(text))


def record_pilot(root: Path, out: Path, seed: int = 0) -> list[str]:
    """Write each finished part of the pilot under ``root`` (its :data:`RUNS`) into ``out/<run>-seed<seed>`` (the
    module's table of files); returns a line for each run trained and each evaluated."""
    written = []
    for run in RUNS:
        name = f"{run}-seed{seed}"
        target, log = out / name, root / f"{run}.log"
        config = root / "runs" / name / "checkpoints" / "last" / "pretrained_model" / "train_config.json"
        if config.is_file() and log.is_file():
            text = config.read_text()
            settings = json.loads(text)
            record, lines = training_record(
                run, log.read_text(errors="replace"), settings["log_freq"], steps=settings["steps"]
            )
            _write_text(target / "train_config.json", portable_text(text, root))
            write_json_atomic(record, target / TRAINING_FILE)
            write_csv_atomic(lines, target / LOG_FILE)
            written.append(f"{name}: trained to step {record['segments'][-1]['to_checkpoint']} of {record['steps']}")
        evaluation = root / "eval" / name
        if (evaluation / SUMMARY_FILE).is_file():
            _write_text(target / SUMMARY_FILE, portable_text((evaluation / SUMMARY_FILE).read_text(), root))
            packed = gzip.compress((evaluation / ROLLOUTS_FILE).read_bytes(), mtime=0)
            atomic_write(target / f"{ROLLOUTS_FILE}.gz", lambda f, packed=packed: f.write(packed), binary=True)
            written.append(f"{name}: evaluated")
    return written


def same_before(a: pd.DataFrame, b: pd.DataFrame, step: int) -> tuple[bool, int]:
    """Whether two runs' step lines (``train_log.csv``) before ``step`` agree in every logged value but the timings
    (:data:`TIMINGS`), and how many lines that compares (0: one of them has none)."""
    a, b = (frame[frame["step"] < step].drop(columns=list(TIMINGS), errors="ignore") for frame in (a, b))
    if a.empty or b.empty:
        return False, 0
    return len(a) == len(b) and list(a.columns) == list(b.columns) and a.astype(str).equals(b.astype(str)), len(a)


def _read(path: Path) -> dict | None:
    return json.loads(path.read_text()) if path.is_file() else None


def _percent(group: dict | None, key: str) -> str:
    return f"{100 * group[key]:.1f}" if group else "-"


def _overall(summary: dict | None) -> dict | None:
    return next((g for g in summary["final"] if g["name"] == "overall"), None) if summary else None


def _rows(folder: Path, label: str) -> tuple[str, list[str]]:
    """A run's row of the table and its rows per difficulty group."""
    record, summary = _read(folder / TRAINING_FILE), _read(folder / SUMMARY_FILE)
    overall = _overall(summary)
    training = resumed = rates = evaluation = "-"
    if record:
        training = f"{record['train_seconds'] / 3600:.2f} h"
        resumed = ", ".join(map(str, record["resumed_at"])) or "-"
        rates = ", ".join(f"{s['seconds_per_step']:.2f}" for s in record["segments"] if s["seconds_per_step"]) or "-"
    if summary:
        evaluation = f"{summary['final_eval_seconds'] / 60:.1f} min"
    row = (
        f"| {label} | {training} | {resumed} | {rates} | {evaluation} | {_percent(overall, 'success')} | "
        f"{_percent(overall, 'fast20')} | {_percent(overall, 'neps')} |"
    )
    groups = [
        f"| {label} | {g['name']} | {g['n_tasks']} | {g['n_rollouts']} | {_percent(g, 'success')} | "
        f"{_percent(g, 'fast20')} | {_percent(g, 'neps')} |"
        for g in (summary["final"] if summary else [])
        if g["name"] != "overall"
    ]
    return row, groups


def _finished(folder: Path) -> tuple[dict, dict] | None:
    record, summary = _read(folder / TRAINING_FILE), _read(folder / SUMMARY_FILE)
    return (record, summary) if record and record["finished"] and summary else None


def _exploratory(results: Path, seed: int) -> list[str]:
    """The paragraph on the exploratory run (``act_tar`` with TAR never on), once it and the pair are finished."""
    runs = {run: _finished(results / f"{run}-seed{seed}") for run in RUNS}
    if any(value is None for value in runs.values()):
        return []
    success = {run: 100 * _overall(summary)["success"] for run, (_, summary) in runs.items()}
    logs = {run: pd.read_csv(results / f"{run}-seed{seed}" / LOG_FILE) for run in ("act_tar", EXPLORATORY)}
    same, compared = same_before(logs["act_tar"], logs[EXPLORATORY], TAR_START)
    agree = "agree" if same else "do NOT agree"
    return [
        "",
        f"Exploratory (PLAN.md, registered after the pair): `{EXPLORATORY}` is `act_tar` with TAR never on "
        f"(`--policy.tar.start={R4_STEPS}`), the uniform mean over the same segments of 16 steps. Its step lines and "
        f"`act_tar`'s {agree} in every value but the timings before TAR's start at step {TAR_START} ({compared} "
        f"lines compared). `act_tar` - `{EXPLORATORY}` (TAR on the same segments): "
        f"{success['act_tar'] - success[EXPLORATORY]:+.1f} points; `{EXPLORATORY}` - `act` (segments of 16 "
        "consecutive frames against 1,024 independent ones, uniform both): "
        f"{success[EXPLORATORY] - success['act']:+.1f} points. One seed: no conclusion.",
    ]


def pilot_report(results: Path, seed: int = 0) -> str:
    """The pair's table (``report.md``) from the results ``record`` wrote under ``results``: the pair's two runs,
    then the exploratory run where it is recorded."""
    rows, groups, seconds = [], [], 0.0
    for run in RUNS:
        folder = results / f"{run}-seed{seed}"
        if run not in ARMS and not folder.is_dir():
            continue
        row, by_group = _rows(folder, folder.name if run in ARMS else f"{folder.name} (exploratory)")
        rows.append(row)
        groups += by_group
    finished = {arm: _finished(results / f"{arm}-seed{seed}") for arm in ARMS}
    missing = [arm for arm, done in finished.items() if done is None]
    if missing:
        cost = f"Not finished: {', '.join(missing)} (trained to step {R4_STEPS} and evaluated); no cost yet."
    else:
        seconds = sum(record["train_seconds"] + summary["final_eval_seconds"] for record, summary in finished.values())
        cost = (
            f"The pair took {seconds / 3600:.1f} hours here (training and evaluation, one run at a time); a "
            f"pre-registered study of 8 pairs at these times takes {8 * seconds / 3600:.0f} hours. One pair supports "
            "no conclusion about TAR."
        )
    lines = [
        "# LeRobot's ACT against act_tar: the first pair (pilot)",
        "",
        "| run | training | resumed at step | s / step | evaluation | success % | Fast20 | NEPS |",
        "|---|---|---|---|---|---|---|---|",
        *rows,
        "",
        cost,
        *_exploratory(results, seed),
        "",
        "Training: from each segment's start of training to its last checkpoint, summed (the work kept; a segment "
        "stopped by a session's end loses its steps after its last checkpoint, and the next segment resumes from "
        "it). s / step: each segment's, in order. Evaluation: tar-rl's evaluator on MT50, 20 rollouts per task, "
        "evaluation seed 1000. Success, Fast20 and NEPS in 100 x units over all tasks, then per difficulty group:",
        "",
        "| run | group | tasks | rollouts | success % | Fast20 | NEPS |",
        "|---|---|---|---|---|---|---|",
        *groups,
        "",
        "Written by `python -m benchmarks.lerobot_pilot_results report` from what `record` wrote.",
    ]
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.lerobot_pilot_results", description=__doc__.splitlines()[0]
    )
    commands = parser.add_subparsers(dest="command", required=True)
    rec = commands.add_parser("record", help="write the pilot's finished runs and evaluations under --out")
    rec.add_argument("--root", required=True, help="the pilot's folder (the plan's --root)")
    rec.add_argument("--seed", type=int, default=0, help="the pair's training seed (default 0)")
    rec.add_argument("--out", default=str(RESULTS), help=f"where they go (default {RESULTS.as_posix()})")
    rep = commands.add_parser("report", help="the pair's table from the recorded results (written as report.md)")
    rep.add_argument("--results", default=str(RESULTS), help=f"the recorded results (default {RESULTS.as_posix()})")
    rep.add_argument("--seed", type=int, default=0, help="the pair's training seed (default 0)")
    args = parser.parse_args(argv)
    if args.command == "record":
        root = Path(args.root)
        if not (root / "runs").is_dir():
            print(f"lerobot_pilot_results record: {root} holds no runs folder (the plan's --root)", file=sys.stderr)
            return 1
        try:
            written = record_pilot(root, Path(args.out), args.seed)
        except (OSError, ValueError) as error:
            print(f"lerobot_pilot_results record: {error}", file=sys.stderr)
            return 1
        print("\n".join(written) if written else f"nothing under {root} is trained or evaluated yet")
        return 0
    results = Path(args.results)
    if not results.is_dir():
        print(f"lerobot_pilot_results report: no recorded results at {results}", file=sys.stderr)
        return 1
    text = pilot_report(results, args.seed)
    _write_text(results / REPORT_FILE, text)
    print(text, end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())
