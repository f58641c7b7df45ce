"""What a study writes beside its runs: provenance, copies of finished runs (``collect``), the records that fix a
plan once its runs started, and the check that a run trained again reproduces a committed one."""

from __future__ import annotations

import gzip
import json
import os
import platform
import shlex
import shutil
import socket
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import pandas as pd

from benchmarks.studies.core import Scale
from tar_rl import runs
from tar_rl.report import run_file

__all__ = [
    "PACKED",
    "REPRODUCED_COLUMNS",
    "check_stage_plan",
    "check_started",
    "collect",
    "final_rollouts",
    "provenance",
    "read_json",
    "reproduces",
]

#: The repository's root: what the tracked copy of a run's config and an output's command name paths relative to.
REPO = Path(__file__).resolve().parents[2]
# Files of a run kept in the repository beside its config and summary, gzip-compressed.
PACKED = (runs.ROLLOUTS_FILE, runs.METRICS_FILE, runs.WEIGHTS_FILE)
# The rollout columns that must agree for a run trained again to stand in for a committed one.
REPRODUCED_COLUMNS = ("task", "variation_seed", "variation_index", "success", "steps")


def portable_argument(arg: str) -> str:
    """A command-line argument with the path it names (``PATH`` or ``KEY=PATH``) written relative to the repository
    (:func:`tar_rl.runs.portable_path`); a path outside the repository and its folders (an output that is not
    committed) is kept."""
    key, sep, value = arg.rpartition("=")
    try:
        return key + sep + runs.portable_path(value, REPO)
    except ValueError:
        return arg


def provenance(scale: Scale, command: str, argv: Sequence[str]) -> dict:
    """Command (``python -m benchmarks.studies`` with ``command`` and ``argv``, its paths relative to the
    repository), git commit, scale and machine of an output."""
    import torch

    from tar_rl.runs import git_commit

    device = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "cpu"
    return {
        "command": f"python -m benchmarks.studies {command} "
        + " ".join(shlex.quote(portable_argument(a)) for a in argv),
        "git_commit": git_commit() or "unknown",
        "scale": scale.name,
        "scale_about": scale.about,
        "hostname": socket.gethostname(),
        "cores": os.cpu_count(),
        "platform": platform.platform(),
        "torch": torch.__version__,
        "device": device,
        "written": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()),
    }


def read_json(path: Path) -> dict | None:
    """The JSON object of a record file, or None where there is none."""
    return json.loads(path.read_text()) if path.is_file() else None


def check_started(path: Path, entries: dict, record: bool, refusal: Callable[[str, object, object], str]) -> None:
    """Refuse entries of a plan that differ from the ones its runs started with, recorded in ``path``; with
    ``record``, add the entries not recorded yet (the plan's first runs start).

    ``refusal(key, recorded, now)`` is the message naming what changed.
    """
    from tar_rl.io import write_json_atomic

    started = read_json(path) or {}
    for key, value in entries.items():
        if key in started and started[key] != value:
            raise SystemExit(refusal(key, started[key], value))
    if record and any(key not in started for key in entries):
        write_json_atomic({**started, **{k: v for k, v in entries.items() if k not in started}}, path)


def check_stage_plan(path: Path, who: str, key: str, specs: dict, record: bool) -> None:
    """Refuse the plan of stage ``key`` (``specs``: its runs per arm) when its digest
    (:func:`~benchmarks.studies.core.plan_digest`) differs from the one recorded in ``path`` when its runs started;
    with ``record``, record it (the stage's first run starts). ``who`` names the study in the refusal."""
    from benchmarks.studies.core import plan_digest

    def refusal(key, recorded, now):
        return (
            f"{who}: {key}'s plan changed after its runs started (recorded {recorded} in {path}, now {now}); a "
            f"plan may not change once its runs started: restore it, or remove {key}'s runs and its entry there"
        )

    check_started(path, {key: plan_digest(specs)}, record, refusal)


