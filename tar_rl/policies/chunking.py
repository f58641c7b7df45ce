"""What every chunked head shares: its settings, its training loss and its inference actor.

A chunked head predicts the next ``H`` actions (a chunk) from the current observation (or the last
``K`` observations) and the task. Three parts serve every such head (``act``, ``octo_linear``,
``octo_diffusion``, ``flow``):

**Settings** (:class:`ChunkedHeadConfig`): the task conditioning, the observation kind and its
normalisation, and how chunks are executed at inference, defined and validated once; each head's
config adds its own fields.

**Training loss** (:class:`ChunkLoss`): one TorchRL ``LossModule`` for every chunked head. The
head's model says which entries it reads (``loss_inputs``) and computes, from them, the loss of
every chunk element ``[B, L, H, A]`` (never reduced) plus optional scalars (``loss_extras``, e.g.
ACT's KL term ``loss_kl`` and its diagnostic ``kl``). Its supervision target is the expert chunk
``action_chunk`` (:attr:`ChunkLoss.target_key`): the objective's supervision transforms (the
``perturb_*`` controls of ``tar_rl.TARLoss``) corrupt that entry. What a padded chunk entry (past
the episode's end, ``action_chunk_valid`` False) contributes is the model's choice; ``TARLoss``
averages each step's loss over the valid entries only (``Policy.event_valid``). A model may offer
ranking signals besides its loss (``signals``, e.g. the ``flow`` head's implied action error):
``ChunkLoss(..., signal=name)`` returns the chosen one beside the loss, one value per step, for
``TARLoss`` to rank the steps by.

**Inference** (:class:`ChunkedActor`): the evaluator collectors call the actor once per environment
step on an ``[N]`` batch of slots, with ``is_init`` (``[N, 1]`` bool, TorchRL's ``InitTracker``)
True on the first step of each slot's rollout. The actor turns chunks into one action per step and
keeps, per slot, what that needs across calls:

* the observation window ``[N, K, D]`` (oldest first, the current observation last) and its
  validity ``[N, K]``: on a rollout's first step only the last entry is real, as in the training
  data's ``observation_history`` (``tar_rl.data``), where entries before the episode start repeat
  the first observation and are flagged invalid;
* ``execution="ensemble"``: ACT's temporal ensembling (Zhao et al. 2023): the action at time ``t``
  is the weighted mean of every prediction made for ``t`` by the chunks of steps ``t-H+1 .. t``
  (since the rollout's start), the prediction made at step ``s`` weighted ``exp(-m * (s - s0))``
  with ``s0`` the oldest of them, ``m = ensemble_decay``: older predictions weigh more. A new chunk
  is predicted every step;
* ``execution="open_loop"``: the first ``execute_steps`` actions of a chunk are executed one per
  step, then a new chunk is predicted (for the slots that need one; the model runs on the whole
  batch only when some slot does).

Actions are clipped to the action space ``[-1, 1]``. The per-slot state is plain tensors held on
the module (not buffers: it is not part of a checkpoint), reset wherever ``is_init`` is True and
dropped when the batch size changes.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import nn
from torchrl.objectives import LossModule

from tar_rl.objectives.elementwise import element_mean
from tar_rl.objectives.inner import SIGNAL

from .base import DataInfo, Policy
from .common import TASK_CONDITIONING

__all__ = ["EXECUTIONS", "TIME", "ChunkLoss", "ChunkedActor", "ChunkedHeadConfig", "check_execution", "chunked_policy"]

EXECUTIONS = ("ensemble", "open_loop")
#: The extra a model offering ranking signals returns beside its loss: each step's training time ``[*B]``.
TIME = "time"


# -- Settings ------------------------------------------------------------------------------------


def check_execution(execution: str, execute_steps: int, ensemble_decay: float, horizon: int) -> None:
    """Raise ``ValueError`` naming the setting for a bad chunk execution (``horizon``: the chunk length ``H``)."""
    if execution not in EXECUTIONS:
        raise ValueError(f"policy.execution must be one of {list(EXECUTIONS)}, got {execution!r}")
    if execution == "open_loop" and not 1 <= execute_steps <= horizon:
        raise ValueError(f"policy.execute_steps must lie in 1..{horizon} (the chunk horizon), got {execute_steps}")
    if not (math.isfinite(ensemble_decay) and ensemble_decay >= 0):
        raise ValueError(f"policy.ensemble_decay must be a finite number >= 0, got {ensemble_decay}")


@dataclass
class ChunkedHeadConfig:
    """Settings every chunked head has: inputs and chunk execution; a head's config inherits them and adds its own.

    Attributes:
        name: registry name (each head's config sets it).
        task_conditioning: the task token: ``embedding`` (learned, one per task) or ``instruction``
            (the words of the task's instruction, :class:`~tar_rl.policies.common.TaskEncoder`).
        execution: inference: ``ensemble`` (ACT's temporal ensembling, a new chunk every step) or
            ``open_loop`` (``execute_steps`` actions of each chunk, then a new one).
        execute_steps: actions executed per chunk with ``open_loop`` (``1 .. H``).
        ensemble_decay: ``m`` of the temporal ensemble's weights ``exp(-m * i)`` (ACT: 0.01).
        normalize_obs: standardise observations with the training data's statistics.
        observation: ``state`` or ``image`` (the current camera image, read as one more token,
            plus the proprioceptive state; needs a dataset with images, ``data.image_size > 0``;
            see :mod:`tar_rl.policies.common`).
        compile: run the attention of training steps on the CPU through ``torch.compile``
            (:mod:`tar_rl.policies.attention`): the same model and, up to float rounding, the same
            numbers, faster steps after a compilation of seconds per attention shape at the start
            (needs a C++ compiler). Evaluation and CUDA runs are unaffected.
    """

    name: str
    task_conditioning: str = "embedding"
    execution: str = "ensemble"
    execute_steps: int = 1
    ensemble_decay: float = 0.01
    normalize_obs: bool = True
    observation: str = "state"
    compile: bool = False

    def check_chunking(self, horizon: int) -> None:
        """Raise ``ValueError`` naming the setting for a bad shared setting (``horizon``: the chunk length ``H``)."""
        if self.task_conditioning not in TASK_CONDITIONING:
            raise ValueError(
                f"policy.task_conditioning must be one of {list(TASK_CONDITIONING)}, got {self.task_conditioning!r}"
            )
        check_execution(self.execution, self.execute_steps, self.ensemble_decay, horizon)


# -- Training loss -------------------------------------------------------------------------------


class ChunkLoss(LossModule):
    """Per-step loss of a chunked head: the loss of every chunk element ``[*B, H, A]``, never reduced.

    The model (shared with the inference actor) provides:

    * ``loss_inputs``: the names of the accepted keys (below) it reads, passed to ``chunk_loss`` as
      keyword arguments of those names; ``action_chunk_valid`` and ``valid`` are optional in the
      input (absent: ``None``, every entry and step real);
    * ``reads_pixels``: with image observations, ``pixels`` is read and passed as well;
    * ``chunk_loss(**inputs) -> (loss, extras)``: ``loss`` ``[*B, H, A]`` and ``extras``, a dict of
      scalars named in ``loss_extras``: ``loss_*`` ones are losses ``TARLoss`` adds unweighted,
      the others detached diagnostics;
    * optionally ``signals``, the names of the ranking signals it offers besides its loss. Such a model
      also returns, among its ``extras``, the training time each step's loss was drawn at, ``[*B]``
      (:data:`TIME`, not part of the output), and provides ``signal_state(name)`` (a module holding
      the signal's state, or ``None``) and ``step_signal(name, step_loss, time, valid, state, update)
      -> [*B]`` (``step_loss``: each step's loss, the mean over its valid chunk entries as ``TARLoss``
      takes it; ``valid``: ``True`` on real steps; ``update``: a training step, which moves the state).

    ``action_chunk_valid``, when present, must be ``torch.bool`` of the chunk's shape without the
    action dim.

    Args:
        model: the head's network.
        loss_name: the per-step output entry, ``loss_<something>`` (``Policy.loss_key`` names it
            when the model has ``loss_*`` extras).
        signal: ``"loss"`` (default: no signal in the output) or one of the model's ``signals``, returned
            detached as the output entry ``"signal"`` ``[*B]`` (``TARLoss``'s ``signal`` key). Its state, if
            any, is the submodule ``signal_state`` (in ``state_dict()``: a resumed run continues it) and moves
            on a training step (training mode, gradients enabled).

    Input: a TensorDict of batch shape ``[*B]`` (``[B, L]`` segments in training) with the keys the
    model reads. It is not modified.
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable input keys.

        Attributes:
            observation (NestedKey): ``[*B, D]`` current observations. Defaults to ``"observation"``.
            observation_history (NestedKey): ``[*B, K, D]`` observation window, oldest first.
                Defaults to ``"observation_history"``.
            observation_history_valid (NestedKey): ``[*B, K]`` bool, True on real observations.
                Defaults to ``"observation_history_valid"``.
            task_id (NestedKey): ``[*B]`` int64 task ids. Defaults to ``"task_id"``.
            action_chunk (NestedKey): ``[*B, H, A]`` the next ``H`` expert actions, the supervision
                target. Defaults to ``"action_chunk"``.
            action_chunk_valid (NestedKey): ``[*B, H]`` bool, True on chunk entries that are real
                steps (a prefix). Defaults to ``"action_chunk_valid"``.
            valid (NestedKey): ``[*B]`` bool, True on real steps. Defaults to ``("collector", "mask")``.
            pixels (NestedKey): ``[*B, 3, S, S]`` uint8 camera images, read by models with image
                observations only. Defaults to ``"pixels"``.
        """

        observation: NestedKey = "observation"
        observation_history: NestedKey = "observation_history"
        observation_history_valid: NestedKey = "observation_history_valid"
        task_id: NestedKey = "task_id"
        action_chunk: NestedKey = "action_chunk"
        action_chunk_valid: NestedKey = "action_chunk_valid"
        valid: NestedKey = ("collector", "mask")
        pixels: NestedKey = "pixels"

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys
    reduction = "none"
    OPTIONAL = ("action_chunk_valid", "valid")

    def __init__(self, model: nn.Module, loss_name: str = "loss_chunk", signal: str = "loss"):
        if not loss_name.startswith("loss_"):
            raise ValueError(f"the loss entry must start with 'loss_', got {loss_name!r}")
        offered = ("loss", *getattr(model, "signals", ()))
        if signal not in offered:
            raise ValueError(
                f"the ranking signal {signal!r} is not one the {type(model).__name__} offers: {list(offered)}"
            )
        super().__init__()
        self.model = model
        self.loss_name = loss_name
        self.signal = signal
        self.signal_state = model.signal_state(signal) if signal != "loss" else None

    @property
    def signals(self) -> tuple[str, ...]:
        """The ranking signals it can return: ``"loss"`` (none beside the loss) and the model's."""
        return ("loss", *getattr(self.model, "signals", ()))

    def with_signal(self, signal: str) -> ChunkLoss:
        """A loss on the same model, with the same keys, that returns the ranking signal ``signal``."""
        loss = ChunkLoss(self.model, self.loss_name, signal)
        loss.set_keys(**dataclasses.asdict(self.tensor_keys))
        return loss

    @property
    def functional(self) -> bool:
        return False

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    @property
    def target_key(self) -> NestedKey:
        """The supervision target: the entry the objective's supervision transforms corrupt."""
        return self.tensor_keys.action_chunk

    @property
    def in_keys(self) -> list[NestedKey]:
        k = self.tensor_keys
        keys = [getattr(k, name) for name in self.model.loss_inputs]
        return keys + ([k.pixels] if self.model.reads_pixels else [])

    @property
    def out_keys(self) -> list[str]:
        return [self.loss_name, *self.model.loss_extras, *([SIGNAL] if self.signal != "loss" else [])]

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        """The model's unreduced chunk loss and its scalar extras (class docstring)."""
        k = self.tensor_keys
        inputs = {}
        for name in self.model.loss_inputs:
            key = getattr(k, name)
            inputs[name] = tensordict.get(key, None) if name in self.OPTIONAL else tensordict.get(key)
        chunk, chunk_valid = inputs.get("action_chunk"), inputs.get("action_chunk_valid")
        if chunk_valid is not None and (chunk_valid.dtype != torch.bool or chunk_valid.shape != chunk.shape[:-1]):
            raise ValueError(
                f"{k.action_chunk_valid!r} must be torch.bool of shape {list(chunk.shape[:-1])}, "
                f"got {chunk_valid.dtype} {list(chunk_valid.shape)}"
            )
        if self.model.reads_pixels:
            inputs["pixels"] = tensordict.get(k.pixels)
        loss, extras = self.model.chunk_loss(**inputs)
        time = extras.get(TIME)
        extras = {name: value for name, value in extras.items() if name != TIME}
        if self.signal != "loss":
            extras[SIGNAL] = self._signal(loss.detach(), time, tensordict, chunk_valid)
        return TensorDict({self.loss_name: loss, **extras}, batch_size=[])

    def _signal(self, loss: torch.Tensor, time, tensordict: TensorDictBase, chunk_valid) -> torch.Tensor:
        """The chosen ranking signal ``[*B]``, detached, from each step's loss as ``TARLoss`` takes it (the mean
        over the step's valid chunk entries) and the model's training times; its state moves on a training step."""
        lead = loss.ndim - 2
        if chunk_valid is None:
            steps = loss.mean((-2, -1))
        else:
            steps = element_mean(loss, chunk_valid[..., None].expand_as(loss), lead)
        valid = tensordict.get(self.tensor_keys.valid, None)
        valid = torch.ones_like(steps, dtype=torch.bool) if valid is None else valid.reshape(steps.shape)
        update = self.training and torch.is_grad_enabled()
        return self.model.step_signal(self.signal, steps, time, valid, self.signal_state, update).detach()


# -- Inference -----------------------------------------------------------------------------------


class ChunkedActor(TensorDictModuleBase):
    """The inference actor of a chunked head (see the module docstring).

    Args:
        model: an ``nn.Module`` with ``predict_chunk(history, history_valid, task_id) -> [N, H, A]``
            (``history`` ``[N, K, D]`` oldest first, ``history_valid`` ``[N, K]`` bool, ``task_id``
            ``[N]`` int64). Its parameters are this actor's parameters.
        horizon: ``H``, the chunk length the model predicts.
        history: ``K``, the observation window the model reads (1: the current observation only).
        execution: ``"ensemble"`` or ``"open_loop"``.
        execute_steps: for ``open_loop``, actions executed per chunk, ``1 <= k <= H``.
        ensemble_decay: ``m`` of the temporal ensemble's weights ``exp(-m * i)`` (ACT: 0.01).
        images: the model reads the current camera image: ``pixels`` ``[N, 3, S, S]`` is an input
            key and goes to ``predict_chunk(..., pixels=...)``.

    Reads ``observation`` ``[N, D]``, ``task_id`` ``[N]`` (or ``[N, 1]``), ``is_init``
    ``[N, 1]`` (absent: every call starts new rollouts) and, with ``images``, ``pixels``; writes
    ``action`` ``[N, A]``.
    """

    in_keys = ["observation", "task_id", "is_init"]
    out_keys = ["action"]

    def __init__(
        self,
        model: nn.Module,
        horizon: int,
        history: int = 1,
        execution: str = "ensemble",
        execute_steps: int = 1,
        ensemble_decay: float = 0.01,
        images: bool = False,
    ):
        super().__init__()
        if horizon < 1 or history < 1:
            raise ValueError(f"the chunk horizon and the history must be >= 1, got {horizon} and {history}")
        check_execution(execution, execute_steps, ensemble_decay, horizon)
        self.model = model
        self.horizon, self.history = int(horizon), int(history)
        self.execution, self.execute_steps = execution, int(execute_steps)
        self.ensemble_decay = float(ensemble_decay)
        self.images = bool(images)
        if self.images:
            self.in_keys = [*self.in_keys, "pixels"]
        self.reset()

    def reset(self) -> None:
        """Forget every slot's state (the next call starts new rollouts)."""
        self._window = self._window_valid = None
        self._sum = self._weight = None  # ensemble: [N, H, A] weighted sums and [N, H] weights, offset from now
        self._chunk = self._age = None  # open loop: [N, H, A] current chunk and [N] actions taken from it

    def __getstate__(self):
        state = dict(self.__dict__)
        for name in ("_window", "_window_valid", "_sum", "_weight", "_chunk", "_age"):
            state[name] = None  # a pickled copy (an evaluation worker) starts without rollouts
        return state

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs = tensordict.get("observation")
        task = tensordict.get("task_id")
        task = task.reshape(obs.shape[0]) if task.ndim > 1 else task
        n = obs.shape[0]
        init = tensordict.get("is_init", None)
        init = torch.ones(n, dtype=torch.bool, device=obs.device) if init is None else init.reshape(n).bool()
        if self._window is None or self._window.shape[0] != n or self._window.device != obs.device:
            self.reset()
            init = torch.ones_like(init)
            k = self.history
            self._window = obs.new_zeros(n, k, obs.shape[-1])
            self._window_valid = torch.zeros(n, k, dtype=torch.bool, device=obs.device)
        self._push(obs, init)
        pixels = tensordict.get("pixels") if self.images else None
        if self.execution == "ensemble":
            action = self._ensemble(task, init, pixels)
        else:
            action = self._open_loop(task, init, pixels)
        tensordict.set("action", action.clamp(-1.0, 1.0))
        return tensordict

    # -- state updates -------------------------------------------------------------------------

    def _push(self, obs: torch.Tensor, init: torch.Tensor) -> None:
        window = torch.cat([self._window[:, 1:], obs[:, None]], dim=1)
        valid = torch.cat([self._window_valid[:, 1:], torch.ones_like(init)[:, None]], dim=1)
        fresh = obs[:, None].expand_as(window)  # a new rollout: the first observation repeated, flagged invalid
        fresh_valid = torch.zeros_like(valid)
        fresh_valid[:, -1] = True
        self._window = torch.where(init[:, None, None], fresh, window)
        self._window_valid = torch.where(init[:, None], fresh_valid, valid)

    def _predict(self, task: torch.Tensor, pixels: torch.Tensor | None) -> torch.Tensor:
        images = {"pixels": pixels} if self.images else {}
        chunk = self.model.predict_chunk(self._window, self._window_valid, task, **images)
        n = self._window.shape[0]
        if chunk.ndim != 3 or chunk.shape[:2] != (n, self.horizon):
            raise ValueError(f"predict_chunk returned shape {list(chunk.shape)}, expected [{n}, {self.horizon}, A]")
        return chunk

    def _ensemble(self, task: torch.Tensor, init: torch.Tensor, pixels: torch.Tensor | None) -> torch.Tensor:
        chunk = self._predict(task, pixels)
        n, h, a = chunk.shape
        if self._sum is None:
            self._sum = chunk.new_zeros(n, h, a)
            self._weight = chunk.new_zeros(n, h)
        else:
            # Move the window on by one step; earlier predictions gain exp(m) against the new one,
            # which is weight exp(-m * i) counted from the oldest, up to a common factor.
            grow = math.exp(self.ensemble_decay)
            self._sum = torch.cat([self._sum[:, 1:], chunk.new_zeros(n, 1, a)], dim=1) * grow
            self._weight = torch.cat([self._weight[:, 1:], chunk.new_zeros(n, 1)], dim=1) * grow
        keep = (~init).to(chunk.dtype)
        self._sum = self._sum * keep[:, None, None] + chunk
        self._weight = self._weight * keep[:, None] + 1.0
        return self._sum[:, 0] / self._weight[:, 0, None]

    def _open_loop(self, task: torch.Tensor, init: torch.Tensor, pixels: torch.Tensor | None) -> torch.Tensor:
        n = init.shape[0]
        if self._chunk is None:
            need = torch.ones_like(init)
            self._age = torch.zeros(n, dtype=torch.long, device=init.device)
        else:
            need = init | (self._age >= self.execute_steps)
        if bool(need.any()):
            chunk = self._predict(task, pixels)
            self._chunk = chunk if self._chunk is None else torch.where(need[:, None, None], chunk, self._chunk)
            self._age = torch.where(need, torch.zeros_like(self._age), self._age)
        action = self._chunk[torch.arange(n, device=init.device), self._age]
        self._age = self._age + 1
        return action


# -- The policy ----------------------------------------------------------------------------------


def chunked_policy(model: nn.Module, cfg: ChunkedHeadConfig, info: DataInfo, loss_name: str, history: int) -> Policy:
    """The :class:`Policy` of a chunked head: a :class:`ChunkedActor` and a :class:`ChunkLoss` sharing ``model``.

    ``history``: the observation window ``K`` the model reads (1: the current observation only).
    """
    images = bool(model.reads_pixels)
    actor = ChunkedActor(
        model,
        horizon=info.chunk_horizon,
        history=history,
        execution=cfg.execution,
        execute_steps=cfg.execute_steps,
        ensemble_decay=cfg.ensemble_decay,
        images=images,
    )
    loss = ChunkLoss(model, loss_name)
    k = loss.tensor_keys
    data = [key for key in loss.in_keys if key not in (k.valid, k.pixels)]
    # "action" is not read by the loss: the recipe's weight recording plots its gripper dimension.
    keys = (*data, "action", *([k.pixels] if images else []))
    several = any(name.startswith("loss_") for name in model.loss_extras)
    return Policy(
        actor=actor,
        loss=loss,
        keys=keys,
        event_valid=k.action_chunk_valid,
        loss_key=loss_name if several else None,
    )
