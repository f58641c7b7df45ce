"""docs/lerobot.md's commands as a new user runs them, and what they write: MetaWorld demonstrations collected with
tar-rl, exported as a LeRobotDataset (round trip against tar-rl's own arrays; tar-rl's refusals), ACT trained with
TAR by ``lerobot-train`` (the log comparable with ACT's), the checkpoint written as a plain ``act`` one (the same
actions), and post-training from it with ``--policy.path``.

The page's code blocks run as written, made small: two reach demonstrations instead of MT50's 2,500, a tiny ACT and
a few steps (:data:`SMALLER`, each replacement checked to apply). tar-rl's side (collecting, its loader's arrays and
messages) runs in tar-rl's own environment, ``.venv/`` at the repository root, which the README's test command makes
before this one; without it these tests are skipped, saying so.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys
from dataclasses import fields
from pathlib import Path

import numpy as np
import pytest
import torch

REPO = Path(__file__).resolve().parents[2]
PAGE = REPO / "docs" / "lerobot.md"
TAR_RL_PYTHON = Path(os.environ.get("TAR_RL_PYTHON", REPO / ".venv" / "bin" / "python"))
SLICE_LEN = 16  # the page's --policy.tar.slice_len
TINY_ACT = (
    "--policy.device=cpu --policy.chunk_size=4 --policy.n_action_steps=4 --policy.dim_model=32 "
    "--policy.dim_feedforward=64 --policy.n_heads=2 --policy.n_encoder_layers=1 --policy.n_decoder_layers=1 "
    "--policy.latent_dim=8 --policy.n_vae_encoder_layers=1"
)
#: The page's sizes -> the tests' (each must occur in the page).
SMALLER = {
    "'mt50', n_demos=50": "'reach', n_demos=2, workers=1",
    "--steps=100000": f"--steps=3 --log_freq=1 --num_workers=0 {TINY_ACT}",
    "--policy.tar.start=20000 --policy.tar.ramp=30000": "--policy.tar.start=1 --policy.tar.ramp=1",
    "--steps=30000": "--steps=2 --log_freq=1 --num_workers=0",
    "--policy.tar.start=6000 --policy.tar.ramp=9000": "--policy.tar.start=1 --policy.tar.ramp=0",
}


def page_blocks() -> list[str]:
    """The page's bash blocks that are not marked ``<!-- skip: ... -->``, in order."""
    lines, blocks, i = PAGE.read_text().splitlines(), [], 0
    while i < len(lines):
        if lines[i].strip() == "```bash":
            end = lines.index("```", i + 1)
            if not lines[i - 1].strip().startswith("<!-- skip:"):
                blocks.append("\n".join(lines[i + 1 : end]))
            i = end
        i += 1
    return blocks


def commands(block: str) -> list[str]:
    """A block's command lines (continuations joined), with the tests' sizes."""
    for old, new in SMALLER.items():
        block = block.replace(old, new)
    return [line for line in block.replace("\\\n", " ").splitlines() if line.strip()]


def run_block(block: str, cwd: Path, env: dict[str, str], train) -> list[tuple[str, subprocess.CompletedProcess]]:
    """Run a block's lines in ``cwd`` as bash would: ``NAME=$(...)`` assigns its output to ``env[NAME]``, ``$NAME``
    expands; ``lerobot-tar`` runs in this process (its ``main``), ``lerobot-train`` by ``train`` (the
    ``lerobot_train`` fixture: its entry point, in the process that runs every test's ``lerobot-train``), every
    other command as a process. Stops at the first failure."""
    from lerobot_policy_tar.cli import main

    done = []
    for line in commands(block):
        assignment = re.fullmatch(r"(\w+)=\$\((.*)\)", line.strip())
        if assignment:
            result = subprocess.run(["bash", "-c", assignment[2]], cwd=cwd, capture_output=True, text=True, timeout=600)
            env[assignment[1]] = result.stdout.strip()
        else:
            argv = [re.sub(r"\$(\w+)", lambda name: env[name[1]], word) for word in shlex.split(line)]
            if Path(argv[0]).name == "lerobot-tar":
                cwd_before = Path.cwd()
                os.chdir(cwd)
                try:
                    status = main(argv[1:])
                finally:
                    os.chdir(cwd_before)
                result = subprocess.CompletedProcess(argv, status, "", "")
            elif Path(argv[0]).name == "lerobot-train":
                result = train(argv[1:], cwd=cwd)
            else:
                result = subprocess.run(argv, cwd=cwd, capture_output=True, text=True, timeout=900, env=env)
        done.append((line, result))
        if result.returncode != 0:
            break
    return done


