"""Tiny LeRobot datasets and configs written in the tests: nothing comes from a hub (the tests run offline)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

# Offline before LeRobot or huggingface_hub is imported: a test never reaches a hub.
os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("HF_DATASETS_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")
os.environ.setdefault("WANDB_MODE", "disabled")

STATE_DIM, ENV_DIM, ACTION_DIM, IMAGE_SIZE = 4, 2, 3, 32
#: Frames per episode of the tiny datasets.
EPISODE_LENGTHS = (12, 9, 15)


def write_dataset(root: Path, *, image: bool, lengths=EPISODE_LENGTHS, seed: int = 0) -> Path:
    """A LeRobotDataset of ``len(lengths)`` episodes of a smooth random walk: state and action, and an environment
    state or (``image``) an image ``observation.images.cam`` of ``IMAGE_SIZE`` pixels; task "push the cube"."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    features = {
        "observation.state": {"dtype": "float32", "shape": (STATE_DIM,), "names": None},
        "action": {"dtype": "float32", "shape": (ACTION_DIM,), "names": None},
    }
    if not image:  # ACT and Diffusion read an image or an environment state besides the robot's state
        features["observation.environment_state"] = {"dtype": "float32", "shape": (ENV_DIM,), "names": None}
    else:
        features["observation.images.cam"] = {
            "dtype": "image",
            "shape": (IMAGE_SIZE, IMAGE_SIZE, 3),
            "names": ["height", "width", "channels"],
        }
    dataset = LeRobotDataset.create(repo_id="local/tar_tiny", fps=10, features=features, root=root, use_videos=False)
    rng = np.random.default_rng(seed)
    for length in lengths:
        state = rng.normal(size=STATE_DIM).astype(np.float32)
        for _ in range(length):
            action = rng.normal(size=ACTION_DIM).astype(np.float32)
            frame = {"observation.state": state.copy(), "action": action, "task": "push the cube"}
            if not image:
                frame["observation.environment_state"] = state[:ENV_DIM] ** 2
            else:
                frame["observation.images.cam"] = rng.integers(0, 256, (IMAGE_SIZE, IMAGE_SIZE, 3), dtype=np.uint8)
            dataset.add_frame(frame)
            state = state + 0.1 * np.pad(action, (0, STATE_DIM - ACTION_DIM))
        dataset.save_episode()
    dataset.finalize()
    return root


@pytest.fixture(scope="session")
def state_dataset(tmp_path_factory) -> Path:
    return write_dataset(tmp_path_factory.mktemp("data") / "state", image=False)


@pytest.fixture(scope="session")
def image_dataset(tmp_path_factory) -> Path:
    return write_dataset(tmp_path_factory.mktemp("data") / "image", image=True)
