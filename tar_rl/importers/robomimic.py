"""robomimic / LIBERO HDF5 demonstrations into a tar-rl dataset folder.

The HDF5 layout read (robomimic's, which LIBERO's demonstration files share)::

    data/                        attrs: env_args (JSON), problem_info (JSON, LIBERO only)
        demo_0/
            obs/<key>            [T] or [T, d] low-dimensional observations (images are refused)
            next_obs/<key>       optional, [T, ...]: the observation after each step
            actions              [T, A], declared range [-1, 1]
            dones                [T] (optional; absent: only the last step ends the episode)
            rewards              [T] (optional; absent: zeros)
        demo_1/ ...
    mask/<filter>                optional: a list of demo names (bytes), e.g. "train", "valid"

Per step, ``observation`` is the concatenation of the chosen ``obs/<key>`` entries, each flattened
to ``[T, d]``, in the order given. ``action`` is the stored action (with ``clip=True`` clipped to
[-1, 1]; ``action_raw`` keeps it as stored). ``("next", "observation")`` comes from ``next_obs``
when the file holds every chosen key there, otherwise it is the following step's observation (the
last step's own observation at the end of an episode). ``("next", "terminated")`` is ``dones``;
``("next", "truncated")`` marks an episode's last step when ``dones`` does not. Demos are stored in
their natural order (``demo_2`` before ``demo_10``), or in the filter's order.

Tasks: one task per file, named by the stem of LIBERO's ``bddl_file_name`` attribute (LIBERO's own
task name, e.g. ``pick_up_the_black_bowl_next_to_the_ramekin_and_place_it_on_the_plate``; its
``problem_info.problem_name`` names the scene, shared by all tasks of a suite), else by
``problem_info.problem_name``, else robomimic's ``env_args.env_name``, else the file's stem. Files
with the same task name share a task id; ids follow the order in which the names first appear.

Every file is read and checked completely before anything is written: a missing key, ragged
arrays, a NaN or Inf, an action outside [-1, 1] (without ``clip``), an unknown or empty filter
raise :class:`DemoImportError` naming the file, the demo and the key. The dataset folder is then
written by :func:`tar_rl.data.write_dataset` (temporary folder, ``metadata.json`` last, rename).
"""

from __future__ import annotations

import argparse
import json
import os
import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from tar_rl import data as _data
from tar_rl.importers.common import (
    ACTION_RANGE,
    IMPORTERS,
    DemoImportError,
    Importer,
    check_action_range,
    fingerprint,
    import_folder,
    parse_keys,
)

__all__ = ["ACTION_RANGE", "NAME_PREFIX", "DemoImportError", "import_robomimic"]

NAME_PREFIX = "robomimic-"
ACTION_TARGET = "the stored action (declared range [-1, 1]); clipped to it only with clip=True; action_raw as stored"


def _natural_key(name: str) -> tuple:
    return tuple(int(p) if p.isdigit() else p for p in re.split(r"(\d+)", name))


def _json_attr(group, name: str, where: str):
    if name not in group.attrs:
        return None
    raw = group.attrs[name]
    if isinstance(raw, bytes):
        raw = raw.decode()
    try:
        return json.loads(raw)
    except (TypeError, ValueError) as err:
        raise DemoImportError(f"{where}: attribute {name!r} is not valid JSON: {err}") from err


def _read_array(demo, key: str, where: str, length: int | None) -> np.ndarray:
    """``demo[key]`` as a ``[T, d]`` float array, checked for existence, rank, length and finiteness."""
    if key not in demo:
        parent = key.rpartition("/")[0]
        group = demo[parent] if parent and parent in demo else demo
        have = sorted(group.keys()) if hasattr(group, "keys") else []
        raise DemoImportError(f"{where}: key {key!r} is missing (present: {have})")
    value = np.asarray(demo[key][()])
    if value.ndim == 0 or value.ndim > 2:
        raise DemoImportError(
            f"{where}: key {key!r} has shape {list(value.shape)}; only low-dimensional entries ([T] or [T, d]) "
            "can be imported"
        )
    if not (np.issubdtype(value.dtype, np.number) or value.dtype == bool):
        raise DemoImportError(f"{where}: key {key!r} has non-numeric dtype {value.dtype}")
    value = value.reshape(len(value), int(np.prod(value.shape[1:], dtype=np.int64)))  # [T, d], T = 0 included
    if length is not None and len(value) != length:
        raise DemoImportError(f"{where}: key {key!r} has {len(value)} steps, 'actions' has {length} (ragged arrays)")
    bad = ~np.isfinite(value.astype(np.float64))
    if bad.any():
        t = int(np.argwhere(bad)[0][0])
        raise DemoImportError(f"{where}: key {key!r} holds NaN or Inf (first at step {t})")
    return value


