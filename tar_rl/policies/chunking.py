"""Inference for heads that predict action chunks and read a window of past observations.

A chunked head predicts the next ``H`` actions from the current observation (or the last ``K``
observations) and the task. The evaluator collectors call the actor once per environment step on
an ``[N]`` batch of slots, with ``is_init`` (``[N, 1]`` bool, TorchRL's ``InitTracker``) True on
the first step of each slot's rollout. :class:`ChunkedActor` turns chunks into one action per step
and keeps, per slot, what that needs across calls:

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

import math

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn

__all__ = ["EXECUTIONS", "ChunkedActor"]

EXECUTIONS = ("ensemble", "open_loop")


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
        if execution not in EXECUTIONS:
            raise ValueError(f"policy.execution must be one of {list(EXECUTIONS)}, got {execution!r}")
        if horizon < 1 or history < 1:
            raise ValueError(f"the chunk horizon and the history must be >= 1, got {horizon} and {history}")
        if execution == "open_loop" and not 1 <= execute_steps <= horizon:
            raise ValueError(f"policy.execute_steps must lie in 1..{horizon} (the chunk horizon), got {execute_steps}")
        if not (math.isfinite(ensemble_decay) and ensemble_decay >= 0):
            raise ValueError(f"policy.ensemble_decay must be a finite number >= 0, got {ensemble_decay}")
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
