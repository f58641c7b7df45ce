"""tar-rl demonstrations as a LeRobotDataset: ``lerobot-tar export-dataset FOLDER ROOT``.

A tar-rl dataset folder (format 4; MetaWorld's demonstrations from ``tar_rl.collectors.metaworld.dataset``, or any
import) is read as data (:mod:`.tar_dataset`: checked as tar-rl checks it, refused with tar-rl's messages) and
written with LeRobot's own writer (``LeRobotDataset.create``, ``add_frame``, ``save_episode``, ``finalize``):

* ``observation.state``: the first ``state_dims`` values of tar-rl's ``observation`` (MetaWorld: 4, the hand's
  position and the gripper's opening, the ``agent_pos`` of LeRobot's own MetaWorld environment);
  ``observation.environment_state``: the rest (MetaWorld: the objects, the previous frame and the goal), which ACT
  and Diffusion need besides the state when there is no image. Without a known split the whole observation is
  ``observation.state``.
* ``action``: tar-rl's ``action``, the supervision target (MetaWorld: the expert's action clipped to [-1, 1]).
* one LeRobot episode per tar-rl episode, in storage order; each frame's ``task`` is its task's instruction (the
  task's name where the dataset has none); ``fps`` from the source (MetaWorld: 80, its control rate) or given.

The dataset is written in a temporary sibling folder and renamed into place when complete: a failed export leaves
nothing at ``ROOT``, and an existing LeRobotDataset there is replaced only when asked (``overwrite``), after the new
one is complete. Images are not exported (tar-rl's ``pixels``): state-based policies only.
"""

from __future__ import annotations

import os
import shutil
import uuid
from pathlib import Path

import numpy as np

from .tar_dataset import DatasetError, TarDataset, read_tar_dataset

__all__ = ["SOURCE_FPS", "SOURCE_STATE_DIMS", "DatasetError", "ExportError", "export_dataset", "plan_export"]

#: Frames per second of the sources whose rate is fixed: MetaWorld steps MuJoCo's 2.5 ms five times per action
#: (80 Hz, the ``fps`` of LeRobot's own MetaWorld environment).
SOURCE_FPS = {"metaworld": 80}
#: How many leading observation values are the robot's state, per source: MetaWorld's hand position (3) and
#: gripper opening (1), LeRobot's MetaWorld ``agent_pos`` (``raw_obs[:4]``).
SOURCE_STATE_DIMS = {"metaworld": 4}
#: LeRobot's metadata file, by which an existing folder is known as a LeRobotDataset.
LEROBOT_INFO = Path("meta") / "info.json"


class ExportError(ValueError):
    """An export that cannot be done as asked (the target folder, the settings, the dataset's entries)."""


def _check_target(root: Path, overwrite: bool) -> None:
    if not root.exists():
        return
    if (root / LEROBOT_INFO).is_file():
        if not overwrite:
            raise ExportError(
                f"{root} already holds a LeRobotDataset: choose another folder, or pass --overwrite to replace it "
                "(the new one replaces it only once complete)"
            )
        return
    if root.is_dir() and not any(root.iterdir()):
        return
    raise ExportError(f"{root} exists and is not a LeRobotDataset (no {LEROBOT_INFO}): choose another folder")


def _float_entry(data: TarDataset, name: str) -> np.ndarray:
    value = data.arrays.get(name)
    if value is None or not value.dtype.is_floating_point or value.dim() != 2:
        spec = data.metadata["keys"].get(name)
        raise ExportError(f"{data.path}: entry {name!r} is {spec!r}; the export needs one float vector per step")
    return value.float().numpy()


def _episode_bounds(data: TarDataset) -> list[tuple[int, int]]:
    """``[(start, stop), ...]``: the runs of equal ``episode`` ids, in storage order; each id in one run."""
    episode = data.arrays["episode"].numpy()
    starts = np.flatnonzero(np.r_[True, episode[1:] != episode[:-1]])
    stops = np.r_[starts[1:], len(episode)]
    seen = set()
    for start in starts.tolist():
        if int(episode[start]) in seen:
            raise ExportError(
                f"{data.path}: entry 'episode' is {int(episode[start])} again at step {start}, after other "
                "episodes; an episode's steps must be contiguous"
            )
        seen.add(int(episode[start]))
    return [(int(a), int(b)) for a, b in zip(starts, stops, strict=True)]


