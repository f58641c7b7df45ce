"""LeRobot datasets on local disk into a tar-rl dataset folder.

Two sources are read, both mapped onto TorchRL's canonical VLA keys first
(:func:`torchrl.data.datasets.lerobot.lerobot_columns_to_tensordict`):

* a LeRobot dataset folder (format v3.x, or v2.x), as the hub holds it::

      meta/info.json              codebase_version, fps, features
      meta/tasks.parquet          the task strings (index or ``task`` column) and ``task_index``
                                  (v2.x: meta/tasks.jsonl)
      data/**/*.parquet           one row per frame: observation.state, action, episode_index,
                                  frame_index, task_index, [next.reward, next.done, ...]

  read with pandas (pyarrow); the ``task`` instruction of each frame is joined from
  ``task_index``;
* the memory-mapped copy that TorchRL's ``LeRobotExperienceReplay(repo_id, root=ROOT,
  download=True)`` leaves in ``ROOT/<repo_id with / as _>`` (tensordict's memmap layout: a
  ``meta.json`` per folder naming each entry's element type and shape, one ``<entry>.memmap`` of
  raw bytes per tensor, the instructions as JSON text in their folder's ``meta.json``). It is read
  here from those files, not through tensordict's ``load_memmap`` (which unpickles a field stored
  as ``pickle.pkl``): element types from a fixed list, entry names of letters, digits, ``_`` and
  ``-``, exact file sizes, no symbolic links; a pickled field or any other kind of entry is refused.

Mapping (LeRobot column -> TorchRL canonical key -> tar-rl entry): the chosen state columns
(default ``observation.state``; several are concatenated in the order given) -> ``observation``;
``action`` -> ``action`` (checked against [-1, 1], clipped only with ``clip=True``; ``action_raw``
keeps it as stored); ``episode_index`` -> ``episode``; ``frame_index`` -> ``frame`` (each
episode's frames must run 0, 1, 2, ... in storage order); ``task`` -> ``language_instruction``
-> the task (one per distinct instruction, in order of appearance; the instruction is the task's
name and its instruction text); ``next.reward`` -> ``reward`` (zeros if absent); ``next.done`` ->
``("next", "terminated")`` (absent: False; an episode whose last frame is not done is marked
``truncated`` there). ``("next", "observation")`` is the following frame's observation (the last
frame's own at the end of an episode). Action chunks and observation windows are rebuilt from the
episodes (:func:`tar_rl.data.steps_tensordict`), so their padding flags mean what they mean for
MetaWorld datasets. Image and video columns are refused (state-only import).

Every frame is checked before anything is written: a missing column, ragged rows, NaN or Inf,
actions outside [-1, 1] (without ``clip``), frames missing or out of order within an episode, an
episode whose instruction changes, raise :class:`DemoImportError` naming the episode and the column.
"""

from __future__ import annotations

import argparse
import json
import os
import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from tar_rl import data as _data
from tar_rl.importers.common import (
    IMPORTERS,
    DemoImportError,
    Importer,
    check_action_range,
    fingerprint,
    import_folder,
    parse_keys,
)
from tar_rl.io import read_json_object

__all__ = ["NAME_PREFIX", "import_lerobot"]

NAME_PREFIX = "lerobot-"
ACTION_TARGET = "the stored action (declared range [-1, 1]); clipped to it only with clip=True; action_raw as stored"
# LeRobot column -> TorchRL canonical key (torchrl.data.datasets.lerobot's default key map).
_EPISODE, _FRAME, _TASK = "episode", "frame", "language_instruction"
_REWARD, _DONE = ("next", "reward"), ("next", "done")


_CANONICAL = {
    "episode_index": _EPISODE,
    "frame_index": _FRAME,
    "task": _TASK,
    "next.reward": _REWARD,
    "next.done": _DONE,
}


def _canonical(column: str):
    """The canonical key of a LeRobot column (TorchRL's default key map; other dotted names nest)."""
    if column in _CANONICAL:
        return _CANONICAL[column]
    return tuple(column.split(".")) if "." in column else column


