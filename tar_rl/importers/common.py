"""What the importers share: the error type, source fingerprints, the cached folder, the steps and the metadata.

An importer reads and checks every episode of its source first, as dicts of per-step arrays::

    {"name": str, "task": str, "observation": [T, D] float32, "next_observation": [T, D] float32,
     "action": [T, A] float32 (the target), "action_raw": [T, A] float32 (as stored),
     "reward": [T] float32, "terminated": [T] bool, "clipped": int}

then :func:`import_folder` writes them as one dataset folder (:func:`tar_rl.data.write_dataset`:
temporary folder, ``metadata.json`` last, rename), or loads the folder a previous import with the
same settings and sources wrote.
"""

from __future__ import annotations

import argparse
import shutil
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from tar_rl import data as _data
from tar_rl.objectives.registry import Registry

__all__ = [
    "ACTION_RANGE",
    "IMPORTERS",
    "DemoImportError",
    "Importer",
    "check_action_range",
    "fingerprint",
    "import_folder",
    "parse_keys",
]

#: The action range the policies and the evaluator assume (MetaWorld's action box).
ACTION_RANGE = (-1.0, 1.0)


class DemoImportError(ValueError):
    """Demonstrations cannot be imported (the message names the file or folder, the episode and the key)."""


@dataclass(frozen=True)
class Importer:
    """A registered format of ``tar-rl data import FORMAT``.

    Attributes:
        name: the format's name on the command line.
        help: one line for ``--help``.
        add_arguments: ``(parser)``: the format's own command-line arguments (the shared ones,
            ``--out``, ``--chunk-horizon``, ``--history``, ``--clip``, are added by the command).
        run: ``(args, out=, chunk_horizon=, history=, clip=)``: import what ``args`` names.
    """

    name: str
    help: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[..., object]


#: The importers by format name (``tar-rl data import FORMAT``).
IMPORTERS: Registry[Importer] = Registry("importer")


def fingerprint(path: Path) -> dict:
    """What identifies a source's content cheaply: its path, and size and mtime of the file (of every file in it)."""
    path = Path(path)
    if path.is_dir():
        files = sorted(p for p in path.rglob("*") if p.is_file())
        return {
            "path": str(path.resolve()),
            "files": [[str(p.relative_to(path)), p.stat().st_size, p.stat().st_mtime_ns] for p in files],
        }
    st = path.stat()
    return {"path": str(path.resolve()), "size": st.st_size, "mtime_ns": st.st_mtime_ns}


def parse_keys(obs_keys: str | Sequence[str], what: str) -> list[str]:
    """The observation keys of an import, from a list or one comma-separated string, in order.

    Raises:
        DemoImportError: no key, or a key named twice (``what`` says what a key is, for the message).
    """
    keys = [k.strip() for k in obs_keys.split(",")] if isinstance(obs_keys, str) else [str(k) for k in obs_keys]
    keys = [k for k in keys if k]
    if not keys:
        raise DemoImportError(f"obs_keys is empty: name at least one {what}")
    dup = sorted({k for k in keys if keys.count(k) > 1})
    if dup:
        raise DemoImportError(f"obs_keys names {dup} more than once")
    return keys


def check_action_range(action: np.ndarray, where: str, key: str, clip: bool) -> tuple[np.ndarray, int]:
    """``action`` clipped to :data:`ACTION_RANGE` and the number of entries outside it.

    Raises:
        DemoImportError: entries outside the range without ``clip`` (names the first one).
    """
    lo, hi = ACTION_RANGE
    outside = (action < lo) | (action > hi)
    if outside.any() and not clip:
        t, j = (int(i) for i in np.argwhere(outside)[0])
        raise DemoImportError(
            f"{where}: key {key!r} leaves the declared range [{lo:g}, {hi:g}] ({outside.sum()} entries, first at "
            f"step {t}, dim {j}: {action[t, j]:.6g}); pass clip=True (--clip) to clip them"
        )
    return np.clip(action, lo, hi), int(outside.sum())


