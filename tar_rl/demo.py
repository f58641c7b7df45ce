"""A short demonstration of the objective on synthetic pick-and-carry demonstrations.

A point "gripper" moves to an object, closes on it (the action's grip channel flips from -1 to
+1 at contact), then carries it to a goal. Demonstrations of varying length go into a TorchRL
``TensorDictReplayBuffer``; ``SliceSampler(pad_output=True)`` cuts ``[B, L]`` segments with
padding; a small MLP is trained with ``BCLoss(reduction="none")`` wrapped in ``TARLoss``, once
per weighting, from the same initialisation and the same batches. The demo prints the
training curves, TAR's weights along one held-out demonstration (contact marked), and the
held-out action error around contact versus elsewhere.

This is a toy to show the moving parts; the MetaWorld recipes are the real experiments.
"""

from __future__ import annotations

import copy
import logging
import tempfile
import time
import warnings
from dataclasses import dataclass

import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.data import LazyMemmapStorage, SliceSampler, TensorDictReplayBuffer
from torchrl.objectives import BCLoss

from tar_rl.objectives import MixSchedule, TARLoss

OBS_DIM, ACT_DIM = 8, 3
CONTACT_WINDOW = 2  # steps on either side of contact counted as "around contact"


@dataclass
class DemoConfig:
    """Settings of the demonstration run."""

    n_train: int = 60  #: training demonstrations
    n_test: int = 20  #: held-out demonstrations
    steps: int = 600  #: optimiser steps per weighting
    batch_segments: int = 32  #: segments per batch (B)
    slice_len: int = 16  #: segment length (L)
    weightings: tuple[str, ...] = ("uniform", "tar")
    seed: int = 0


def make_demonstrations(n: int, generator: torch.Generator, first_episode: int = 0) -> TensorDict:
    """``n`` scripted pick-and-carry demonstrations, concatenated along time.

    Observation (8): gripper xy, object xy, goal xy, grip state, holding flag.
    Action (3): xy velocity in [-1, 1] and the grip command (-1 open, +1 closed).
    Each step also records ``contact`` (True at the step the grip closes), its index ``step`` in its
    demonstration and the demonstration's length ``episode_length``.
    """
    episodes = []
    for e in range(n):
        pos, obj, goal = (torch.rand(3, 2, generator=generator) * 2 - 1).unbind(0)
        holding = False
        rows: dict[str, list[torch.Tensor]] = {"observation": [], "action": [], "contact": []}
        for _ in range(200):
            target = goal if holding else obj
            delta = target - pos
            contact = (not holding) and bool(delta.norm() < 0.08)
            move = (delta * 6).clamp(-1, 1) if not contact else torch.zeros(2)
            grip = 1.0 if (holding or contact) else -1.0
            obs = torch.cat([pos, obj, goal, torch.tensor([grip if holding else -1.0, float(holding)])])
            rows["observation"].append(obs)
            rows["action"].append(torch.cat([move, torch.tensor([grip])]))
            rows["contact"].append(torch.tensor(contact))
            holding = holding or contact
            pos = (pos + 0.1 * move).clamp(-1, 1)
            if holding:
                obj = pos.clone()
            if holding and (goal - pos).norm() < 0.05:
                break
        t = len(rows["action"])
        done = torch.zeros(t, 1, dtype=torch.bool)
        done[-1] = True
        episodes.append(
            TensorDict(
                {
                    **{k: torch.stack(v) for k, v in rows.items()},
                    "episode": torch.full((t,), first_episode + e),
                    "step": torch.arange(t),
                    "episode_length": torch.full((t,), t),  # with step: the position in the episode (dro_time)
                    ("next", "done"): done,
                },
                [t],
            )
        )
    return torch.cat(episodes)


def make_policy(seed: int) -> TensorDictModule:
    """The MLP actor: observation -> action, wrapped for TensorDicts."""
    torch.manual_seed(seed)
    net = nn.Sequential(nn.Linear(OBS_DIM, 128), nn.ReLU(), nn.Linear(128, 128), nn.ReLU(), nn.Linear(128, ACT_DIM))
    return TensorDictModule(net, in_keys=["observation"], out_keys=["action"])