def _parse_columns(obs_keys: str | Sequence[str]) -> list[str]:
    keys = parse_keys(obs_keys, "state column (e.g. observation.state)")
    images = [k for k in keys if k.startswith("observation.images.") or k.startswith("observation.image")]
    if images:
        raise DemoImportError(f"obs_keys {images} are images or videos; only state columns can be imported")
    return keys


def _torchrl_lerobot():
    """``torchrl.data.datasets.lerobot``, imported without torchrl 0.14.1's warning about its own collectors."""
    import warnings

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", "Creating .* which inherits from WeightUpdaterBase", DeprecationWarning)
        from torchrl.data.datasets import lerobot
    return lerobot


def _read_folder(path: Path, columns: list[str]):
    """A LeRobot v2.x/v3.x folder's frames as TorchRL's canonical ``[N]`` TensorDict (module docstring)."""
    import pandas as pd

    lerobot_columns_to_tensordict = _torchrl_lerobot().lerobot_columns_to_tensordict
    try:
        info = json.loads((path / "meta" / "info.json").read_text())
    except (OSError, ValueError) as err:
        raise DemoImportError(f"{path}: meta/info.json cannot be read: {err}") from err
    version = str(info.get("codebase_version", "?"))
    if version.lstrip("v").split(".")[0] not in ("2", "3"):
        raise DemoImportError(f"{path}: LeRobot format {version!r} is not supported (v2.x and v3.x are)")
    files = sorted((path / "data").rglob("*.parquet"))
    if not files:
        raise DemoImportError(f"{path}: no data/**/*.parquet files")
    try:
        frames = pd.concat([pd.read_parquet(f) for f in files], ignore_index=True)
    except Exception as err:  # pyarrow raises several kinds for damaged files
        raise DemoImportError(f"{path}: the data parquet files cannot be read: {type(err).__name__}: {err}") from err
    if "index" in frames:
        frames = frames.sort_values("index", kind="stable").reset_index(drop=True)
    for col in ("episode_index", *columns):
        if col not in frames:
            raise DemoImportError(f"{path}: column {col!r} is missing (present: {sorted(frames.columns)})")
    tasks = _tasks_table(path)
    out = {"episode_index": frames["episode_index"].to_numpy(np.int64)}
    for col in ("frame_index", "next.reward", "next.done"):
        if col in frames:
            out[col] = frames[col].to_numpy()
    for col in columns:
        out[col] = _stack(frames[col], col, out["episode_index"], path)
    if "task_index" in frames:
        index = frames["task_index"].to_numpy(np.int64)
        unknown = sorted(set(index.tolist()) - set(tasks))
        if unknown:
            raise DemoImportError(f"{path}: task_index {unknown} not in the task table (meta/tasks.*)")
        out["task"] = [tasks[i] for i in index.tolist()]
    elif "task" in frames:
        out["task"] = [str(t) for t in frames["task"]]
    columns_td = {k: (v if isinstance(v, list) else torch.from_numpy(np.array(v))) for k, v in out.items()}
    return lerobot_columns_to_tensordict(columns_td), {"format": version, "fps": info.get("fps")}


def _tasks_table(path: Path) -> dict[int, str]:
    import pandas as pd

    meta = path / "meta"
    if (meta / "tasks.parquet").is_file():
        df = pd.read_parquet(meta / "tasks.parquet")
        text = df["task"] if "task" in df else pd.Series(df.index, index=df.index)
        return {int(i): str(t) for i, t in zip(df["task_index"], text)}
    if (meta / "tasks.jsonl").is_file():
        rows = [json.loads(line) for line in (meta / "tasks.jsonl").read_text().splitlines() if line.strip()]
        return {int(r["task_index"]): str(r["task"]) for r in rows}
    return {}