def import_folder(
    out: str | Path,
    name_prefix: str,
    stem: str,
    settings: dict,
    read: Callable[[], tuple[list[dict], dict]],
    verbose: bool,
) -> _data.DemoDataset:
    """Load ``out/<name_prefix><stem>-<key>`` if it holds ``settings``; else ``read()`` and write it.

    ``key`` is a hash of ``settings`` (which include the sources' fingerprints). ``read()`` returns
    the checked episodes (module docstring) and the metadata entries particular to the source
    (``source``, ``settings``, ``tasks``, ``instructions``, the per-task counts, ...: see
    :func:`_metadata`); it runs before anything is written, so bad input leaves nothing behind.
    Tasks get ids in order of first appearance, unless the entries give ``task_names`` (a fixed task
    list: the id of a task is its index there).
    A folder left incomplete or stale by an earlier import is removed and written again.
    """
    key = _data.cache_key(settings)
    name = f"{name_prefix}{stem}-{key}"
    root = Path(out)
    final = root / name
    root.mkdir(parents=True, exist_ok=True)
    _data.clean_temp_siblings(root, name)
    if final.exists():
        try:
            found = _data.load_dataset(final)
            if found.metadata.get("settings") == settings:
                if verbose:
                    print(f"already imported: {final}")
                return found
            raise _data.DatasetError("its metadata describes other settings")
        except _data.DatasetError as err:
            print(f"dataset {final} is incomplete or stale ({err}); removing it and importing again")
            shutil.rmtree(final)
    start = time.perf_counter()
    episodes, extra = read()
    tasks = list(dict.fromkeys(ep["task"] for ep in episodes))
    names = extra.pop("task_names", None) or tasks
    ids = {t: names.index(t) for t in tasks}
    data = _steps(episodes, ids, settings["chunk_horizon"], settings["history"])
    metadata = _metadata(settings, key, names, ids, episodes, data, extra, time.perf_counter() - start)
    path = _data.write_dataset(root, name, data, metadata)
    dataset = _data.load_dataset(path)
    if verbose:
        print(f"imported {len(episodes)} episodes, {len(data)} steps, {len(tasks)} task(s) into {path}")
    return dataset


def _steps(episodes: Sequence[dict], ids: dict[str, int], chunk_horizon: int, history: int):
    lengths = np.array([len(ep["action"]) for ep in episodes], dtype=np.int64)
    ends = np.cumsum(lengths) - 1
    cat = {k: np.concatenate([ep[k] for ep in episodes]) for k in _STEP_KEYS}
    truncated = np.zeros(int(lengths.sum()), dtype=bool)
    truncated[ends] = ~cat["terminated"][ends]  # an episode that ends without terminating was cut
    task_id = np.concatenate([np.full(len(ep["action"]), ids[ep["task"]], np.int64) for ep in episodes])
    return _data.steps_tensordict(
        **cat, truncated=truncated, lengths=lengths, task_id=task_id, horizon=chunk_horizon, history=history
    )


_STEP_KEYS = ("observation", "next_observation", "action", "action_raw", "reward", "terminated")


def _metadata(settings, key, names, ids, episodes, data, extra, secs) -> dict:
    import tar_rl

    tasks = list(ids)
    per_task = {}
    for task in tasks:
        lengths = [len(ep["action"]) for ep in episodes if ep["task"] == task]
        per_task[task] = {
            "task_id": ids[task],
            "instruction": (extra.get("instructions") or {}).get(task),
            "episodes": len(lengths),
            "kept": len(lengths),
            "steps": int(sum(lengths)),
            "episode_lengths": lengths,
        }
    meta = {
        "format_version": _data.FORMAT_VERSION,
        "source": settings["source"],
        "cache_key": key,
        "settings": settings,
        "tasks": tasks,
        "task_ids": {task: p["task_id"] for task, p in per_task.items()},
        "task_names": list(names),
        "instructions": {task: p["instruction"] for task, p in per_task.items()},
        "per_task": per_task,
        "total_steps": int(data.shape[0]),
        "total_episodes": len(episodes),
        "clipped_action_entries": int(sum(ep["clipped"] for ep in episodes)),
        "chunk_horizon": settings["chunk_horizon"],
        "history": settings["history"],
        "image_size": 0,
        "action_range": list(ACTION_RANGE),
        "stats": {
            "observation": _data.array_stats(data["observation"].numpy()),
            "action": _data.array_stats(data["action"].numpy()),
            "action_raw": _data.array_stats(data["action_raw"].numpy()),
        },
        "versions": {
            "tar_rl": tar_rl.__version__,
            "torch": torch.__version__,
            "torchrl": _data.package_version("torchrl"),
            "tensordict": _data.package_version("tensordict"),
            "numpy": np.__version__,
        },
        "import_seconds": secs,
        "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    extra = {k: v for k, v in extra.items() if k != "instructions"}
    per_task_extra = extra.pop("per_task", {})
    for task, more in per_task_extra.items():
        meta["per_task"][task].update(more)
    versions = extra.pop("versions", {})
    meta["versions"].update(versions)
    meta.update(extra)
    return meta
