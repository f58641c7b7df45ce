"""``tar-rl data info PATH``: a summary of any tar-rl dataset folder (MetaWorld or imported)."""

from __future__ import annotations

import os

import numpy as np

from tar_rl import data as _data

__all__ = ["dataset_info", "format_info"]


def dataset_info(path: str | os.PathLike) -> dict:
    """Episodes, steps, stored entries, action range and per-task counts of the dataset at ``path``.

    Counts and ranges are computed from the stored steps (not copied from the metadata).

    Raises:
        tar_rl.data.DatasetError: ``path`` is not a complete dataset folder.
    """
    ds = _data.load_dataset(path)
    td = ds.data
    episode = td["episode"].numpy()
    task_id = td["task_id"].numpy()
    action = td["action"].numpy()
    names = {int(i): n for n, i in ds.metadata.get("task_ids", {}).items()}
    per_task = {}
    for t in np.unique(task_id):
        rows = task_id == t
        per_task[names.get(int(t), f"task {int(t)}")] = {
            "task_id": int(t),
            "episodes": len(np.unique(episode[rows])),
            "steps": int(rows.sum()),
        }
    return {
        "path": str(ds.path),
        "source": ds.metadata.get("source", "metaworld"),
        "episodes": len(np.unique(episode)),
        "steps": len(ds),
        "chunk_horizon": ds.metadata.get("chunk_horizon"),
        "history": ds.metadata.get("history"),
        "keys": {k: {"shape": v["shape"], "dtype": v["dtype"]} for k, v in ds.metadata["keys"].items()},
        "action_min": action.min(0).tolist() if len(action) else [],
        "action_max": action.max(0).tolist() if len(action) else [],
        "per_task": per_task,
    }


def format_info(info: dict) -> str:
    """The human-readable text of :func:`dataset_info`."""
    lines = [
        f"dataset: {info['path']}",
        f"source: {info['source']}",
        f"episodes: {info['episodes']}",
        f"steps: {info['steps']}",
        f"chunk_horizon: {info['chunk_horizon']}  history: {info['history']}",
        "keys:",
    ]
    width = max(len(k) for k in info["keys"])
    for k, v in info["keys"].items():
        lines.append(f"  {k:<{width}}  {v['dtype']:<8} {v['shape']}")
    fmt = lambda xs: "[" + ", ".join(f"{x:.4g}" for x in xs) + "]"  # noqa: E731
    lines.append(f"action min: {fmt(info['action_min'])}")
    lines.append(f"action max: {fmt(info['action_max'])}")
    lines.append("tasks (task_id  episodes  steps  name):")
    for name, p in info["per_task"].items():
        lines.append(f"  {p['task_id']:>7}  {p['episodes']:>8}  {p['steps']:>5}  {name}")
    return "\n".join(lines)