def _stack(series, column: str, episodes: np.ndarray, path: Path) -> np.ndarray:
    """A column of per-frame lists (or scalars) as ``[N, d]`` float64; ragged rows are refused."""
    values = series.to_list()
    if values and np.ndim(values[0]) == 0:
        return np.asarray(values, dtype=np.float64).reshape(-1, 1)
    widths = np.array([np.size(v) for v in values])
    bad = np.flatnonzero(widths != widths[0]) if len(widths) else []
    if len(bad):
        row = int(bad[0])
        raise DemoImportError(
            f"{path}: episode {int(episodes[row])}: column {column!r} has rows of {widths[row]} and {widths[0]} "
            "values (ragged arrays)"
        )
    return np.stack([np.asarray(v, dtype=np.float64).reshape(-1) for v in values]) if values else np.zeros((0, 1))


# tensordict's own entries in a memmap folder's meta.json, beside the stored keys (not read).
_TD_SETTINGS = ("shape", "device", "_type", "names")
_COPY_KEY = re.compile(r"[A-Za-z0-9_-]+")


def _read_torchrl_cache(path: Path):
    """The memory-mapped copy TorchRL's ``LeRobotExperienceReplay`` made, read from its files (module docstring)."""
    if not (path / "meta.json").is_file():
        raise DemoImportError(
            f"{path}: not a TorchRL LeRobot copy (no meta.json) nor a LeRobot folder (no meta/info.json)"
        )
    return _read_memmap_folder(path, None), {"format": "torchrl-lerobot-memmap"}


def _copy_json(file: Path) -> dict:
    if file.is_symlink() or not file.is_file():
        raise DemoImportError(f"{file}: missing or not a plain file (a TorchRL LeRobot copy)")
    return read_json_object(file, "a JSON object", DemoImportError)


def _read_memmap_folder(folder: Path, frames: int | None):
    """One folder of tensordict's memmap layout as a TensorDict of private memory maps and lists of text."""
    from tensordict import NonTensorStack, TensorDict

    meta_file = folder / "meta.json"
    meta = _copy_json(meta_file)
    shape = meta.get("shape")
    if not (isinstance(shape, list) and len(shape) == 1 and type(shape[0]) is int and shape[0] >= 0):
        raise DemoImportError(f"{meta_file}: shape is {shape!r}, not one number of frames")
    n = shape[0]
    if frames is not None and n != frames:
        raise DemoImportError(f"{meta_file}: {n} frames, the folder above holds {frames}")
    out = TensorDict(batch_size=[n])
    for key, entry in meta.items():
        if key in _TD_SETTINGS:
            continue
        if not _COPY_KEY.fullmatch(key) or not isinstance(entry, dict):
            raise DemoImportError(f"{meta_file}: entry {key!r} is not read (names of letters, digits, _ and -)")
        kind = entry.get("type")
        if kind == "TensorDict":
            if (folder / key).is_symlink():
                raise DemoImportError(f"{folder / key} is a symbolic link; a copy holds plain folders only")
            out.set(key, _read_memmap_folder(folder / key, n))
        elif kind == "NonTensorStack":
            texts = _copy_json(folder / key / "meta.json").get("data")
            if not (isinstance(texts, list) and len(texts) == n and all(isinstance(t, str) for t in texts)):
                raise DemoImportError(
                    f"{folder / key / 'meta.json'}: entry {key!r} is not {n} texts in JSON (a pickled or other "
                    "non-tensor field is not read)"
                )
            out.set(key, NonTensorStack.from_list(texts))
        elif kind is None and "dtype" in entry:
            out.set(key, _read_copy_tensor(folder, key, entry, n, meta_file))
        else:
            raise DemoImportError(f"{meta_file}: entry {key!r} is a {kind!r}, not read (tensors and texts only)")
    return out