def _read_file(path: Path, keys: list[str], filter_key: str | None, clip: bool) -> dict:
    import h5py

    if not path.is_file():
        raise DemoImportError(f"{path}: no such file")
    try:
        f = h5py.File(path, "r")
    except OSError as err:
        raise DemoImportError(f"{path}: not a readable HDF5 file ({err})") from err
    with f:
        if "data" not in f:
            raise DemoImportError(f"{path}: no 'data' group (not a robomimic/LIBERO file)")
        group = f["data"]
        env_args = _json_attr(group, "env_args", f"{path}: data")
        problem_info = _json_attr(group, "problem_info", f"{path}: data")
        bddl = group.attrs.get("bddl_file_name") if problem_info else None
        if filter_key is not None:
            masks = sorted(f["mask"].keys()) if "mask" in f else []
            if filter_key not in masks:
                raise DemoImportError(f"{path}: filter {filter_key!r} not found (filters in the file: {masks})")
            names = [n.decode() if isinstance(n, bytes) else str(n) for n in np.asarray(f["mask"][filter_key][()])]
            if not names:
                raise DemoImportError(f"{path}: filter {filter_key!r} ('mask/{filter_key}') lists no demos")
            missing = [n for n in names if n not in group]
            if missing:
                raise DemoImportError(f"{path}: filter {filter_key!r} names demos not in 'data': {missing}")
        else:
            names = sorted(group.keys(), key=_natural_key)
            if not names:
                raise DemoImportError(f"{path}: 'data' holds no demos")
        demos = []
        for name in names:
            demo = group[name]
            where = f"{path}: demo {name!r}"
            actions = _read_array(demo, "actions", where, None).astype(np.float32)
            n = len(actions)
            if n == 0:
                raise DemoImportError(f"{where}: key 'actions' has no steps (empty episode)")
            obs = np.concatenate([_read_array(demo, f"obs/{k}", where, n) for k in keys], axis=1)
            if "next_obs" in demo and all(k in demo["next_obs"] for k in keys):
                next_obs = np.concatenate([_read_array(demo, f"next_obs/{k}", where, n) for k in keys], axis=1)
            else:
                next_obs = np.concatenate([obs[1:], obs[-1:]])
            dones = _read_array(demo, "dones", where, n)[:, 0] != 0 if "dones" in demo else np.zeros(n, bool)
            rewards = _read_array(demo, "rewards", where, n)[:, 0] if "rewards" in demo else np.zeros(n)
            target, clipped = check_action_range(actions, where, "actions", clip)
            demos.append(
                {
                    "name": name,
                    "observation": obs.astype(np.float32),
                    "next_observation": next_obs.astype(np.float32),
                    "action_raw": actions,
                    "action": target,
                    "reward": rewards.astype(np.float32),
                    "terminated": dones,
                    "clipped": clipped,
                }
            )
        dims = [int(np.prod(group[names[0]]["obs"][k].shape[1:], dtype=np.int64)) for k in keys]
    widths = {(d["observation"].shape[1], d["action"].shape[1]) for d in demos}
    if len(widths) != 1:
        raise DemoImportError(f"{path}: demos disagree on the observation/action widths {sorted(widths)}")
    if isinstance(bddl, bytes):
        bddl = bddl.decode()
    if bddl:  # LIBERO: the BDDL file names the task (problem_name is the scene, shared by a suite's tasks)
        task = Path(str(bddl).replace("\\", "/")).stem
    elif problem_info and problem_info.get("problem_name"):
        task = str(problem_info["problem_name"])
    elif env_args and env_args.get("env_name"):
        task = str(env_args["env_name"])
    else:
        task = path.stem
    instruction = (problem_info or {}).get("language_instruction")
    return {
        "path": path,
        "task": task,
        "instruction": instruction,
        "env_args": env_args,
        "problem_info": problem_info,
        "demos": demos,
        "dims": dims,
        "width": widths.pop(),
    }


