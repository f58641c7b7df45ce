"""Tiny LeRobot datasets and configs written in the tests: nothing comes from a hub (the tests run offline)."""

from __future__ import annotations

import json
import os
import select
import subprocess
import sys
import tempfile
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


def write_smolvlm(folder: Path) -> Path:
    """A tiny SmolVLM folder for ``--policy.vlm_model_name`` (SmolVLA builds its VLM from the config and reads the
    processor and tokenizer; ``load_vlm_weights=false``): a word-level tokenizer over the task's words with
    SmolVLM's image tokens, a 2-layer 32-wide Llama text model, a 1-layer SigLIP tower for 32-pixel images."""
    from tokenizers import Tokenizer, models, pre_tokenizers
    from transformers import (
        PreTrainedTokenizerFast,
        SmolVLMConfig,
        SmolVLMImageProcessor,
        SmolVLMProcessor,
        SmolVLMVideoProcessor,
    )

    special = {
        "fake_image_token": "<fake_token_around_image>",
        "global_image_token": "<global-img>",
        "image_token": "<image>",
        "end_of_utterance_token": "<end_of_utterance>",
    }
    vocab = {word: i for i, word in enumerate(["<unk>", "<pad>", *special.values(), "push", "the", "cube"])}
    words = Tokenizer(models.WordLevel(vocab, unk_token="<unk>"))
    words.pre_tokenizer = pre_tokenizers.Whitespace()
    tokenizer = PreTrainedTokenizerFast(
        tokenizer_object=words, unk_token="<unk>", pad_token="<pad>", extra_special_tokens=special
    )
    processor = SmolVLMProcessor(
        image_processor=SmolVLMImageProcessor(),
        tokenizer=tokenizer,
        video_processor=SmolVLMVideoProcessor(),
        image_seq_len=4,
    )
    text = {"model_type": "llama", "hidden_size": 32, "intermediate_size": 64, "num_hidden_layers": 2}
    text |= {"num_attention_heads": 4, "num_key_value_heads": 2, "vocab_size": len(vocab), "pad_token_id": 1}
    vision = {"hidden_size": 16, "intermediate_size": 32, "num_hidden_layers": 1, "num_attention_heads": 2}
    vision |= {"image_size": IMAGE_SIZE, "patch_size": 8}
    config = SmolVLMConfig(text_config=text, vision_config=vision, scale_factor=2, image_token_id=vocab["<image>"])
    processor.save_pretrained(folder)
    config.save_pretrained(folder)
    return folder


@pytest.fixture(scope="session")
def smolvlm(tmp_path_factory) -> Path:
    return write_smolvlm(tmp_path_factory.mktemp("smolvlm"))


@pytest.fixture(scope="session")
def state_dataset(tmp_path_factory) -> Path:
    return write_dataset(tmp_path_factory.mktemp("data") / "state", image=False)


@pytest.fixture(scope="session")
def image_dataset(tmp_path_factory) -> Path:
    return write_dataset(tmp_path_factory.mktemp("data") / "image", image=True)


class LeRobotTrain:
    """``lerobot-train`` for the tests: ``lerobot_train_runs.py`` running in this environment, each command line
    through ``lerobot-train``'s entry point in that one process (LeRobot starts once for all the tests' runs, not
    once each, and each run takes the path of the user's ``lerobot-train`` command). Calling it runs one command
    line and returns its exit status and output as ``subprocess.run`` would (``timeout`` seconds at most)."""

    def __init__(self):
        self.folder, self.runs = None, 0  # folder: where the runs' output goes, set before the first run
        self.errors = tempfile.TemporaryFile()
        env = {**os.environ, "HF_HUB_OFFLINE": "1", "WANDB_MODE": "disabled"}
        script = Path(__file__).with_name("lerobot_train_runs.py")
        self.process = subprocess.Popen(
            [sys.executable, str(script)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=self.errors, env=env
        )

    def __call__(self, argv: list[str], cwd: Path | None = None, timeout: float = 900) -> subprocess.CompletedProcess:
        self.runs += 1
        out = self.folder / f"run{self.runs}"
        request = {"argv": [str(a) for a in argv], "out": str(out), "cwd": str(cwd or Path.cwd())}
        self.process.stdin.write(json.dumps(request).encode() + b"\n")
        self.process.stdin.flush()
        answer = b""
        while not answer.endswith(b"\n"):
            ready, _, _ = select.select([self.process.stdout], [], [], timeout)
            chunk = os.read(self.process.stdout.fileno(), 4096) if ready else b""
            if not chunk:
                self.errors.seek(0)
                said = self.errors.read().decode(errors="replace")[-3000:]
                raise AssertionError(f"lerobot-train gave no answer in {timeout} s or ended: {said}")
            answer += chunk
        status = int(answer.decode().removeprefix("STATUS ").strip())
        stdout, stderr = ((out / name).read_text(errors="replace") for name in ("stdout", "stderr"))
        return subprocess.CompletedProcess(["lerobot-train", *request["argv"]], status, stdout, stderr)

    def close(self) -> None:
        self.process.stdin.close()
        if not self.runs:  # no test ran lerobot-train (deselected, --collect-only): the import need not finish
            self.process.kill()
        self.process.wait(timeout=60)
        self.process.stdout.close()
        self.errors.close()


#: The session's ``lerobot-train`` process, started as soon as the tests are collected when one of them runs
#: ``lerobot-train``: LeRobot's import there overlaps the tests that come before.
RUNNER: dict[str, LeRobotTrain] = {}


def pytest_collection_finish(session):
    if any("lerobot_train" in item.fixturenames for item in session.items):
        RUNNER["process"] = LeRobotTrain()


def pytest_sessionfinish(session):
    if "process" in RUNNER:
        RUNNER.pop("process").close()


@pytest.fixture(scope="session")
def lerobot_train(tmp_path_factory) -> LeRobotTrain:
    if "process" not in RUNNER:
        RUNNER["process"] = LeRobotTrain()
    runner = RUNNER["process"]
    runner.folder = tmp_path_factory.mktemp("lerobot_train_runs")
    return runner