def _read_copy_tensor(folder: Path, key: str, entry: dict, n: int, meta_file: Path) -> torch.Tensor:
    dtype = _data.DTYPES.get(str(entry["dtype"]).removeprefix("torch."))
    shape = entry.get("shape")
    ok_shape = isinstance(shape, list) and shape[:1] == [n] and all(type(d) is int and d >= 0 for d in shape)
    if dtype is None or not ok_shape or entry.get("is_nested"):
        raise DemoImportError(
            f"{meta_file}: entry {key!r} ({entry.get('dtype')!r}, shape {shape!r}) is not read: a tensor of "
            f"{n} frames of one of {list(_data.DTYPES)} is"
        )
    file = folder / f"{key}.memmap"
    numel = int(np.prod(shape, dtype=np.int64))
    need = numel * torch.empty((), dtype=dtype).element_size()
    if file.is_symlink() or not file.is_file() or file.stat().st_size != need:
        size = file.stat().st_size if file.is_file() else None
        raise DemoImportError(f"{file}: missing, linked or of {size} bytes; {need} expected for entry {key!r}")
    # A private map: the copy's file is never written.
    return torch.from_file(str(file), shared=False, size=numel, dtype=dtype).reshape(shape)


def _keys(td) -> set:
    """Every leaf key of ``td``, strings and string lists (``NonTensorStack``) included."""
    return {k if isinstance(k, str) else tuple(k) for k in td.keys(True, True, is_leaf=_is_leaf)}


def _is_leaf(cls) -> bool:
    from tensordict import NonTensorStack, TensorDictBase

    return issubclass(cls, NonTensorStack) or not issubclass(cls, TensorDictBase)


def _episodes(td, columns: list[str], action_key: str, clip: bool, where: str) -> list[dict]:
    """Split the canonical TensorDict into checked episodes (``importers.common``'s format)."""
    keys = _keys(td)

    def need(column: str):
        key = _canonical(column)
        if key not in keys:
            present = sorted(".".join(k) if isinstance(k, tuple) else k for k in keys)
            raise DemoImportError(f"{where}: column {column!r} is missing (present: {present})")
        return td.get(key)

    episode = need("episode_index").reshape(-1).numpy().astype(np.int64)
    obs = np.concatenate([need(c).reshape(len(episode), -1).double().numpy() for c in columns], axis=1)
    action = need(action_key).reshape(len(episode), -1).double().numpy()
    frame = td.get(_FRAME).reshape(-1).numpy().astype(np.int64) if _FRAME in keys else None
    reward = td.get(_REWARD).reshape(-1).double().numpy() if _REWARD in keys else np.zeros(len(episode))
    # Compared with 0 rather than cast: a stored bool byte other than 0 or 1 still reads as done.
    done = (td.get(_DONE).reshape(-1).to(torch.int64) != 0).numpy() if _DONE in keys else np.zeros(len(episode), bool)
    text = list(td.get(_TASK).tolist()) if _TASK in keys else None
    if len(episode) == 0:
        raise DemoImportError(f"{where}: the dataset holds no frames")
    starts = np.flatnonzero(np.r_[True, episode[1:] != episode[:-1]])
    ids = episode[starts]
    if len(set(ids.tolist())) != len(ids):
        e = int(ids[next(i for i, x in enumerate(ids) if x in ids[:i])])
        raise DemoImportError(f"{where}: episode {e}: its frames are not contiguous in storage order")
    out = []
    for a, b in zip(starts, np.r_[starts[1:], len(episode)]):
        e = int(episode[a])
        here = f"{where}: episode {e}"
        if frame is not None and not np.array_equal(frame[a:b], np.arange(b - a)):
            t = int(np.flatnonzero(frame[a:b] != np.arange(b - a))[0])
            raise DemoImportError(
                f"{here}: column 'frame_index' is {int(frame[a + t])} at its frame {t} (frames missing or out of order)"
            )
        for column, values in (*((c, obs[a:b]) for c in columns), (action_key, action[a:b])):
            bad = ~np.isfinite(values)
            if bad.any():
                raise DemoImportError(
                    f"{here}: column {column!r} holds NaN or Inf (first at frame {int(np.argwhere(bad)[0][0])})"
                )
        if not np.isfinite(reward[a:b]).all():
            raise DemoImportError(f"{here}: column 'next.reward' holds NaN or Inf")
        task = "default"
        if text is not None:
            names = set(text[a:b])
            if len(names) != 1:
                raise DemoImportError(f"{here}: column 'task' changes within the episode: {sorted(names)}")
            task = names.pop()
        target, clipped = check_action_range(action[a:b].astype(np.float32), here, action_key, clip)
        o = obs[a:b].astype(np.float32)
        out.append(
            {
                "name": f"episode_{e}",
                "task": task,
                "observation": o,
                "next_observation": np.concatenate([o[1:], o[-1:]]),
                "action": target,
                "action_raw": action[a:b].astype(np.float32),
                "reward": reward[a:b].astype(np.float32),
                "terminated": done[a:b],
                "clipped": clipped,
            }
        )
    return out


