"""The real client: ``lerobot-train --policy.type=<base>_tar`` runs offline for a few steps on a LeRobotDataset written
here, saves a checkpoint, and the checkpoint loads back with ``from_pretrained`` and acts; bad settings stop it
before training with a message naming them. The command lines run through ``lerobot-train``'s entry point, all in one
process (the ``lerobot_train`` fixture of ``conftest.py``)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from conftest import ACTION_DIM

STEPS = 3
TINY = {
    "act_tar": [
        "--policy.chunk_size=4", "--policy.n_action_steps=4", "--policy.dim_model=32", "--policy.dim_feedforward=64",
        "--policy.n_heads=2", "--policy.n_encoder_layers=1", "--policy.n_decoder_layers=1", "--policy.latent_dim=8",
        "--policy.pretrained_backbone_weights=null", "--policy.tar.slice_len=3",
    ],
    "diffusion_tar": [
        "--policy.n_obs_steps=2", "--policy.horizon=8", "--policy.n_action_steps=4", "--policy.down_dims=[16,32]",
        "--policy.diffusion_step_embed_dim=16", "--policy.n_groups=4", "--policy.kernel_size=3",
        "--policy.num_train_timesteps=10", "--policy.pretrained_backbone_weights=null", "--policy.crop_shape=[28,28]",
        "--policy.use_group_norm=true",
        "--policy.spatial_softmax_num_keypoints=8", "--policy.tar.slice_len=3",
    ],
    "smolvla_tar": [
        "--policy.load_vlm_weights=false", "--policy.num_vlm_layers=2", "--policy.resize_imgs_with_padding=[32,32]",
        "--policy.chunk_size=4", "--policy.n_action_steps=4", "--policy.tar.slice_len=2",
    ],
}  # fmt: skip


def lerobot_train_args(dataset: Path, out: Path, policy_type: str, *extra: str) -> list[str]:
    return [
        "--dataset.repo_id=local/tar_tiny", f"--dataset.root={dataset}", f"--policy.type={policy_type}",
        "--policy.device=cpu", "--policy.push_to_hub=false", "--batch_size=4", f"--steps={STEPS}",
        f"--save_freq={STEPS}", "--log_freq=1", "--num_workers=0", f"--output_dir={out}", "--wandb.enable=false",
        *extra,
    ]  # fmt: skip


@pytest.fixture(scope="module")
def runs(state_dataset, image_dataset, smolvlm, lerobot_train, tmp_path_factory) -> dict:
    """The module's ``lerobot-train`` command lines, by name, each run once by the ``lerobot_train`` fixture
    (``lerobot-train``'s entry point in one process): its exit status and output, and its ``--output_dir``."""
    lines = {
        "diffusion_tar-image": (
            image_dataset, "diffusion_tar", *TINY["diffusion_tar"], "--policy.tar.signal=time_normalized"
        ),
        "smolvla_tar": (image_dataset, "smolvla_tar", *TINY["smolvla_tar"], f"--policy.vlm_model_name={smolvlm}"),
        "gamma": (state_dataset, "act_tar", *TINY["act_tar"], "--policy.tar.gamma=0"),
        "slice_len": (state_dataset, "act_tar", *TINY["act_tar"], "--policy.tar.slice_len=99"),
        "pi0_fast": (state_dataset, "pi0_fast_tar"),
    }  # fmt: skip
    folder = tmp_path_factory.mktemp("train")
    return {
        name: (lerobot_train(lerobot_train_args(data, folder / name, kind, *extra)), folder / name)
        for name, (data, kind, *extra) in lines.items()
    }


def load_and_act(checkpoint: Path, dataset: Path, policy_class) -> torch.Tensor:
    """The saved policy and processors from disk; one action for the dataset's first frame."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from lerobot.policies.factory import make_pre_post_processors

    policy = policy_class.from_pretrained(checkpoint)
    preprocessor, postprocessor = make_pre_post_processors(policy.config, pretrained_path=str(checkpoint))
    frame = LeRobotDataset("local/tar_tiny", root=dataset)[0]
    observation = {k: v for k, v in frame.items() if k.startswith("observation.")} | {"task": frame["task"]}
    policy.reset()
    with torch.no_grad():
        action = postprocessor(policy.select_action(preprocessor(observation)))
    assert int(policy.tar_step) == STEPS  # the schedule's count is saved with the weights
    if policy.config.tar.signal == "time_normalized":  # and the signal's running means per time bin
        assert policy.tar_normalizer.weight.sum() > 0
    return action


# act_tar on a state dataset: test_walkthrough.py (the page's commands); act_tar's images: smolvla_tar's run below
# folds images of one observation step as ACT does, and test_policies.py checks ACT's image loss in process. The
# diffusion run ranks by time_normalized, whose running means the checkpoint holds.
@pytest.mark.parametrize("policy_type", ["diffusion_tar"])
@pytest.mark.parametrize("data", ["image"])
def test_lerobot_train_runs_saves_and_the_checkpoint_acts(policy_type, data, request, runs):
    from lerobot_policy_tar.modeling_tar import ACTTARPolicy, DiffusionTARPolicy

    dataset = request.getfixturevalue(f"{data}_dataset")
    done, out = runs[f"{policy_type}-{data}"]
    assert done.returncode == 0, done.stderr[-4000:]
    assert f"step:{STEPS} " in done.stderr and "tar_mix:1.000" in done.stderr, done.stderr[-4000:]
    checkpoint = out / "checkpoints" / "last" / "pretrained_model"
    policy_class = {"act_tar": ACTTARPolicy, "diffusion_tar": DiffusionTARPolicy}[policy_type]
    action = load_and_act(checkpoint, dataset, policy_class)
    assert action.shape == (1, ACTION_DIM) and torch.isfinite(action).all()


def test_lerobot_train_runs_smolvla_tar_on_a_tiny_local_smolvlm_and_the_checkpoint_acts(image_dataset, runs):
    from lerobot_policy_tar.modeling_tar import SmolVLATARPolicy

    done, out = runs["smolvla_tar"]
    assert done.returncode == 0, done.stderr[-4000:]
    assert f"step:{STEPS} " in done.stderr and "tar_mix:1.000" in done.stderr, done.stderr[-4000:]
    action = load_and_act(out / "checkpoints" / "last" / "pretrained_model", image_dataset, SmolVLATARPolicy)
    assert action.shape == (1, ACTION_DIM) and torch.isfinite(action).all()


@pytest.mark.parametrize(
    "run, message",
    [
        ("gamma", "policy.tar: gamma must be a finite number > 0"),
        ("slice_len", "policy.tar.slice_len=99 is longer than every episode of the dataset"),
    ],
    ids=["gamma", "slice_len"],
)
def test_lerobot_train_refuses_bad_tar_settings_before_training(run, message, runs):
    done, _ = runs[run]
    assert done.returncode != 0
    assert message in done.stderr + done.stdout, done.stderr[-4000:]
    assert "Start offline training" not in done.stderr


def test_lerobot_train_refuses_pi0_fast_with_the_reason(runs):
    done, _ = runs["pi0_fast"]
    assert done.returncode != 0
    assert "pi0_fast is not supported by TAR" in done.stderr + done.stdout, done.stderr[-4000:]
