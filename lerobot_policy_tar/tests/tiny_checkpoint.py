"""A tiny ACT checkpoint on MetaWorld's observation, and its chunks computed by hand: the fixtures of the policy
server's tests, on both sides (``test_serve.py`` here, ``tests/experiments/test_lerobot_pilot.py`` in tar-rl's
environment, which runs this file by its path with the plugin's Python).

``python tiny_checkpoint.py write FOLDER``: a freshly initialised ``act`` (or ``--type act_tar``) saved with LeRobot's
``save_pretrained``, and its processors built from made-up dataset statistics (every feature standardised), as
``lerobot-train`` saves them. ``python tiny_checkpoint.py chunks FOLDER IN OUT``: for the observations ``[N, 39]``
and tasks of ``IN`` (``.npz``: ``observations``, ``tasks``), the chunks the policy predicts, ``[N, H, A]`` into ``OUT``
(``.npz``: ``chunks``), computed without the processors: the observation split by hand, standardised with the
statistics read back from the checkpoint's files, the network called, the chunk unstandardised.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch

STATE_DIMS, ENVIRONMENT_DIMS, ACTION_DIMS, HORIZON = 4, 35, 4, 8
STATE, ENVIRONMENT, ACTION = "observation.state", "observation.environment_state", "action"


def statistics(seed: int = 0) -> dict[str, dict[str, np.ndarray]]:
    """Made-up means and standard deviations of every feature, far from 0 and 1 (a forgotten step shows)."""
    rng = np.random.default_rng(seed)
    sizes = {STATE: STATE_DIMS, ENVIRONMENT: ENVIRONMENT_DIMS, ACTION: ACTION_DIMS}
    return {
        name: {
            "mean": rng.normal(0.0, 2.0, size).astype(np.float32),
            "std": rng.uniform(0.5, 3.0, size).astype(np.float32),
        }
        for name, size in sizes.items()
    }


def write(folder: Path, policy_type: str = "act", seed: int = 0) -> Path:
    """A tiny freshly initialised ``policy_type`` checkpoint (``act`` or ``act_tar``) with its processors."""
    from lerobot.configs.types import FeatureType, NormalizationMode, PolicyFeature
    from lerobot.policies.factory import get_policy_class, make_policy_config, make_pre_post_processors

    import lerobot_policy_tar  # noqa: F401  (registers act_tar)

    torch.manual_seed(seed)
    config = make_policy_config(
        policy_type,
        input_features={
            STATE: PolicyFeature(FeatureType.STATE, (STATE_DIMS,)),
            ENVIRONMENT: PolicyFeature(FeatureType.ENV, (ENVIRONMENT_DIMS,)),
        },
        output_features={ACTION: PolicyFeature(FeatureType.ACTION, (ACTION_DIMS,))},
        normalization_mapping={kind: NormalizationMode.MEAN_STD for kind in ("STATE", "ENV", "ACTION")},
        device="cpu",
        chunk_size=HORIZON,
        n_action_steps=HORIZON,
        dim_model=16,
        dim_feedforward=32,
        n_heads=2,
        n_encoder_layers=1,
        n_decoder_layers=1,
        n_vae_encoder_layers=1,
        latent_dim=4,
        pretrained_backbone_weights=None,
        push_to_hub=False,
    )
    policy = get_policy_class(policy_type)(config)
    stats = {name: {k: torch.from_numpy(v) for k, v in s.items()} for name, s in statistics(seed).items()}
    preprocessor, postprocessor = make_pre_post_processors(config, dataset_stats=stats)
    policy.save_pretrained(folder)
    preprocessor.save_pretrained(folder)
    postprocessor.save_pretrained(folder)
    return folder


def _saved_statistics(folder: Path) -> dict[str, dict[str, torch.Tensor]]:
    """The statistics as the checkpoint's preprocessor file holds them (``<feature>.mean``, ``<feature>.std``)."""
    from safetensors.torch import load_file

    (file,) = sorted(folder.glob("policy_preprocessor_step_*normalizer*.safetensors"))
    flat = load_file(file)
    return {name: {k: flat[f"{name}.{k}"] for k in ("mean", "std")} for name in (STATE, ENVIRONMENT, ACTION)}


def chunks(folder: Path, observations: np.ndarray, tasks: list[str]) -> np.ndarray:
    """The checkpoint's chunks ``[N, H, A]`` for ``observations`` ``[N, 39]``, without LeRobot's processors."""
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.factory import get_policy_class

    import lerobot_policy_tar  # noqa: F401

    config = PreTrainedConfig.from_pretrained(folder)
    policy = get_policy_class(config.type).from_pretrained(folder).eval()
    stats = _saved_statistics(folder)
    obs = torch.from_numpy(observations)
    batch = {
        STATE: (obs[:, :STATE_DIMS] - stats[STATE]["mean"]) / stats[STATE]["std"],
        ENVIRONMENT: (obs[:, STATE_DIMS:] - stats[ENVIRONMENT]["mean"]) / stats[ENVIRONMENT]["std"],
        "task": list(tasks),
    }
    with torch.no_grad():
        chunk = policy.predict_action_chunk(batch)
    # LeRobot standardises with std + 1e-8: at these stds the same floats up to rounding.
    return (chunk * stats[ACTION]["std"] + stats[ACTION]["mean"]).numpy()


if __name__ == "__main__":
    command, folder = sys.argv[1], Path(sys.argv[2])
    if command == "write":
        write(folder, *sys.argv[3:])
    else:
        given = np.load(sys.argv[3])
        np.savez(sys.argv[4], chunks=chunks(folder, given["observations"], given["tasks"].tolist()))