def import_lerobot(
    path: str | os.PathLike,
    obs_keys: str | Sequence[str] = "observation.state",
    *,
    action_key: str = "action",
    out: str | os.PathLike = "data",
    chunk_horizon: int = 8,
    history: int = 2,
    clip: bool = False,
    verbose: bool = True,
) -> _data.DemoDataset:
    """Import a LeRobot dataset on local disk as a tar-rl dataset folder under ``out``.

    The folder is ``out/lerobot-<name>-<key>``, ``key`` a hash of the settings and of the source
    files' paths, sizes and modification times: the same import again loads it.

    Args:
        path: a LeRobot dataset folder (``meta/info.json``, ``data/``), or the folder TorchRL's
            ``LeRobotExperienceReplay`` converted it into (module docstring).
        obs_keys: the state columns that make the observation, concatenated in this order (a
            list, or one comma-separated string).
        action_key: the action column.
        out: the folder holding datasets.
        chunk_horizon: ``H`` of ``action_chunk``.
        history: ``K`` of ``observation_history``.
        clip: clip actions outside [-1, 1] instead of refusing them.
        verbose: print a one-line summary.

    Raises:
        DemoImportError: bad input (the message names the episode and column); nothing is written.
    """
    path = Path(path)
    columns = _parse_columns(obs_keys)
    try:
        chunk_horizon = _data.positive_int("chunk_horizon", chunk_horizon)
        history = _data.positive_int("history", history)
    except ValueError as err:
        raise DemoImportError(str(err)) from None
    if not path.is_dir():
        raise DemoImportError(f"{path}: no such folder")
    lerobot_folder = (path / "meta" / "info.json").is_file()
    settings = {
        "source": "lerobot",
        "files": fingerprint(path),
        "obs_keys": columns,
        "action_key": action_key,
        "chunk_horizon": chunk_horizon,
        "history": history,
        "clip": bool(clip),
        "format_version": _data.FORMAT_VERSION,
    }

    def read() -> tuple[list[dict], dict]:
        td, about = _read_folder(path, [*columns, action_key]) if lerobot_folder else _read_torchrl_cache(path)
        episodes = _episodes(td, columns, action_key, bool(clip), str(path))
        widths = [int(np.prod(td.get(_canonical(c)).shape[1:], dtype=np.int64)) for c in columns]
        offsets = np.concatenate([[0], np.cumsum(widths)]).tolist()
        tasks = list(dict.fromkeys(ep["task"] for ep in episodes))
        return episodes, {
            "instructions": {t: t for t in tasks} if _TASK in _keys(td) else {},
            "lerobot": {"path": str(path.resolve()), **about},
            "obs_keys": [
                {"key": c, "dim": d, "slice": [offsets[i], offsets[i + 1]]}
                for i, (c, d) in enumerate(zip(columns, widths))
            ],
            "action_target": ACTION_TARGET,
        }

    return import_folder(out, NAME_PREFIX, path.name, settings, read, verbose)


def _arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("folder", help="the dataset folder (meta/info.json, data/), or TorchRL's converted copy")
    parser.add_argument(
        "--obs-keys",
        default="observation.state",
        help="state columns to concatenate, in order (default: observation.state)",
    )
    parser.add_argument("--action-key", default="action", help="the action column (default: action)")


IMPORTERS.register(
    "lerobot",
    Importer(
        "lerobot",
        "a LeRobot dataset on local disk (v3.x / v2.x, or TorchRL's copy of one)",
        _arguments,
        lambda args, **common: import_lerobot(args.folder, args.obs_keys, action_key=args.action_key, **common),
    ),
)
