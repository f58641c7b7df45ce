"""The inputs every head shares: observation normalisation, task conditioning and the image encoder.

**Observation normalisation** (:class:`ObsNorm`): ``(x - mean) / std`` with the training data's
statistics held as buffers, so a checkpoint's state dict restores them.

**Task conditioning** (:class:`TaskEncoder`): ``TaskEncoder(kind, n_tasks, dim, instructions=None)``
maps ``task_id`` (``[...]`` int64, the index in the dataset's ``task_names``, whose instruction texts
are ``instructions``) to ``[..., dim]``:

* ``embedding``: one learned vector per task id (the default of every head);
* ``instruction``: the task's instruction sentence (one per task id, from the dataset's metadata) as
  a bag of words: lower-cased words (runs of letters and digits), a learned vector
  per word of the instructions' vocabulary, mean-pooled, then a linear layer. Tasks that share words share
  parameters, so related tasks ("Push the puck ...", "Push the puck to the goal ...") start close.
  No pretrained language model is used: nothing can be downloaded at run time here, and the paper's language encoders
  are part of the pretrained policies it fine-tunes.

**Image observations** (:class:`ConvEncoder`, :func:`image_encoder`): with ``observation="image"`` a
head sees the camera image ``pixels`` (``[..., 3, S, S]`` uint8, see :mod:`tar_rl.collectors.metaworld.render`)
and the robot's own state only: the first :data:`PROPRIO_DIMS` entries of MetaWorld's observation
(hand position x, y, z and the gripper opening). The object and goal positions of the state vector
are left out: they must be seen in the image. Every head takes the switch
(``policy.observation=image``): the ``mlp`` head concatenates the image features to the
proprioceptive state; the transformer heads (``act``, ``octo_*``, ``flow``) read the image of the
current step as one more token (see their modules). Only the current step's image is stored and
seen: the observation history of the Octo-style backbone holds proprioception.
"""

from __future__ import annotations

import re
from collections.abc import Sequence

import torch
from torch import nn

__all__ = [
    "OBSERVATIONS",
    "PROPRIO_DIMS",
    "TASK_CONDITIONING",
    "ConvEncoder",
    "ObsNorm",
    "TaskEncoder",
    "image_encoder",
    "instruction_tokens",
]


# -- Observation normalisation ---------------------------------------------------------------


class ObsNorm(nn.Module):
    """``(x - mean) / std`` with statistics held as buffers (std floored at 1e-3: some MetaWorld
    observation dims are constant within a task)."""

    def __init__(self, dim: int, mean=None, std=None, min_std: float = 1e-3):
        super().__init__()
        mean = torch.zeros(dim) if mean is None else torch.as_tensor(mean, dtype=torch.float32)
        std = torch.ones(dim) if std is None else torch.as_tensor(std, dtype=torch.float32)
        if mean.shape != (dim,) or std.shape != (dim,):
            raise ValueError(
                f"observation statistics must have shape ({dim},), got {tuple(mean.shape)}, {tuple(std.shape)}"
            )
        self.register_buffer("mean", mean.clone())
        self.register_buffer("std", std.clamp_min(min_std))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.mean) / self.std


# -- Task conditioning -------------------------------------------------------------------------

TASK_CONDITIONING = ("embedding", "instruction")


def instruction_tokens(
    n_tasks: int, instructions: Sequence[str] | None = None
) -> tuple[torch.Tensor, torch.Tensor, int]:
    """Word ids ``[n_tasks, W]`` of each task's instruction (padded with 0), their ``[n_tasks, W]`` mask,
    and the vocabulary size (id 0 is padding).

    ``instructions``: the text of each task id; every task id needs one.
    """
    if instructions is None:
        raise ValueError(
            "policy.task_conditioning=instruction needs the instruction text of every task id; the data has none"
        )
    if len(instructions) != n_tasks:
        raise ValueError(f"{len(instructions)} instructions for {n_tasks} task ids")
    missing = [i for i, t in enumerate(instructions) if not t or not t.strip()]
    if missing:
        raise ValueError(
            f"task ids {missing} have no instruction text, which policy.task_conditioning=instruction needs "
            "(an imported dataset without instructions: use task_conditioning=embedding)"
        )
    text = [t.lower() for t in instructions]
    sentences = [re.findall(r"[a-z0-9]+", t) for t in text]
    vocab = {w: j + 1 for j, w in enumerate(sorted({w for s in sentences for w in s}))}
    width = max(1, max(len(s) for s in sentences))
    ids = torch.zeros(n_tasks, width, dtype=torch.long)
    for i, words in enumerate(sentences):
        ids[i, : len(words)] = torch.tensor([vocab[w] for w in words], dtype=torch.long)
    return ids, ids > 0, len(vocab) + 1


class TaskEncoder(nn.Module):
    """``task_id [...] -> [..., dim]`` by a learned embedding or the instruction's words (module docstring)."""

    def __init__(self, kind: str, n_tasks: int, dim: int, instructions: Sequence[str] | None = None):
        super().__init__()
        if kind not in TASK_CONDITIONING:
            raise ValueError(f"policy.task_conditioning must be one of {list(TASK_CONDITIONING)}, got {kind!r}")
        if dim < 1:
            raise ValueError(f"the task embedding width must be >= 1, got {dim}")
        self.kind = kind
        if kind == "embedding":
            self.embedding = nn.Embedding(n_tasks, dim)
        else:
            ids, mask, vocab = instruction_tokens(n_tasks, instructions)
            self.register_buffer("word_ids", ids, persistent=False)
            self.register_buffer("word_mask", mask, persistent=False)
            self.words = nn.Embedding(vocab, dim, padding_idx=0)
            self.project = nn.Linear(dim, dim)

    def task_rows(self, task_ids: Sequence[int]) -> dict[str, torch.Tensor]:
        """The rows of this encoder's tables that training on ``task_ids`` updates: ``{parameter name: [rows] bool}``.

        ``embedding``: the rows of those task ids. ``instruction``: the rows of the words of their
        instructions (the projection is shared by every task and not listed). A row outside these
        gets no gradient from those tasks' data.
        """
        ids = torch.as_tensor(list(task_ids), dtype=torch.long)
        if self.kind == "embedding":
            rows = torch.zeros(self.embedding.num_embeddings, dtype=torch.bool)
            rows[ids] = True
            return {"embedding.weight": rows}
        rows = torch.zeros(self.words.num_embeddings, dtype=torch.bool)
        rows[self.word_ids[ids][self.word_mask[ids]]] = True
        return {"words.weight": rows}

    def forward(self, task_id: torch.Tensor) -> torch.Tensor:
        if self.kind == "embedding":
            return self.embedding(task_id)
        mask = self.word_mask.to(self.words.weight.dtype)  # [T, W]
        pooled = (self.words(self.word_ids) * mask[..., None]).sum(1) / mask.sum(1, keepdim=True).clamp_min(1)
        return self.project(pooled)[task_id]


# -- Image observations ------------------------------------------------------------------------

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
