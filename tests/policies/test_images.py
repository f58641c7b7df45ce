"""Image observations: rendered demonstrations, the conv encoder, every head on images.

Rendering needs MuJoCo's off-screen backend (``MUJOCO_GL=egl``), chosen when MuJoCo is imported:
the collection runs it in worker processes; the independent reference render below runs in a
subprocess of its own.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest
import torch
from recipe_helpers import tiny
from tensordict import TensorDict
from tensordict.nn import TensorDictModuleBase

from tar_rl.collectors.metaworld.dataset import build_dataset
from tar_rl.collectors.metaworld.evaluate import RolloutPool, evaluate
from tar_rl.policies import POLICIES, DataInfo, build_policy
from tar_rl.policies.common import ConvEncoder
from tar_rl.recipes import make_objective, offline_bc, policy_from_checkpoint, train
from tar_rl.recipes.config import objective_config
from tar_rl.runs import load_checkpoint

S = 32
H = 4
HEADS = sorted(POLICIES)
INFO = DataInfo(chunk_horizon=H, history=2, image_size=S)

_REFERENCE = """
import json, sys
import mujoco, numpy as np
from tar_rl.collectors.metaworld import tasks
env = tasks.make_env("reach-v3")
env.set_task(tasks.variation("reach-v3", 0, 0))
obs, _ = env.reset()
env.model.vis.quality.shadowsize = 0
r = mujoco.Renderer(env.model, {S}, {S})
r.update_scene(env.data, camera="corner2")
img = r.render()[::-1, ::-1].transpose(2, 0, 1)  # corner2 is upside down: rotate by 180 degrees
print(json.dumps({{"obs": obs.tolist(), "img": img.tolist()}}))
"""


@pytest.fixture(scope="module")
def image_datasets(tmp_path_factory):
    """A dataset folder shared by the module (one rendered dataset, collected once: ``image_dataset``)."""
    return tmp_path_factory.mktemp("image-datasets")


class _KeptPool(RolloutPool):
    """A pool that outlives the jobs it serves: leaving a job's ``with`` keeps its worker; ``close()`` ends it."""

    def __exit__(self, *exc) -> None:
        pass


@pytest.fixture(scope="module")
def image_pool():
    """The worker process that renders the module's image evaluations, started once."""
    pool = _KeptPool()
    yield pool
    pool.close()


@pytest.fixture(scope="module")
def image_dataset(image_datasets):
    """The rendered dataset of the recipe jobs (``tiny``'s: reach, 2 demonstrations, seed 0): they load it."""
    return build_dataset(image_datasets, ["reach"], 2, seed=0, image_size=S, workers=1, progress=False, verbose=False)


@pytest.mark.slow
def test_rendered_demonstrations_store_the_image_of_each_observation(image_dataset):
    data = image_dataset.data
    pixels = data["pixels"]
    assert pixels.dtype == torch.uint8 and pixels.shape == (len(data), 3, S, S)
    assert image_dataset.metadata["image_size"] == S
    assert not torch.equal(pixels[0], pixels[-1])  # the arm moved
    env = dict(os.environ, MUJOCO_GL="egl")
    out = subprocess.run([sys.executable, "-c", _REFERENCE.format(S=S)], env=env, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-2000:]
    ref = json.loads(out.stdout.strip().splitlines()[-1])
    np.testing.assert_allclose(data["observation"][0].numpy(), np.array(ref["obs"], np.float32), atol=1e-6)
    np.testing.assert_array_equal(pixels[0].numpy(), np.array(ref["img"], np.uint8))


def test_conv_encoder_folds_leading_axes_and_checks_the_size():
    torch.manual_seed(0)
    enc = ConvEncoder(S, 16)
    pixels = torch.randint(0, 256, (2, 3, 3, S, S), dtype=torch.uint8)
    out = enc(pixels)
    assert out.shape == (2, 3, 16)
    torch.testing.assert_close(out[1, 2], enc(pixels[1, 2][None])[0])
    with pytest.raises(ValueError, match="expected"):
        enc(torch.zeros(2, 3, S + 1, S + 1, dtype=torch.uint8))


def _image_inputs(n: int = 3, seed: int = 0) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    return TensorDict(
        {
            "observation": torch.randn(n, 39, generator=g),
            "task_id": torch.tensor([1, 2, 3])[:n],
            "is_init": torch.ones(n, 1, dtype=torch.bool),
            "pixels": torch.randint(0, 256, (n, 3, S, S), dtype=torch.uint8, generator=g),
        },
        [n],
    )


def _image_segments(seed: int = 0) -> TensorDict:
    """``[2, 4]`` training segments with images, histories and chunks for every head."""
    g = torch.Generator().manual_seed(seed)
    b, length = 2, 4
    obs = torch.randn(b, length, 39, generator=g)
    chunk = torch.tanh(torch.randn(b, length, H, 4, generator=g))
    return TensorDict(
        {
            "observation": obs,
            "observation_history": torch.stack([obs.roll(1, 1), obs], dim=2),
            "observation_history_valid": torch.ones(b, length, 2, dtype=torch.bool),
            "task_id": torch.ones(b, length, dtype=torch.long),
            "action": chunk[:, :, 0].clone(),
            "action_chunk": chunk,
            "action_chunk_valid": torch.ones(b, length, H, dtype=torch.bool),
            "pixels": torch.randint(0, 256, (b, length, 3, S, S), dtype=torch.uint8, generator=g),
            ("collector", "mask"): torch.ones(b, length, dtype=torch.bool),
        },
        [b, length],
    )