@pytest.fixture(scope="session")
def walkthrough(tmp_path_factory, lerobot_train) -> dict:
    """The page's first block run in a fresh folder (beside the two environments), and tar-rl's side of its data."""
    if not TAR_RL_PYTHON.is_file():
        pytest.skip(f"tar-rl's environment is missing ({TAR_RL_PYTHON}): the README's test command makes it first")
    home = tmp_path_factory.mktemp("user")
    (home / ".venv").symlink_to(TAR_RL_PYTHON.parents[1])
    (home / ".venv-lerobot").symlink_to(Path(sys.executable).parents[1])
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "WANDB_MODE": "disabled"}
    blocks = page_blocks()
    ran = run_block(blocks[0], home, env, lerobot_train)
    assert all(r.returncode == 0 for _, r in ran), "\n".join(
        f"{c}\n{r.stdout[-2000:]}{r.stderr[-3000:]}" for c, r in ran
    )
    demos = home / env["demos"]
    assert (demos / "digest.json").is_file(), env["demos"]
    side = home / "tar_rl_side"
    script = Path(__file__).with_name("tar_rl_side.py")
    done = subprocess.run([str(TAR_RL_PYTHON), str(script), str(demos), str(side)], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-3000:]
    return {
        "home": home,
        "env": env,
        "ran": ran,
        "demos": demos,
        "side": side,
        "blocks": blocks,
        "train": lerobot_train,
    }


# -- The page ---------------------------------------------------------------------------------------


def test_the_install_line_is_the_one_test_sh_runs():
    page = PAGE.read_text()
    test_sh = (REPO / "lerobot_policy_tar" / "test.sh").read_text()
    assert "```bash\nlerobot_policy_tar/env.sh\n```" in page
    assert "\nlerobot_policy_tar/env.sh test\n" in test_sh  # the page's line, with the tests' extra
    for old in SMALLER:
        assert old in page, f"the page no longer has {old!r}: update SMALLER"


def test_the_walkthrough_runs_and_its_log_compares_with_acts(walkthrough):
    """The training log has the comparable keys, and ``tar_epochs`` is LeRobot's own sample count x slice_len over
    the dataset's frames (LeRobot's ``epch`` counts segments)."""
    train = next(r for c, r in walkthrough["ran"] if "lerobot-train" in c)
    log = train.stderr + train.stdout
    frames = int(re.search(r"dataset\.num_frames=(\d+)", log)[1])
    lines = [line for line in log.splitlines() if re.search(r"step:\d+ ", line)]
    assert len(lines) == 3, log[-3000:]
    for line in lines:
        values = dict(re.findall(r"(\w+):([-\d.eE+]+)", line))
        for key in ("tar_uniform_loss", "l1_loss", "kld_loss", "tar_mix", "tar_max_weight", "tar_ess", "tar_epochs"):
            assert key in values, (key, line)
        assert float(values["tar_epochs"]) == pytest.approx(int(values["smpl"]) * SLICE_LEN / frames, abs=5e-4)
    assert "tar_mix:1.000" in lines[-1] and float(dict(re.findall(r"(\w+):([\d.]+)", lines[-1]))["tar_ess"]) < 1
    config = json.loads((walkthrough["home"] / "act_mt50" / "config.json").read_text())
    assert config["type"] == "act" and "tar" not in config


# -- The export ---------------------------------------------------------------------------------------


