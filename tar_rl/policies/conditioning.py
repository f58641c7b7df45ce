"""Task conditioning shared by the heads: a learned task embedding or an instruction-text embedding.

``TaskEncoder(kind, n_tasks, dim, instructions=None)`` maps ``task_id`` (``[...]`` int64, the
index in ``tar_rl.collectors.tasks.TASKS``, or an imported dataset's own ids with their
``instructions``) to ``[..., dim]``:

* ``embedding``: one learned vector per task id (the default of every head);
* ``instruction``: the task's instruction sentence (``tasks.INSTRUCTIONS``, one per task, or the
  dataset's) as a bag of words: lower-cased words (runs of letters and digits), a learned vector
  per word of the instructions' vocabulary, mean-pooled, then a linear layer. Tasks that share words share
  parameters, so related tasks ("Push the puck ...", "Push the puck to the goal ...") start close.
  No pretrained language model is used: nothing can be downloaded at run time here, and the paper's language encoders
  are part of the pretrained policies it fine-tunes.
"""

from __future__ import annotations

import re
from collections.abc import Sequence

import torch
from torch import nn

from tar_rl.collectors.tasks import INSTRUCTIONS, TASKS

__all__ = ["TASK_CONDITIONING", "TaskEncoder", "instruction_tokens"]

TASK_CONDITIONING = ("embedding", "instruction")


def instruction_tokens(
    n_tasks: int, instructions: Sequence[str] | None = None
) -> tuple[torch.Tensor, torch.Tensor, int]:
    """Word ids ``[n_tasks, W]`` of each task's instruction (padded with 0), their ``[n_tasks, W]`` mask,
    and the vocabulary size (id 0 is padding).

    ``instructions``: the text of each task id (a dataset with its own task ids); ``None``:
    MetaWorld's (``tasks.INSTRUCTIONS`` in ``TASKS`` order). Every task needs a text.
    """
    if instructions is None:
        instructions = [INSTRUCTIONS[TASKS[i]] if i < len(TASKS) else "" for i in range(n_tasks)]
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