def import_robomimic(
    paths: str | os.PathLike | Sequence[str | os.PathLike],
    obs_keys: str | Sequence[str],
    *,
    filter_key: str | None = None,
    out: str | os.PathLike = "data",
    chunk_horizon: int = 8,
    history: int = 2,
    clip: bool = False,
    verbose: bool = True,
) -> _data.DemoDataset:
    """Import robomimic/LIBERO HDF5 files as one tar-rl dataset folder under ``out``.

    The folder is ``out/robomimic-<stem>-<key>``, ``key`` a hash of the settings and of the
    files' paths, sizes and modification times: importing the same files with the same settings
    again loads the existing folder.

    Args:
        paths: one HDF5 file or several (one task per file, see the module docstring).
        obs_keys: the low-dimensional ``obs/<key>`` entries, concatenated in this order (a list,
            or one comma-separated string such as ``"robot0_eef_pos,robot0_eef_quat,object"``).
        filter_key: import only the demos listed in ``mask/<filter_key>``; ``None``: every demo.
        out: the folder holding datasets.
        chunk_horizon: ``H`` of ``action_chunk`` (``[H, A]`` per step).
        history: ``K`` of ``observation_history`` (``[K, D]`` per step).
        clip: clip actions outside [-1, 1] instead of refusing them.
        verbose: print a one-line summary.

    Returns:
        The imported :class:`~tar_rl.data.DemoDataset`.

    Raises:
        DemoImportError: bad input (the message names the file, demo and key); nothing is written.
    """
    files = [Path(paths)] if isinstance(paths, (str, os.PathLike)) else [Path(p) for p in paths]
    if not files:
        raise DemoImportError("no files to import")
    keys = parse_keys(obs_keys, "low-dimensional observation key")
    try:
        chunk_horizon = _data.positive_int("chunk_horizon", chunk_horizon)
        history = _data.positive_int("history", history)
    except ValueError as err:
        raise DemoImportError(str(err)) from None
    if filter_key is not None and not str(filter_key):
        raise DemoImportError("filter_key is empty: give a filter name (e.g. 'train') or None for every demo")

    sources = [_read_file(p, keys, filter_key, bool(clip)) for p in files]  # everything checked before writing
    widths = {s["width"] for s in sources}
    if len(widths) != 1:
        raise DemoImportError(f"the files disagree on (observation, action) widths: {sorted(widths)}")
    dims = {tuple(s["dims"]) for s in sources}
    if len(dims) != 1:
        raise DemoImportError(f"the files disagree on the widths of the keys {keys}: {sorted(dims)}")

    settings = {
        "source": "robomimic",
        "files": [fingerprint(p) for p in files],
        "obs_keys": keys,
        "filter": filter_key,
        "chunk_horizon": chunk_horizon,
        "history": history,
        "clip": bool(clip),
        "format_version": _data.FORMAT_VERSION,
    }

    def episodes() -> tuple[list[dict], dict]:
        eps = [{**d, "task": s["task"]} for s in sources for d in s["demos"]]
        return eps, _metadata(settings, keys, sources)

    return import_folder(out, NAME_PREFIX, files[0].stem, settings, episodes, verbose)


def _metadata(settings, keys, sources) -> dict:
    """The metadata entries particular to robomimic files (the common ones: ``importers.common``)."""
    dims = sources[0]["dims"]
    offsets = np.concatenate([[0], np.cumsum(dims)]).tolist()
    tasks = list(dict.fromkeys(s["task"] for s in sources))
    return {
        "instructions": {
            t: next((s["instruction"] for s in sources if s["task"] == t and s["instruction"]), None) for t in tasks
        },
        "per_task": {t: {"files": [str(s["path"]) for s in sources if s["task"] == t]} for t in tasks},
        "sources": [
            {
                "path": str(s["path"].resolve()),
                "task": s["task"],
                "filter": settings["filter"],
                "episodes": len(s["demos"]),
                "steps": int(sum(len(d["action"]) for d in s["demos"])),
                "demos": [d["name"] for d in s["demos"]],
                "clipped_action_entries": int(sum(d["clipped"] for d in s["demos"])),
                "env_args": s["env_args"],
                "problem_info": s["problem_info"],
            }
            for s in sources
        ],
        "obs_keys": [
            {"key": k, "dim": d, "slice": [offsets[i], offsets[i + 1]]} for i, (k, d) in enumerate(zip(keys, dims))
        ],
        "action_target": ACTION_TARGET,
        "versions": {"h5py": _data.package_version("h5py")},
    }


def _arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("files", nargs="+", metavar="FILE", help="HDF5 files, one task per file")
    parser.add_argument(
        "--obs-keys",
        required=True,
        help="obs/<key> entries to concatenate, in order (e.g. robot0_eef_pos,robot0_eef_quat,object)",
    )
    parser.add_argument("--filter", help="import only the demos of mask/<FILTER> (e.g. train); default: every demo")


IMPORTERS.register(
    "robomimic",
    Importer(
        "robomimic",
        "robomimic / LIBERO HDF5 files (low-dimensional observations)",
        _arguments,
        lambda args, **common: import_robomimic(args.files, args.obs_keys, filter_key=args.filter, **common),
    ),
)
