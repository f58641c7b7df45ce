"""Policy heads, chosen by name from a small registry.

A head gives the recipe two things (:class:`Policy`):

* ``actor``: a ``TensorDictModule`` for inference, reading ``observation`` (``[..., D]``) and
  ``task_id`` (int64, the index in the dataset's ``task_names``) and writing ``action``
  (``[..., A]``). The evaluator collectors call it on ``[N]`` batches; it must be picklable.
* ``loss``: a TorchRL ``LossModule`` built with ``reduction="none"`` whose one ``loss_*`` output is
  the per-step loss ``[B, L]`` or ``[B, L, ...]`` on a ``[B, L]`` segment batch. Heads never
  average over the segment axis: ``tar_rl.TARLoss`` owns that reduction. A loss names its
  supervision target by a ``target_key`` (the chunked heads' :class:`ChunkLoss`: ``action_chunk``)
  or, as torchrl's BC losses do, by its ``action`` key: that is the entry the objective's
  supervision transforms (the ``perturb_*`` controls) corrupt.

The modules: :mod:`.base` (the shared types, :class:`DataInfo`, :class:`Policy`, :class:`PolicySpec`, and the
registry), :mod:`.common` (inputs every head shares: observation normalisation, task
conditioning, the image encoder), :mod:`.chunking` (what every chunked head shares: settings,
:class:`ChunkLoss`, the inference actor), and one module per head family: :mod:`.mlp`,
:mod:`.act`, :mod:`.octo` (the Octo-style backbone and ``octo_linear``), :mod:`.diffusion`
(``octo_diffusion``), :mod:`.flow`.

Every head is registered in :data:`POLICIES` with its config dataclass (the fields a recipe may
set, with defaults) and its builder ``build(config, info) -> Policy``. ``info``
(:class:`DataInfo`) carries what a head needs from the dataset: dimensions, normalisation
statistics, the number of task ids and their instructions. The statistics are stored as buffers
of the network, so a checkpoint's state dict restores them.
"""

from __future__ import annotations

from .base import POLICIES, DataInfo, Policy, PolicySpec, build_policy, register_policy

# The heads register themselves on import, in this order (the order of listings and messages).
# isort: off
from .mlp import MLPConfig, MLPPolicy
from .act import ACTConfig, ACTModel
from .octo import OctoConfig, OctoLinearConfig
from .diffusion import OctoDiffusionConfig
from .flow import FlowConfig

# isort: on
from .chunking import ChunkedHeadConfig, ChunkLoss
from .common import ObsNorm

__all__ = [
    "POLICIES",
    "ACTConfig",
    "ACTModel",
    "ChunkLoss",
    "ChunkedHeadConfig",
    "DataInfo",
    "FlowConfig",
    "MLPConfig",
    "MLPPolicy",
    "ObsNorm",
    "OctoConfig",
    "OctoDiffusionConfig",
    "OctoLinearConfig",
    "Policy",
    "PolicySpec",
    "build_policy",
    "register_policy",
]
