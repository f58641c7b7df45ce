"""Image observations for the heads: a small conv encoder and the proprioceptive part of the state.

With ``observation="image"`` a head sees the camera image ``pixels`` (``[..., 3, S, S]`` uint8, see
:mod:`tar_rl.collectors.render`) and the robot's own state only: the first :data:`PROPRIO_DIMS`
entries of MetaWorld's observation (hand position x, y, z and the gripper opening). The object
and goal positions of the state vector are left out: they must be seen in the image.

Every head takes the switch (``policy.observation=image``): the ``mlp`` head concatenates the image
features to the proprioceptive state; the transformer heads (``act``, ``octo_*``, ``flow``) read
the image of the current step as one more token (see their modules). Only the current step's image
is stored and seen: the observation history of the Octo-style backbone holds proprioception.
"""

from __future__ import annotations

import torch
from torch import nn

__all__ = ["OBSERVATIONS", "PROPRIO_DIMS", "ConvEncoder", "image_encoder"]

OBSERVATIONS = ("state", "image")
PROPRIO_DIMS = 4


class ConvEncoder(nn.Module):
    """``pixels [..., 3, S, S]`` (uint8) -> ``[..., out_dim]``.

    Three stride-2 convolutions (32, 64, 64 channels) with ReLU, flattened, then a linear layer
    and LayerNorm. Pixels are scaled to ``[-0.5, 0.5]``. Any leading shape (``[N]`` at inference,
    ``[B, L]`` in training) is folded into one batch axis for the convolutions; steps are encoded
    independently.

    Args:
        image_size: ``S``.
        out_dim: feature width.
    """

    def __init__(self, image_size: int, out_dim: int):
        super().__init__()
        if image_size < 8:
            raise ValueError(f"data.image_size must be >= 8 pixels for the conv encoder, got {image_size}")
        if out_dim < 1:
            raise ValueError(f"the image feature width must be >= 1, got {out_dim}")
        self.image_size = image_size
        self.conv = nn.Sequential(
            nn.Conv2d(3, 32, 5, stride=2, padding=2),
            nn.ReLU(),
            nn.Conv2d(32, 64, 3, stride=2, padding=1),
            nn.ReLU(),
            nn.Conv2d(64, 64, 3, stride=2, padding=1),
            nn.ReLU(),
            nn.Flatten(),
        )
        with torch.no_grad():
            width = self.conv(torch.zeros(1, 3, image_size, image_size)).shape[-1]
        self.out = nn.Sequential(nn.Linear(width, out_dim), nn.LayerNorm(out_dim))

    def forward(self, pixels: torch.Tensor | None) -> torch.Tensor:
        if pixels is None:
            raise ValueError("this policy reads images (policy.observation=image): the input has no 'pixels'")
        lead = pixels.shape[:-3]
        if pixels.shape[-3:] != (3, self.image_size, self.image_size):
            raise ValueError(
                f"pixels of shape {list(pixels.shape)}: expected [..., 3, {self.image_size}, {self.image_size}]"
            )
        x = pixels.reshape(-1, *pixels.shape[-3:]).float() / 255.0 - 0.5
        return self.out(self.conv(x)).reshape(*lead, -1)


def image_encoder(observation: str, image_size: int, out_dim: int) -> ConvEncoder | None:
    """The conv encoder of a head with ``policy.observation=observation`` (``None`` for ``state``).

    Raises:
        ValueError: an unknown observation kind, or ``image`` on a dataset without images
            (``image_size`` 0).
    """
    if observation not in OBSERVATIONS:
        raise ValueError(f"policy.observation must be one of {list(OBSERVATIONS)}, got {observation!r}")
    if observation == "state":
        return None
    if not image_size:
        raise ValueError("policy.observation=image needs a dataset with images: set data.image_size (e.g. 64)")
    return ConvEncoder(image_size, out_dim)
