"""Segments of a dataset's episodes for training: :class:`SegmentSampler` over TorchRL's ``SliceSampler``."""

from __future__ import annotations

from collections.abc import Iterable, Iterator

import torch
from tensordict import TensorDict
from torchrl.data import SliceSampler, TensorDictReplayBuffer, TensorStorage

from .checks import positive_int

__all__ = ["EPISODE_LENGTH_KEY", "VALID_KEY", "SegmentSampler"]

VALID_KEY = ("collector", "mask")  # the [B, L] validity of a sampled segment, True on real steps
EPISODE_LENGTH_KEY = "episode_length"  # the [B, L] length of each sampled step's episode


class _OneGatherSliceSampler(SliceSampler):
    """``SliceSampler`` without its second read of the storage (used by :class:`SegmentSampler` only).

    torchrl 0.14's ``SliceSampler._finalize_index`` gathers every sampled entry of the storage
    (``storage[index]``) to look for a stored ``is_init`` to mark slice starts in, and the buffer
    then gathers them again for the batch. With ``truncated_key=None`` and ``init_key=None``
    that first gather is read by nothing: this returns the same index and mask without it
    (tests/data/test_data.py checks the batches equal those of the plain ``SliceSampler``).
    """

    def _finalize_index(self, *, index, num_slices, seq_length, target_seq_length, mask_flat, storage):
        if self.truncated_key is not None or self.init_key is not None:
            return super()._finalize_index(
                index=index,
                num_slices=num_slices,
                seq_length=seq_length,
                target_seq_length=target_seq_length,
                mask_flat=mask_flat,
                storage=storage,
            )
        info = {} if mask_flat is None else {("collector", "mask"): mask_flat}
        return index.to(torch.long).unbind(-1), info


class SegmentSampler:
    """Draws ``[B, L]`` segments of the dataset's episodes with TorchRL's ``SliceSampler``.

    ``buffer`` is a ``TensorDictReplayBuffer`` sampling with ``SliceSampler(slice_len=L,
    traj_key="episode", strict_length=False, pad_output=True)``; its flat ``[B * L]`` sample is
    reshaped to ``[B, L]``. Segments lie within one episode; ``SliceSampler`` places them so that
    they fit, so only a segment of an episode shorter than ``L`` is cut at the episode's end and
    padded at its end (the last real step repeated). ``("collector", "mask")`` is the ``[B, L]``
    bool validity mask, True on real steps (all True when no segment needed padding). The stored
    ``("next", "truncated")`` is returned as stored (the sampler's slice-end marking is off).

    ``episode_length`` (``[B, L]`` int64) is the number of steps of each step's episode, so that with
    the stored ``step`` a step's normalised time in its episode is known (what the ``dro_time``
    weighting reads); ``SliceSampler`` gives no such entry. It is looked up in a table of episode
    lengths counted once here (``torch.bincount`` of the stored ``episode``, the ids ``0 .. E-1``
    of the dataset format; any ids ``>= 0`` work).

    The buffer's ``TensorStorage`` holds plain-tensor views of the dataset's memory maps (zero
    copy): indexing a ``MemoryMappedTensor`` goes through a Python override per entry, and
    ``SliceSampler`` indexes the storage twice per batch, which made sampling ~40% slower; the
    second read (a look for a stored ``is_init``, which the dataset does not have) is skipped
    (``_OneGatherSliceSampler``).

    Args:
        storage: the dataset's ``TensorStorage`` (or any filled ``TensorStorage``, a ``LazyMemmapStorage`` too).
        batch_segments: ``B``.
        slice_len: ``L``.
        keys: the entries to sample (nested keys as tuples); default all. ``"episode"`` is
            always included; ``"episode_length"`` is always written (it may be named here, it is
            not stored). Fewer entries sample faster.
        generator: optional ``torch.Generator`` for reproducible sampling.
    """

    def __init__(
        self,
        storage: TensorStorage,
        batch_segments: int,
        slice_len: int,
        keys: Iterable | None = None,
        generator: torch.Generator | None = None,
    ):
        self.batch_segments = positive_int("batch_segments", batch_segments)
        self.slice_len = positive_int("slice_len", slice_len)
        self.dataset_storage = storage  # keeps the memory maps alive
        stored = storage._storage[: len(storage)]
        episode = stored.get("episode").as_subclass(torch.Tensor).long().reshape(-1)
        if episode.numel() and int(episode.min()) < 0:
            raise ValueError(f"the dataset's episode ids must be >= 0, got {int(episode.min())}")
        # episode id -> its number of steps (all of an episode's steps are stored)
        self.episode_lengths = torch.bincount(episode)
        if keys is not None:
            keys = [k for k in dict.fromkeys([*keys, "episode"]) if k != EPISODE_LENGTH_KEY]
            available = set(stored.keys(True, True))
            unknown = [k for k in keys if k not in available]
            if unknown:
                raise KeyError(f"unknown dataset entries {unknown}; the dataset holds {sorted(map(str, available))}")
            stored = stored.select(*keys)
        views = stored.apply(lambda x: x.as_subclass(torch.Tensor))
        self.buffer = TensorDictReplayBuffer(
            storage=TensorStorage(views),
            sampler=_OneGatherSliceSampler(
                slice_len=self.slice_len,
                traj_key="episode",
                strict_length=False,
                pad_output=True,
                cache_values=True,
                truncated_key=None,
                init_key=None,  # the dataset stores no is_init: nothing to mark
            ),
            batch_size=self.batch_segments * self.slice_len,
            generator=generator,
        )

    def sample(self) -> TensorDict:
        """A ``[B, L]`` TensorDict of segments with the bool mask at ``("collector", "mask")`` and
        each step's ``episode_length``."""
        batch = self.buffer.sample().reshape(self.batch_segments, self.slice_len)
        if VALID_KEY not in batch.keys(True):
            # SliceSampler writes the mask only when some slice needed padding.
            batch.set(VALID_KEY, torch.ones(batch.shape, dtype=torch.bool))
        batch.set(EPISODE_LENGTH_KEY, self.episode_lengths[batch.get("episode").long()])
        return batch

    def __iter__(self) -> Iterator[TensorDict]:
        while True:
            yield self.sample()
