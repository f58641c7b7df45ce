"""Helpers shared by the recipe tests: compose a config as `tar-rl train` does, and a tiny job."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

from hydra import compose, initialize

from tar_rl.recipes import resolve_config
from tar_rl.recipes.config import register_configs
from tar_rl.runs import CHECKPOINT

TASK = "reach"


def compose_config(*overrides: str) -> dict:
    register_configs()
    with initialize(version_base="1.3", config_path=None):
        return resolve_config(compose(config_name="train", overrides=list(overrides)))


def tiny(tmp_path: Path, data_root: Path, *overrides: str) -> dict:
    """A 30-step job on the shared tiny dataset (``data_root``), evaluated with one 20-step rollout.

    The MLP head (the default) gets two hidden layers of 32; another head (``policy=<name>``
    among the overrides) keeps its defaults.
    """
    head = [] if any(o.startswith("policy=") for o in overrides) else ["policy.hidden=[32,32]"]
    steps = ("optim.steps=30", "optim.warmup=5", "logging.every=5", "logging.checkpoint_every=10")
    return compose_config(*_tiny_settings(tmp_path, data_root), *head, *steps, *overrides)


def _tiny_settings(tmp_path: Path, data_root: Path) -> list[str]:
    """The tiny job's data, logging, evaluation and runs folder settings (its head and steps are the caller's)."""
    return [
        f"data.tasks=[{TASK}]",
        "data.n_demos=2",
        "data.workers=1",
        f"data.root={data_root}",
        "data.batch_segments=8",
        "data.slice_len=8",
        "logging.progress=false",
        "logging.record_weights_at=[]",
        "eval.rollouts=1",
        "eval.horizon=20",
        "eval.workers=1",
        f"runs_root={tmp_path / 'runs'}",
    ]


def train_command(tmp_path: Path, data_root: Path, *args: str) -> list[str]:
    """``python -m tar_rl train`` with the tiny job's settings (the MLP at 2 x 32), then ``args``."""
    tiny_job = _tiny_settings(tmp_path, data_root)
    return [sys.executable, "-m", "tar_rl", "train", *tiny_job, "policy.hidden=[32,32]", *args]


def wait_for_checkpoint(proc: subprocess.Popen, runs_root: Path, deadline: float) -> None:
    """Wait until the training process ``proc`` has written a checkpoint under ``runs_root``; fail when it exits
    first or ``deadline`` seconds pass."""
    give_up = time.monotonic() + deadline
    while not list(runs_root.glob(f"*/{CHECKPOINT}")):
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < give_up, f"no checkpoint within {deadline} s"
        time.sleep(0.2)