def plan_export(data: TarDataset, *, fps: int | None = None, state_dims: int | None = None) -> dict:
    """What :func:`export_dataset` writes for ``data``: ``fps``, ``state_dims``, the LeRobot ``features``, the
    episodes' ``bounds`` and each step's ``tasks`` (its text); ``ExportError`` for what cannot be exported."""
    source = data.metadata["source"]
    if fps is None:
        fps = SOURCE_FPS.get(source)
        if fps is None:
            raise ExportError(
                f"{data.path}: the frame rate of its source {source!r} is not known here: pass --fps "
                "(the rate at which its steps were recorded)"
            )
    if isinstance(fps, bool) or not isinstance(fps, int) or fps < 1:
        raise ExportError(f"fps must be an integer >= 1, got {fps!r}")
    observation = _float_entry(data, "observation")
    action = _float_entry(data, "action")
    dims = observation.shape[1]
    if state_dims is None:
        state_dims = min(SOURCE_STATE_DIMS.get(source, dims), dims)
    if isinstance(state_dims, bool) or not isinstance(state_dims, int) or not 1 <= state_dims <= dims:
        raise ExportError(f"state_dims must be an integer in 1..{dims} (the observation's size), got {state_dims!r}")
    features = {
        "observation.state": {"dtype": "float32", "shape": (state_dims,), "names": None},
        "action": {"dtype": "float32", "shape": (action.shape[1],), "names": None},
    }
    if state_dims < dims:
        features["observation.environment_state"] = {"dtype": "float32", "shape": (dims - state_dims,), "names": None}
    names = data.metadata["task_names"]
    texts = data.metadata.get("instructions", {})
    task_text = [texts.get(name) or name for name in names]
    tasks = [task_text[i] for i in data.arrays["task_id"].tolist()]
    return {
        "fps": fps,
        "state_dims": state_dims,
        "features": features,
        "bounds": _episode_bounds(data),
        "tasks": tasks,
        "observation": observation,
        "action": action,
    }


def export_dataset(
    source: str | os.PathLike,
    root: str | os.PathLike,
    *,
    repo_id: str | None = None,
    fps: int | None = None,
    state_dims: int | None = None,
    overwrite: bool = False,
) -> Path:
    """Write the tar-rl dataset folder ``source`` as a LeRobotDataset at ``root``.

    Args:
        source: a tar-rl dataset folder (format 4, sealed).
        root: the LeRobotDataset's folder (``--dataset.root`` of ``lerobot-train``).

    Keyword Args:
        repo_id: the dataset's ``repo_id`` (``--dataset.repo_id``); default ``local/<root's name>``.
        fps: frames per second; default the source's (MetaWorld 80), required for other sources.
        state_dims: the leading observation values that are the robot's state; default the source's (MetaWorld 4),
            else all of them.
        overwrite: replace a LeRobotDataset already at ``root`` (only once the new one is complete).

    Returns:
        ``root``.

    Raises:
        DatasetError: ``source`` is not a sealed format-4 tar-rl dataset folder or fails tar-rl's checks.
        ExportError: ``root`` holds a LeRobotDataset (without ``overwrite``) or something else; a setting or an
            entry the export cannot use. Nothing is written in either case.
    """
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    root = Path(root)
    _check_target(root, overwrite)
    plan = plan_export(read_tar_dataset(source), fps=fps, state_dims=state_dims)
    repo_id = repo_id or f"local/{root.name}"
    root.parent.mkdir(parents=True, exist_ok=True)
    tmp = root.parent / f".{root.name}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    old = root.parent / f".{root.name}.old-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    k, observation, action, tasks = plan["state_dims"], plan["observation"], plan["action"], plan["tasks"]
    moved = False  # True while an existing dataset at root lies at old
    try:
        dataset = LeRobotDataset.create(repo_id, plan["fps"], plan["features"], root=tmp, use_videos=False)
        for start, stop in plan["bounds"]:
            for step in range(start, stop):
                frame = {"observation.state": observation[step, :k], "action": action[step], "task": tasks[step]}
                if "observation.environment_state" in plan["features"]:
                    frame["observation.environment_state"] = observation[step, k:]
                dataset.add_frame(frame)
            dataset.save_episode()
        dataset.finalize()
        if root.exists():  # checked above: an empty folder, or a LeRobotDataset to replace
            os.rename(root, old)
            moved = True
        os.rename(tmp, root)
        moved = False
    finally:
        if moved:  # the new dataset did not take its place: the old one goes back
            os.rename(old, root)
        shutil.rmtree(tmp, ignore_errors=True)
        shutil.rmtree(old, ignore_errors=True)
    return root