def _move(td: TensorDict, dims: slice, shift: float) -> TensorDict:
    """A copy with the observation entries ``dims`` shifted (in the current observation and its history)."""
    out = td.clone()
    out["observation"][..., dims] += shift
    if "observation_history" in out.keys():
        out["observation_history"][..., dims] += shift
    return out


@pytest.mark.parametrize("name", HEADS)
def test_every_head_on_images_reads_pixels_and_proprioception_only(name):
    torch.manual_seed(0)
    policy = build_policy({"name": name, "observation": "image"}, INFO)
    assert "pixels" in policy.actor.in_keys and "pixels" in policy.keys
    actor = policy.actor.eval()
    inputs = _image_inputs()

    def act(td):
        with torch.no_grad():
            return actor(td.clone())["action"]

    base = act(inputs)
    torch.testing.assert_close(act(_move(inputs, slice(4, None), 5.0)), base)  # objects, goal: not seen
    assert not torch.allclose(act(_move(inputs, slice(0, 4), 1.0)), base)  # hand and gripper: seen
    other = inputs.clone()
    other["pixels"] = 255 - other["pixels"]
    assert not torch.allclose(act(other), base)
    # Training: the per-step loss reads the same inputs, and the conv encoder learns.
    objective = make_objective(objective_config("tar")(start=0.0, ramp=0.0), 10, 0, policy).train()
    segments = _image_segments()

    def step_losses(td):
        torch.manual_seed(5)  # the generative heads draw the same noise each call
        return objective.step_losses(td)

    losses = step_losses(segments)
    assert losses.shape == (2, 4)
    torch.testing.assert_close(step_losses(_move(segments, slice(4, None), 5.0)), losses)
    torch.manual_seed(5)
    objective(segments)["loss_tar"].backward()
    encoder = [n for n, p in objective.named_parameters() if ".image." in f".{n}" and p.requires_grad]
    assert encoder and all(
        p.grad is not None and p.grad.abs().sum() > 0 for n, p in objective.named_parameters() if n in encoder
    )
    with pytest.raises((ValueError, KeyError), match="pixels"):
        actor(inputs.exclude("pixels"))


def test_image_policy_needs_a_dataset_with_images():
    for name in HEADS:
        with pytest.raises(ValueError, match=r"data\.image_size"):
            build_policy({"name": name, "observation": "image"}, DataInfo(chunk_horizon=H, history=2))
        with pytest.raises(ValueError, match=r"policy\.observation"):
            build_policy({"name": name, "observation": "depth"}, INFO)


class _PixelProbe(TensorDictModuleBase):
    """Zero actions (reach never succeeds with them); saves the pixels of its first call to ``path``."""

    in_keys = ["observation", "pixels"]
    out_keys = ["action"]

    def __init__(self, path):
        super().__init__()
        self.path = str(path)

    def forward(self, td):
        pixels = td["pixels"]
        assert pixels.dtype == torch.uint8 and pixels.shape == (td.batch_size[0], 3, S, S)
        if not os.path.exists(self.path):
            np.save(self.path, pixels.numpy())
        td.set("action", torch.zeros(td.batch_size[0], 4))
        return td


@pytest.mark.slow
def test_evaluation_gives_the_policy_the_image_of_each_slot(image_dataset, image_pool, tmp_path):
    # Rollout k of seed 0 starts in the variation of demonstration k: the same first image.
    path = tmp_path / "seen.npy"
    rows = evaluate(
        _PixelProbe(path), ["reach"], rollouts_per_task=2, seed=0, horizon=3, workers=1, image_size=S, pool=image_pool
    )
    assert len(rows) == 2 and not rows.success.any()
    seen = np.load(path)
    np.testing.assert_array_equal(seen[0], image_dataset.data["pixels"][0].numpy())
    assert not np.array_equal(seen[0], seen[1])  # another variation: the goal and arm start elsewhere


@pytest.mark.slow
@pytest.mark.parametrize("name", HEADS)
def test_a_tiny_image_job_trains_and_evaluates_through_the_recipe(
    name, tmp_path, image_datasets, image_dataset, image_pool, monkeypatch
):
    monkeypatch.setattr(offline_bc, "make_evaluation_pool", lambda suite: image_pool)  # the jobs share one worker
    config = tiny(
        tmp_path,
        image_datasets,
        f"policy={name}",
        "policy.observation=image",
        f"data.image_size={S}",
        "optim.steps=6",
        "logging.every=3",
        "eval.horizon=5",
    )
    run_dir = train(config)
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["finished"] and summary["steps"] == 6
    rollouts = pd.read_csv(run_dir / "eval_rollouts.csv")
    assert len(rollouts) == 1 and rollouts.failure.isna().all()
    assert "pixels" in policy_from_checkpoint(load_checkpoint(run_dir)).in_keys