def test_the_export_round_trips_tar_rls_arrays(walkthrough):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    arrays = np.load(walkthrough["side"] / "arrays.npz")
    tasks = json.loads((walkthrough["side"] / "tasks.json").read_text())
    root = walkthrough["home"] / "data" / "lerobot" / "metaworld-mt50"
    dataset = LeRobotDataset("local/metaworld-mt50", root=root)
    assert dataset.fps == 80 and dataset.num_frames == len(arrays["action"]) == 95
    episodes = list(dict.fromkeys(arrays["episode"].tolist()))
    assert dataset.num_episodes == len(episodes) == 2
    table = dataset.hf_dataset.with_format("numpy")[:]
    state = np.stack(table["observation.state"])
    environment = np.stack(table["observation.environment_state"])
    assert state.shape[1] == 4  # the hand's position and the gripper's opening: LeRobot's MetaWorld agent_pos
    assert np.array_equal(np.concatenate([state, environment], axis=1), arrays["observation"])
    assert np.array_equal(np.stack(table["action"]), arrays["action"])
    assert np.array_equal(table["frame_index"], arrays["step"])  # each episode starts at its first step
    assert np.array_equal(table["episode_index"], np.searchsorted(episodes, arrays["episode"]))
    assert np.allclose(table["timestamp"], arrays["step"] / 80)
    texts = [tasks["instructions"][tasks["task_names"][i]] for i in arrays["task_id"]]
    task_of = {int(index): text for text, index in dataset.meta.tasks["task_index"].items()}
    assert [task_of[int(i)] for i in table["task_index"]] == texts
    assert texts[0] == "Reach the goal position with the gripper."  # tar-rl's instruction for reach-v3, not its name


def _nothing_written(parent: Path) -> bool:
    return not parent.exists() or not any(parent.iterdir())


@pytest.mark.parametrize("variant", ["unsealed", "format_3", "format_5", "nan", "edited"])
def test_folders_tar_rl_refuses_are_refused_with_its_message_and_nothing_is_written(walkthrough, variant, tmp_path):
    from lerobot_policy_tar.export import DatasetError, export_dataset

    expected = json.loads((walkthrough["side"] / "messages.json").read_text())[variant]
    with pytest.raises(DatasetError) as refused:
        export_dataset(expected["path"], tmp_path / "out" / "dataset")
    assert str(refused.value) == expected["message"]
    assert _nothing_written(tmp_path / "out")


def test_the_command_refuses_in_one_line_and_an_existing_dataset_is_replaced_only_when_asked(
    walkthrough, tmp_path, capsys
):
    from lerobot_policy_tar.cli import main

    unsealed = json.loads((walkthrough["side"] / "messages.json").read_text())["unsealed"]
    assert main(["export-dataset", unsealed["path"], str(tmp_path / "x")]) == 1
    assert capsys.readouterr().err == f"lerobot-tar export-dataset: {unsealed['message']}\n"
    assert not (tmp_path / "x").exists()
    root = walkthrough["home"] / "data" / "lerobot" / "metaworld-mt50"
    before = {p: p.read_bytes() for p in root.rglob("*") if p.is_file()}
    assert main(["export-dataset", str(walkthrough["demos"]), str(root)]) == 1
    assert "already holds a LeRobotDataset: choose another folder, or pass --overwrite" in capsys.readouterr().err
    assert {p: p.read_bytes() for p in root.rglob("*") if p.is_file()} == before
    copy = tmp_path / "copy"
    assert main(["export-dataset", str(walkthrough["demos"]), str(copy), "--state-dims", "39"]) == 0
    assert main(["export-dataset", str(walkthrough["demos"]), str(copy), "--overwrite"]) == 0
    info = json.loads((copy / "meta" / "info.json").read_text())
    assert info["features"]["observation.state"]["shape"] == [4]  # the new export replaced the old one
    assert sorted(p.name for p in tmp_path.iterdir()) == ["copy"]  # no temporary folder left
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("mine")
    assert main(["export-dataset", str(walkthrough["demos"]), str(tmp_path / "other"), "--overwrite"]) == 1
    assert "exists and is not a LeRobotDataset" in capsys.readouterr().err
    assert (tmp_path / "other" / "notes.txt").read_text() == "mine"


# -- The checkpoints ------------------------------------------------------------------------------------


def _act(checkpoint: Path, frame: dict) -> torch.Tensor:
    """The checkpoint's policy, by its type through LeRobot's factory, and its processors: one action."""
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.factory import get_policy_class, make_pre_post_processors

    config = PreTrainedConfig.from_pretrained(checkpoint)
    policy = get_policy_class(config.type).from_pretrained(checkpoint)
    preprocessor, postprocessor = make_pre_post_processors(policy.config, pretrained_path=str(checkpoint))
    policy.reset()
    with torch.no_grad():
        return postprocessor(policy.select_action(preprocessor(dict(frame))))


