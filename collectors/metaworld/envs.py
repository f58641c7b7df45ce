"""TorchRL environments for MetaWorld v3: one task (``make_metaworld_env``) or a batch (``make_batched_env``).

Both are ``torchrl.envs.GymWrapper`` around bare MetaWorld environments (``tasks.make_env``; not
``GymEnv``, whose keyword arguments clash with MetaWorld's ``make``), with

* ``success``: a bool entry read from MetaWorld's info by ``SuccessReader`` (torchrl's
  ``default_info_dict_reader`` crashes on the Python float MetaWorld returns);
* ``observation`` in float32: MetaWorld gives float64; ``MaskedVectorEnv`` casts the batch once in
  numpy (its observation space is float32), and the one-task env uses ``DoubleToFloat``;
* ``task_id``: the task's fixed index (``tasks.task_index``, int64), written on reset and carried
  through every step by torchrl's ``TensorDictPrimer``, so that multi-task policies can read it.

``make_batched_env`` wraps a list of bare environments (each already ``set_task`` on its own
variation) in ``MaskedVectorEnv``, a gymnasium vector env that steps only the sub-environments
marked active. torchrl's ``SerialEnv`` does masked (partial) steps too, but builds and stacks one
TensorDict per sub-environment per step, which costs about as much as the MuJoCo step itself;
one GymWrapper around a vector env converts the whole batch at once. gymnasium's own
``SyncVectorEnv`` always steps every sub-environment (a finished MetaWorld rollout would keep
simulating, and raises after step 500), so the masked step is the small piece written here.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import numpy as np
import torch
from gymnasium.spaces import Box
from gymnasium.vector import AutoresetMode, SyncVectorEnv
from gymnasium.vector.utils import batch_space
from torchrl.data import Unbounded
from torchrl.envs import Compose, DoubleToFloat, GymWrapper, InitTracker, TensorDictPrimer, TransformedEnv
from torchrl.envs.gym_like import BaseInfoDictReader

from tar_rl.collectors.metaworld import tasks

__all__ = ["MaskedVectorEnv", "SuccessReader", "make_batched_env", "make_metaworld_env"]


class SuccessReader(BaseInfoDictReader):
    """Writes MetaWorld's ``info["success"]`` (a Python float, or an array for a vector env) as a bool tensor.

    Reset infos carry no ``success``: it is then False.
    """

    def __init__(self, batch_size: Sequence[int] = ()):
        self.batch_size = torch.Size(batch_size)

    def __call__(self, info_dict, tensordict):
        value = info_dict.get("success") if isinstance(info_dict, dict) else None
        if value is None:
            success = torch.zeros(self.batch_size, dtype=torch.bool)
        else:
            success = torch.as_tensor(np.asarray(value, dtype=np.float32) > 0.5).reshape(self.batch_size)
        tensordict.set("success", success)
        return tensordict

    @property
    def info_spec(self):
        return {"success": Unbounded(self.batch_size, dtype=torch.bool)}


class MaskedVectorEnv(SyncVectorEnv):
    """A ``SyncVectorEnv`` (autoreset disabled) whose ``step`` steps only the sub-environments in ``active``.

    Set ``active`` (a bool array, one per sub-environment) before each step; inactive ones return
    their last observation, reward 0 and no success. A sub-environment whose step raises, or which
    MetaWorld reports as numerically unstable (``_did_see_sim_exception``: it then freezes its
    observation and never succeeds), is terminated and its reason kept in ``failures[i]``; the others
    go on. ``reset`` clears ``failures`` and sets the sub-environments it resets active.
    """

    def __init__(self, envs: Sequence, task_ids: Sequence[int] | None = None):
        envs = list(envs)
        if not envs:
            raise ValueError("MaskedVectorEnv needs at least one environment")
        super().__init__([_Const(e) for e in envs], copy=False, autoreset_mode=AutoresetMode.DISABLED)
        # The batch is handed out in float32 (what policies read): one numpy cast per step here is
        # cheaper than a DoubleToFloat transform on the TorchRL side (same rounding, to nearest).
        self._bare_observation_space = self.single_observation_space
        low, high = (
            bound.astype(np.float32)
            for bound in (self.single_observation_space.low, self.single_observation_space.high)
        )
        self.single_observation_space = Box(low, high, dtype=np.float32)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.active = np.ones(self.num_envs, dtype=bool)
        self.failures = [""] * self.num_envs
        #: The task id of each slot, read (cloned) by the ``task_id`` primer at every reset.
        self.task_ids = torch.tensor(list(task_ids) if task_ids is not None else [0] * len(envs), dtype=torch.int64)

    def replace(self, i: int, env, task_id: int) -> None:
        """Put ``env`` (a bare MetaWorld env, already ``set_task``) in slot ``i``; reset that slot next."""
        if env.observation_space != self._bare_observation_space or env.action_space != self.single_action_space:
            raise ValueError(f"slot {i}: the new env's spaces differ from the batch's")
        self.envs[i] = env
        self.task_ids[i] = task_id

    def reset(self, *, seed=None, options=None):
        """Reset every sub-environment, or those in ``options["reset_mask"]`` (torchrl's partial ``_reset``).

        A sub-environment whose reset raises keeps its previous observation (zeros if it has none),
        gets the reason in ``failures[i]`` and is not stepped: its rollout ends as failed at the next
        step. (Autoreset is disabled, so SyncVectorEnv's reset bookkeeping is not needed; MetaWorld
        ignores reset seeds.)
        """
        mask = (options or {}).get("reset_mask")
        for i in np.flatnonzero(np.ones(self.num_envs, dtype=bool) if mask is None else mask):
            self.active[i] = True
            self.failures[i] = ""
            try:
                self._env_obs[i], _ = self.envs[i].reset()
            except Exception as err:  # recorded per rollout; the other sub-environments go on
                self.failures[i] = f"reset failed: {type(err).__name__}: {err}"
                if self._env_obs[i] is None:
                    space = self.single_observation_space
                    self._env_obs[i] = np.zeros(space.shape, dtype=space.dtype)
        return np.stack(self._env_obs, dtype=np.float32), {}

    def step(self, actions):
        n = self.num_envs
        rewards = np.zeros(n, dtype=np.float64)
        terminated = np.zeros(n, dtype=bool)
        truncated = np.zeros(n, dtype=bool)
        success = np.zeros(n, dtype=np.float32)
        for i in np.flatnonzero(self.active):
            env = self.envs[i]
            if self.failures[i]:  # its reset failed
                terminated[i] = True
                continue
            try:
                obs, reward, term, trunc, info = env.step(actions[i])
            except Exception as err:  # recorded per rollout; the other sub-environments go on
                self.failures[i] = f"{type(err).__name__}: {err}"
                terminated[i] = True
                continue
            if getattr(env.unwrapped, "_did_see_sim_exception", False):
                self.failures[i] = "MuJoCo simulation became unstable"
                terminated[i] = True
                continue
            self._env_obs[i] = obs
            rewards[i] = reward
            terminated[i] = term
            truncated[i] = trunc
            success[i] = info.get("success", 0.0)
        return np.stack(self._env_obs, dtype=np.float32), rewards, terminated, truncated, {"success": success}


class _Const:
    """``SyncVectorEnv`` takes environment factories; this one returns an environment built beforehand."""

    def __init__(self, env):
        self.env = env

    def __call__(self):
        return self.env


def _reward_spec(batch_size) -> Unbounded:
    # MetaWorld's rewards are Python floats; GymWrapper would round them to float32. Kept in float64
    # so that a rollout's return is the exact sum a plain gymnasium loop gives.
    return Unbounded((*batch_size, 1), dtype=torch.float64)


def _transforms(task_ids: torch.Tensor, to_float: bool) -> Compose:
    # InitTracker writes `is_init` ([..., 1] bool): True on the first step of a rollout (also in a
    # slot that a partial reset refills), so stateful policies (history, action chunks) know
    # when to forget.
    return Compose(
        *([DoubleToFloat(in_keys=["observation"])] if to_float else []),
        InitTracker(init_key="is_init"),
        TensorDictPrimer(
            expand_specs=True,
            task_id=Unbounded((), dtype=torch.int64),
            default_value={"task_id": functools.partial(torch.clone, task_ids)},
        ),
    )


def make_metaworld_env(task: str, variation=None) -> TransformedEnv:
    """A TorchRL env for one MetaWorld task: ``observation`` (float32 [39]), ``action`` [4], ``success``, ``task_id``.

    ``variation`` (a ``metaworld.Task``, e.g. ``tasks.variation(task, seed, k)``) is set on the env if
    given; otherwise call ``env.base_env._env.set_task(...)`` before ``reset``.
    """
    index = tasks.task_index(task)  # raises on an unknown name
    bare = tasks.make_env(tasks.TASKS[index])
    if variation is not None:
        bare.set_task(variation)
    env = GymWrapper(bare)
    env.set_info_dict_reader(SuccessReader())
    env.reward_spec = _reward_spec(())
    return TransformedEnv(env, _transforms(torch.tensor(index, dtype=torch.int64), to_float=True))


def make_batched_env(envs: Sequence, task_names: Sequence[str]) -> tuple[TransformedEnv, MaskedVectorEnv]:
    """A batch-[N] TorchRL env over bare MetaWorld envs (each already ``set_task``), one per entry of ``task_names``.

    Returns the TorchRL env and its ``MaskedVectorEnv`` (set ``.active`` before a step; read ``.failures``;
    ``.replace(i, env, task_id)`` then ``reset`` with a ``_reset`` mask starts a new rollout in slot ``i``).
    """
    if len(envs) != len(task_names):
        raise ValueError(f"got {len(envs)} environments but {len(task_names)} task names")
    vec = MaskedVectorEnv(envs, [tasks.task_index(t) for t in task_names])
    env = GymWrapper(vec)
    env.set_info_dict_reader(SuccessReader((len(envs),)))
    env.reward_spec = _reward_spec((len(envs),))
    return TransformedEnv(env, _transforms(vec.task_ids, to_float=False)), vec