def _copy_run(run: Path, tmp: Path, name: str, config: dict, summary: dict, keep: set[str]) -> None:
    """One finished run's config, summary and compressed logs (``weights.csv`` and the checkpoint where ``keep``
    names them) into ``tmp``."""
    import yaml

    from tar_rl.io import write_json_atomic

    (tmp / runs.CONFIG_FILE).write_text(yaml.safe_dump(config, sort_keys=False))
    write_json_atomic({**summary, "run_name": name}, tmp / runs.SUMMARY_FILE)
    for log in PACKED:
        if log == runs.WEIGHTS_FILE and log not in keep:
            continue
        if (run / log).is_file():
            with open(run / log, "rb") as f_in, gzip.GzipFile(tmp / f"{log}.gz", "wb", mtime=0) as f_out:
                shutil.copyfileobj(f_in, f_out)
    if runs.CHECKPOINT in keep:
        shutil.copy2(run / runs.CHECKPOINT, tmp / runs.CHECKPOINT)


def collect(src: Path, out: Path, keep_checkpoint: Sequence[str] = (), keep_weights: Sequence[str] = ()) -> list[str]:
    """Copy the finished runs of ``src`` into ``out/runs`` (logs gzip-compressed; checkpoints only for
    the run names in ``keep_checkpoint``); returns the names copied. Runs already there are skipped.

    ``weights.csv`` (TAR's weights along training demonstrations, the largest file of a run) is kept only for
    the run names in ``keep_weights``, the runs an analysis reads; every run's summary (weight per episode-time
    bin) and ``metrics.csv`` (largest weight, ESS) keep its weight statistics. The machine's folders in the config
    (``data.root``, ``runs_root``, ``init.from``) and summary are written relative to the repository
    (:func:`tar_rl.runs.portable_summary`).

    Each copy is named by its identity as this code computes it from the run's config (a run trained
    by code that named runs otherwise gets its current name; its summary's ``run_name`` follows). A config written
    by an older version (every weighting's parameters in its objective section) is copied, in the config file and
    the summary, as this version writes it (:func:`tar_rl.recipes.rundir.migrate_config`, what
    ``benchmarks/migrate_configs.py`` did to the committed runs)."""
    import yaml

    from tar_rl.recipes import run_name
    from tar_rl.recipes.rundir import migrate_config

    copied = []
    for run in sorted(p for p in src.iterdir() if (p / "summary.json").is_file()):
        summary = json.loads((run / "summary.json").read_text())
        if not summary.get("finished"):
            continue
        saved = migrate_config(yaml.safe_load((run / runs.CONFIG_FILE).read_text()))
        name = run_name(saved)
        target = out / "runs" / name
        if (target / "summary.json").is_file():
            continue
        if isinstance(summary.get("config"), dict):
            summary["config"] = migrate_config(summary["config"])
        try:
            config = runs.portable_config(saved, REPO)
            summary = runs.portable_summary(summary, REPO)
        except ValueError as err:
            raise SystemExit(f"collect: {run.name}: {err}") from None
        keep = {runs.WEIGHTS_FILE} if name in keep_weights else set()
        keep |= {runs.CHECKPOINT} if name in keep_checkpoint else set()
        tmp = target.with_name(f".{name}.tmp")
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
        _copy_run(run, tmp, name, config, summary, keep)
        tmp.rename(target)
        copied.append(name)
    return copied


def final_rollouts(run_dir: Path) -> pd.DataFrame:
    """The final evaluation's rollouts of a run (:data:`REPRODUCED_COLUMNS`), in a fixed order."""
    path = run_file(run_dir, runs.ROLLOUTS_FILE)
    if not path.is_file():
        return pd.DataFrame(columns=list(REPRODUCED_COLUMNS))
    df = pd.read_csv(path)
    cols = list(REPRODUCED_COLUMNS)
    return df[df["step"] == df["step"].max()][cols].sort_values(cols[:3]).reset_index(drop=True)


def reproduces(run_dir: Path, committed_dir: Path) -> tuple[bool, str]:
    """Whether a reproduced run's final per-rollout results equal the committed run's, and how many differ."""
    mine, theirs = final_rollouts(run_dir), final_rollouts(committed_dir)
    if mine.empty or theirs.empty:
        return False, "one of the two runs has no evaluation"
    if mine.shape != theirs.shape:
        return False, f"{len(mine)} rollouts against {len(theirs)}"
    differ = int((mine != theirs).any(axis=1).sum())
    return differ == 0, f"{differ} of {len(theirs)} rollouts differ"