def test_the_base_checkpoint_acts_exactly_as_the_tar_one_and_needs_no_plugin(walkthrough):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from lerobot.policies.act.modeling_act import ACTPolicy
    from safetensors import safe_open

    home = walkthrough["home"]
    tar = home / "outputs" / "act_tar_mt50" / "checkpoints" / "last" / "pretrained_model"
    base = home / "act_mt50"
    frame = LeRobotDataset("local/metaworld-mt50", root=home / "data" / "lerobot" / "metaworld-mt50")[7]
    observation = {k: v for k, v in frame.items() if k.startswith("observation.")} | {"task": frame["task"]}
    ours, theirs = _act(tar, observation), _act(base, observation)
    assert ours.shape == (1, 4) and torch.equal(ours, theirs)
    with safe_open(base / "model.safetensors", "pt") as weights, safe_open(tar / "model.safetensors", "pt") as trained:
        assert set(weights.keys()) == set(trained.keys()) - {"tar_step"}
        assert all(torch.equal(weights.get_tensor(key), trained.get_tensor(key)) for key in weights.keys())
    assert type(ACTPolicy.from_pretrained(base)) is ACTPolicy  # LeRobot's own class, not the plugin's


def test_checkpoint_conversions_refuse_what_they_cannot_convert(walkthrough, tmp_path):
    from lerobot_policy_tar.checkpoints import CheckpointError, to_base, to_tar

    home = walkthrough["home"]
    with pytest.raises(CheckpointError, match=r"act_mt50 is a 'act' checkpoint, not a TAR one \(act_tar, "):
        to_base(home / "act_mt50", tmp_path / "a")
    tar = home / "outputs" / "act_tar_mt50" / "checkpoints" / "last"
    with pytest.raises(CheckpointError, match=r"is already a TAR checkpoint \('act_tar'\)"):
        to_tar(tar, tmp_path / "b")
    with pytest.raises(CheckpointError, match=r"is not a LeRobot policy checkpoint: it has no config\.json"):
        to_base(home / "data", tmp_path / "c")
    with pytest.raises(CheckpointError, match=r"exists: choose a new folder"):
        to_base(tar, home / "act_mt50")
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_post_training_from_the_base_checkpoint_runs_as_the_page_says_without_warnings(walkthrough):
    """The page's second block: ``to-tar``, then ``lerobot-train --policy.path``; the run loads every weight of the
    base checkpoint (no missing or unexpected key) and starts TAR's schedule at 0."""
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata
    from lerobot.policies.factory import make_policy
    from safetensors.torch import load_file

    home = walkthrough["home"]
    ran = run_block(walkthrough["blocks"][1], home, dict(walkthrough["env"]), walkthrough["train"])
    train = ran[-1][1]
    assert len(ran) == 2 and train.returncode == 0, train.stderr[-3000:]
    log = train.stderr + train.stdout
    assert "Loading weights from local directory" in log
    assert "Missing key" not in log and "Unexpected key" not in log
    assert "step:2 " in log and "tar_mix:1.000" in log
    config = PreTrainedConfig.from_pretrained(home / "act_tar_init")
    config.pretrained_path = home / "act_tar_init"
    meta = LeRobotDatasetMetadata("local/metaworld-mt50", root=home / "data" / "lerobot" / "metaworld-mt50")
    policy = make_policy(config, ds_meta=meta)  # as lerobot-train makes it
    pretrained = load_file(home / "act_mt50" / "model.safetensors")
    state = policy.state_dict()
    assert int(state.pop("tar_step")) == 0 and state.keys() == pretrained.keys()
    assert all(torch.equal(state[key], pretrained[key]) for key in pretrained)


def test_a_base_checkpoint_loads_into_a_tar_policy_without_a_warning(walkthrough, caplog):
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.act.configuration_act import ACTConfig
    from lerobot_policy_tar.modeling_tar import ACTTARPolicy

    home = walkthrough["home"]
    base_config = PreTrainedConfig.from_pretrained(home / "act_mt50")
    config = ACTTARPolicy.config_class(**{f.name: getattr(base_config, f.name) for f in fields(ACTConfig) if f.init})
    with caplog.at_level("WARNING"):
        policy = ACTTARPolicy.from_pretrained(home / "act_mt50", config=config)
    assert not [r for r in caplog.records if "key" in r.getMessage()], caplog.text
    assert int(policy.tar_step) == 0