def train(cfg: DemoConfig, buffer: TensorDictReplayBuffer, weighting: str, actor: TensorDictModule) -> list[float]:
    """Train ``actor`` in place with ``TARLoss(weighting)``; return the loss per step."""
    loss = TARLoss(
        BCLoss(actor, loss_function="mse", reduction="none"),
        weighting,
        schedule=MixSchedule(start=cfg.steps // 5, ramp=cfg.steps * 3 // 10),
    )
    optim = torch.optim.Adam(loss.parameters(), lr=1e-3)
    torch.manual_seed(cfg.seed + 1)  # the same batches for every weighting
    history = []
    for _ in range(cfg.steps):
        batch = buffer.sample().reshape(cfg.batch_segments, cfg.slice_len)
        out = loss(batch)
        out["loss_tar"].backward()
        optim.step()
        optim.zero_grad()
        history.append(out["uniform_loss"].item())
    return history


def run(cfg: DemoConfig | None = None) -> dict:
    """Run the demonstration; print a report and return its numbers."""
    cfg = cfg or DemoConfig()
    logging.getLogger("torchrl").setLevel(logging.WARNING)
    warnings.filterwarnings("ignore", message="The name target_actor_network_params wasn't part of the annotations")
    started = time.perf_counter()
    generator = torch.Generator().manual_seed(cfg.seed)
    train_data = make_demonstrations(cfg.n_train, generator)
    test_data = make_demonstrations(cfg.n_test, generator, first_episode=cfg.n_train)
    contact = test_data["contact"]
    near = torch.zeros_like(contact)
    for shift in range(-CONTACT_WINDOW, CONTACT_WINDOW + 1):
        near |= contact.roll(shift)
    report: dict = {"weightings": {}}
    print(
        f"tar-rl demo: {cfg.n_train} demonstrations ({train_data.shape[0]} steps), segments "
        f"[{cfg.batch_segments}, {cfg.slice_len}], {cfg.steps} steps per weighting\n"
    )
    base = make_policy(cfg.seed)
    with tempfile.TemporaryDirectory() as scratch:
        buffer = TensorDictReplayBuffer(
            storage=LazyMemmapStorage(train_data.shape[0], scratch_dir=scratch),
            sampler=SliceSampler(slice_len=cfg.slice_len, traj_key="episode", strict_length=False, pad_output=True),
            batch_size=cfg.batch_segments * cfg.slice_len,
        )
        buffer.extend(train_data)
        for name in cfg.weightings:
            actor = copy.deepcopy(base)
            history = train(cfg, buffer, name, actor)
            with torch.no_grad():
                err = (actor(test_data.exclude("action").clone())["action"] - test_data["action"]).square().mean(-1)
            report["weightings"][name] = {
                "train_loss_last50": sum(history[-50:]) / 50,
                "test_mse_near_contact": err[near].mean().item(),
                "test_mse_elsewhere": err[~near].mean().item(),
            }
        weights = TARLoss(BCLoss(actor, loss_function="mse", reduction="none"), "tar", return_weights=True)
        first = test_data[test_data["episode"] == cfg.n_train][: 3 * cfg.slice_len]
        t = first.shape[0] - first.shape[0] % cfg.slice_len
        with torch.no_grad():
            w = weights(first[:t].reshape(-1, cfg.slice_len))["weights"].reshape(-1)
    print(
        f"TAR weights along a held-out demonstration, policy trained with {name!r} "
        "(segments of L steps, '*' = contact):"
    )
    _print_weights(w, first["contact"][:t])
    print("\nheld-out per-step action MSE (lower is better):")
    print(f"  {'weighting':<10} {'train loss':>11} {'near contact':>13} {'elsewhere':>10}")
    for name, row in report["weightings"].items():
        print(
            f"  {name:<10} {row['train_loss_last50']:>11.4f} {row['test_mse_near_contact']:>13.4f} "
            f"{row['test_mse_elsewhere']:>10.4f}"
        )
    report["seconds"] = time.perf_counter() - started
    print(f"\ndone in {report['seconds']:.1f} s")
    return report


def _print_weights(weights: torch.Tensor, contact: torch.Tensor) -> None:
    for t, (w, c) in enumerate(zip(weights.tolist(), contact.tolist())):
        print(f"  t={t:3d} {'*' if c else ' '} {w:5.2f} {'#' * round(w * 10)}")
