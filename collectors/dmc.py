"""dm_control tasks: TorchRL environments, scripted experts, demonstrations and the evaluator collector.

Tasks (``DMC_TASKS``; the order fixes the ``task_id`` of each, ``0 .. 1``):

* ``point_mass-easy``: push a point mass to the target at the centre of the arena.
* ``reacher-easy``: bring a two-link arm's fingertip into a randomly placed target.

Both are TorchRL ``DMControlEnv`` s (dm-control 1.0.28 on MuJoCo 3.3.0, MetaWorld's pin) with a
:class:`TaskObservation` transform that gives every task the same 6-d float32 ``observation``
``[position (2), to_target (2), velocity (2)]`` (point_mass's target is the origin: its
``to_target`` is ``-position``), the bool ``success`` and the int64 ``task_id``; ``InitTracker``
writes ``is_init`` for stateful policies. Actions are 2-d in [-1, 1].

Success (documented per task, read from the observation): the task's own "inside the target"
condition, the one where its reward's target term is 1: point_mass ``||to_target|| < 0.015``
(the target's radius), reacher-easy ``||to_target|| < 0.06`` (target radius 0.05 + fingertip 0.01).
A rollout stops at its first success (``terminated``), as MetaWorld rollouts do; ``steps`` counts
the executed steps and ``rho = steps / H``. The suites' own time limit is 1000 steps (20 s at
50 Hz): ``H`` is at most that.

Variations: rollout ``k`` of a task runs with the task's random seed ``seed + k`` (initial state,
and reacher's target position). Demonstrations use ``data_seed + attempt``; evaluation
``eval_seed + k``; the two ranges must not overlap (:func:`check_disjoint`).

Experts (:class:`DMCExpert`, from the observation alone): point_mass a PD controller toward the
origin, reacher a Jacobian-transpose PD controller of the fingertip toward the target
(link lengths 0.12 and 0.12, from reacher.xml). Both succeed well within the suites' horizon
(``tests/collectors/test_dmc.py`` runs them through the evaluator).

Evaluation batches the rollouts of a call in TorchRL ``SerialEnv`` s (``batch`` at once) and
rolls them out with ``EnvBase.rollout(break_when_all_done=True)``: finished sub-environments are
no longer stepped. A batch whose simulation raises is run again one rollout at a time; the
rollout that raises is recorded as failed with the reason.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence

import numpy as np
import pandas as pd
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.data import Composite, Unbounded
from torchrl.envs.transforms import Transform

from tar_rl.collectors.suite import COLUMNS, EvalSpec, Suite
from tar_rl.objectives.registry import did_you_mean

__all__ = [
    "ACTION_DIM",
    "DMC_TASKS",
    "GROUP",
    "INSTRUCTIONS",
    "MAX_HORIZON",
    "NAME_PREFIX",
    "OBS_DIM",
    "DMCExpert",
    "TaskObservation",
    "build_dataset",
    "check_disjoint",
    "evaluate",
    "expert_episodes",
    "make_env",
    "max_attempts",
    "resolve_tasks",
]

DMC_TASKS = ("point_mass-easy", "reacher-easy")
GROUP = "dm_control"
INSTRUCTIONS = {
    "point_mass-easy": "push the point mass into the target at the centre",
    "reacher-easy": "reach the target with the fingertip",
}
_THRESHOLD = {"point_mass-easy": 0.015, "reacher-easy": 0.06}
OBS_DIM, ACTION_DIM = 6, 2
NAME_PREFIX = "dm_control-"
MAX_HORIZON = 1000  # the suites' 20 s time limit at 50 Hz
_LINKS = (0.12, 0.12)  # reacher.xml: the hand body at 0.12 from the shoulder, the finger at 0.12 from the wrist


def resolve_tasks(spec: Sequence[str]) -> list[str]:
    """Task names (``point_mass-easy``, ``reacher-easy``) or the group ``dm_control``, in ``DMC_TASKS`` order.

    Raises:
        ValueError: an unknown name (the message lists the valid ones).
    """
    names: set[str] = set()
    for name in spec:
        if name == GROUP:
            names.update(DMC_TASKS)
        elif name in DMC_TASKS:
            names.add(name)
        else:
            valid = [*DMC_TASKS, GROUP]
            raise ValueError(f"unknown dm_control task {name!r}{did_you_mean(name, valid)}; valid: {valid}")
    if not names:
        raise ValueError(f"no dm_control task named; valid: {[*DMC_TASKS, GROUP]}")
    return [t for t in DMC_TASKS if t in names]


def check_disjoint(data_seed: int, attempts: int, eval_seed: int, rollouts: int) -> None:
    """Raise ``ValueError`` if demonstration seeds ``data_seed + [0, attempts)`` meet ``eval_seed + [0, rollouts)``."""
    if data_seed < eval_seed + rollouts and eval_seed < data_seed + attempts:
        raise ValueError(
            f"demonstration seeds {data_seed}..{data_seed + attempts - 1} overlap evaluation seeds "
            f"{eval_seed}..{eval_seed + rollouts - 1}"
        )


class TaskObservation(Transform):
    """``observation`` [6] float32 and ``success`` [1] bool of a dm_control task; success terminates the step.

    ``observation`` is ``[position, to_target, velocity]`` (point_mass: ``to_target = -position``);
    ``success`` is ``||to_target||`` below the task's threshold (module docstring).
    """

    def __init__(self, task: str):
        super().__init__(in_keys=[], out_keys=["observation", "success"])
        self.task = task
        self.threshold = _THRESHOLD[task]

    def _observe(self, td: TensorDictBase) -> TensorDictBase:
        position = td.get("position").to(torch.float32)
        velocity = td.get("velocity").to(torch.float32)
        to_target = td.get("to_target").to(torch.float32) if "to_target" in td.keys() else -position
        td.set("observation", torch.cat([position, to_target, velocity], dim=-1))
        td.set("success", (torch.linalg.vector_norm(to_target, dim=-1) < self.threshold).unsqueeze(-1))
        return td

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        return self._observe(tensordict_reset)

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        next_tensordict = self._observe(next_tensordict)
        success = next_tensordict.get("success")
        next_tensordict.set("terminated", next_tensordict.get("terminated") | success)
        next_tensordict.set("done", next_tensordict.get("done") | success)
        return next_tensordict

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        shape = observation_spec.shape
        observation_spec["observation"] = Unbounded((*shape, OBS_DIM), dtype=torch.float32)
        observation_spec["success"] = Unbounded((*shape, 1), dtype=torch.bool)
        return observation_spec


def make_env(task: str, seed: int):
    """The TorchRL env of ``task`` with random seed ``seed``: ``observation``, ``success``, ``task_id``, ``is_init``."""
    from torchrl.envs import Compose, DMControlEnv, InitTracker, TensorDictPrimer, TransformedEnv

    if task not in DMC_TASKS:
        raise ValueError(f"unknown dm_control task {task!r}; valid: {list(DMC_TASKS)}")
    domain, level = task.split("-")
    with warnings.catch_warnings():  # dm_control's viewer probes for a display it does not need here
        warnings.filterwarnings("ignore", category=UserWarning, module="glfw")
        base = DMControlEnv(domain, level, random=int(seed))
    index = DMC_TASKS.index(task)
    return TransformedEnv(
        base,
        Compose(
            TaskObservation(task),
            InitTracker(init_key="is_init"),
            TensorDictPrimer(task_id=Unbounded((), dtype=torch.int64), default_value=index, expand_specs=True),
        ),
    )


class DMCExpert(TensorDictModuleBase):
    """The scripted experts as a TensorDict policy: ``observation``, ``task_id`` -> ``action`` (module docstring)."""

    in_keys = ["observation", "task_id"]
    out_keys = ["action"]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs = tensordict.get("observation").double()
        ids = tensordict.get("task_id").reshape(obs.shape[:-1])
        position, to_target, velocity = obs[..., 0:2], obs[..., 2:4], obs[..., 4:6]
        # point_mass: PD toward the origin (one actuator per axis)
        point = to_target / 0.05 - 0.2 * velocity / 0.05
        # reacher: fingertip force toward the target through the arm's Jacobian transpose, damped
        q1, q12 = position[..., 0], position[..., 0] + position[..., 1]
        l1, l2 = _LINKS
        jx = torch.stack([-l1 * torch.sin(q1) - l2 * torch.sin(q12), -l2 * torch.sin(q12)], -1)
        jy = torch.stack([l1 * torch.cos(q1) + l2 * torch.cos(q12), l2 * torch.cos(q12)], -1)
        force = to_target / 0.01
        reach = jx * force[..., :1] + jy * force[..., 1:] - 0.1 * velocity
        reacher = (ids == DMC_TASKS.index("reacher-easy")).unsqueeze(-1)
        action = torch.where(reacher, reach, point).clamp(-1.0, 1.0).to(torch.float32)
        tensordict.set("action", action)
        return tensordict


class _CheckedPolicy(TensorDictModuleBase):
    """Calls ``policy`` and refuses a wrong action shape or non-finite actions, naming the tasks and the step."""

    def __init__(self, policy, tasks: Sequence[str]):
        super().__init__()
        self.policy, self.tasks, self.step = policy, list(tasks), 0
        self.in_keys, self.out_keys = list(policy.in_keys), ["action"]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        self.step += 1
        tensordict = self.policy(tensordict)
        action = tensordict.get("action", None)
        n = tensordict.shape[0]
        if not isinstance(action, torch.Tensor) or tuple(action.shape) != (n, ACTION_DIM):
            shape = tuple(action.shape) if isinstance(action, torch.Tensor) else type(action).__name__
            raise ValueError(
                f"the policy returned actions of shape {shape} at step {self.step} of {self.tasks}; "
                f"expected ({n}, {ACTION_DIM})"
            )
        finite = torch.isfinite(action).all(-1)
        if not bool(finite.all()):
            bad = int((~finite).nonzero()[0, 0])
            raise ValueError(f"the policy returned non-finite actions for {self.tasks[bad]} at step {self.step}")
        return tensordict


def _rollouts(policy, jobs: Sequence[tuple[str, int]], horizon: int) -> list[dict]:
    """Roll ``policy`` out on the (task, seed) ``jobs`` in one ``SerialEnv``; one trajectory dict per job."""
    from torchrl.envs import SerialEnv

    env = SerialEnv(len(jobs), [lambda t=t, s=s: make_env(t, s) for t, s in jobs])
    try:
        with torch.no_grad():
            td = env.rollout(
                horizon,
                _CheckedPolicy(policy, [t for t, _ in jobs]),
                break_when_any_done=False,
                break_when_all_done=True,
            )
    finally:
        env.close()
    out = []
    for i, (task, seed) in enumerate(jobs):
        done = td["next", "done"][i, :, 0]
        last = int(done.nonzero()[0, 0]) if bool(done.any()) else td.shape[1] - 1
        traj = td[i, : last + 1]
        out.append(
            {
                "task": task,
                "seed": seed,
                "success": bool(traj["next", "success"][-1, 0]),
                "steps": last + 1,
                "return": float(traj["next", "reward"].double().sum()),
                "trajectory": traj,
            }
        )
    return out


def _run(policy, jobs, horizon, batch) -> list[dict]:
    """``_rollouts`` over batches; a batch that raises is run again one job at a time (failures recorded)."""
    results = []
    for a in range(0, len(jobs), batch):
        part = jobs[a : a + batch]
        try:
            results += _rollouts(policy, part, horizon)
        except ValueError:  # the policy's own error (shape, non-finite): a bug to report, not a failed rollout
            raise
        except Exception as first:
            if len(part) == 1:
                results.append({"task": part[0][0], "seed": part[0][1], "failure": f"{type(first).__name__}: {first}"})
                continue
            results += _run(policy, part, horizon, 1)
    return results


def evaluate(
    policy: TensorDictModuleBase,
    tasks: Sequence[str],
    rollouts_per_task: int = 50,
    seed: int = 1000,
    horizon: int = 500,
    batch: int = 16,
    shard: tuple[int, int] = (0, 1),
) -> pd.DataFrame:
    """Roll ``policy`` out ``rollouts_per_task`` times per task; one row per rollout (``COLUMNS``).

    Rollout ``k`` of a task uses the task's random seed ``seed + k``, stops at its first success
    or at ``horizon`` (at most :data:`MAX_HORIZON`). ``group`` is ``dm_control``; a rollout whose
    simulation raised has ``success=False``, ``steps=horizon`` and the reason in ``failure``.
    ``shard=(index, count)`` runs only the rollouts ``index, index + count, ...`` of the (task,
    rollout) list (one process's share), as MetaWorld's evaluator does.
    """
    names = resolve_tasks(tasks)
    if not (isinstance(horizon, int) and 1 <= horizon <= MAX_HORIZON):
        raise ValueError(f"horizon must be an integer in 1..{MAX_HORIZON}, got {horizon!r}")
    if not (isinstance(rollouts_per_task, int) and rollouts_per_task >= 1):
        raise ValueError(f"rollouts_per_task must be a positive integer, got {rollouts_per_task!r}")
    was_training = policy.training
    policy.eval()
    try:
        index, count = shard
        jobs = [(t, seed + k) for t in names for k in range(rollouts_per_task)][index::count]
        results = _run(policy, jobs, horizon, batch) if jobs else []
    finally:
        policy.train(was_training)
    rows = []
    for r in results:
        failure = r.get("failure", "")
        success = not failure and r["success"]
        steps = r["steps"] if success else horizon
        rows.append(
            {
                "task": r["task"],
                "task_id": DMC_TASKS.index(r["task"]),
                "group": GROUP,
                "variation_seed": r["seed"],
                "variation_index": r["seed"] - seed,
                "success": success,
                "steps": steps,
                "rho": steps / horizon,
                "return": r.get("return", 0.0),
                "failure": failure,
            }
        )
    return pd.DataFrame(rows, columns=list(COLUMNS))


def expert_episodes(tasks: Sequence[str], n_demos: int, seed: int, max_attempts: int, batch: int = 16) -> tuple:
    """The experts' first ``n_demos`` successful episodes per task (attempt ``i`` with seed ``seed + i``).

    Returns the episodes (``importers.common``'s format) and, per task, the seeds tried and kept.

    Raises:
        ValueError: a task whose expert did not succeed ``n_demos`` times in ``max_attempts`` attempts.
    """
    expert = DMCExpert()
    episodes, per_task = [], {}
    for task in resolve_tasks(tasks):
        kept, tried = [], 0
        while len(kept) < n_demos and tried < max_attempts:
            count = min(batch, max_attempts - tried, 2 * (n_demos - len(kept)))
            jobs = [(task, seed + tried + i) for i in range(count)]
            tried += count
            kept += [r for r in _run(expert, jobs, MAX_HORIZON, batch) if r.get("success")][: n_demos - len(kept)]
        if len(kept) < n_demos:
            raise ValueError(
                f"dm_control task {task!r}: the expert succeeded {len(kept)} times in {tried} attempts, "
                f"{n_demos} demonstrations were asked for"
            )
        per_task[task] = {"seeds_tried": [seed, seed + tried - 1], "kept_seeds": [r["seed"] for r in kept]}
        for r in kept:
            traj = r["trajectory"]
            obs = traj["observation"].numpy()
            action = traj["action"].numpy()
            terminated = traj["next", "terminated"][:, 0].numpy().astype(bool)
            episodes.append(
                {
                    "name": f"{task}/seed_{r['seed']}",
                    "task": task,
                    "observation": obs,
                    "next_observation": traj["next", "observation"].numpy(),
                    "action": action,
                    "action_raw": action,
                    "reward": traj["next", "reward"][:, 0].numpy().astype(np.float32),
                    "terminated": terminated,
                    "clipped": 0,
                }
            )
    return episodes, per_task


def max_attempts(n_demos: int) -> int:
    """Attempts allowed per task for ``n_demos`` demonstrations (the experts rarely fail)."""
    return 2 * n_demos + 8


def build_dataset(
    root,
    tasks: Sequence[str],
    n_demos: int,
    seed: int = 0,
    chunk_horizon: int = 8,
    history: int = 2,
    verbose: bool = True,
):
    """The experts' demonstrations of ``tasks`` as a tar-rl dataset folder under ``root`` (collected once).

    The folder is ``root/dm_control-<tasks>-<key>``, ``key`` a hash of the settings: the same
    settings load it again. Task ids are the ``DMC_TASKS`` indices (``task_names`` in the metadata
    lists both); ``variation_seeds`` lists every seed the experts tried, for :func:`check_disjoint`.
    Written through ``tar_rl.importers.common.import_folder`` (the same format, atomically).
    """
    from tar_rl import data as _data
    from tar_rl.importers.common import import_folder

    names = resolve_tasks(tasks)
    n_demos = _data.positive_int("n_demos", n_demos)
    attempts = max_attempts(n_demos)
    settings = {
        "source": "dm_control",
        "tasks": names,
        "n_demos": n_demos,
        "seed": int(seed),
        "max_attempts": attempts,
        "chunk_horizon": _data.positive_int("chunk_horizon", chunk_horizon),
        "history": _data.positive_int("history", history),
        "dm_control": _data.package_version("dm-control"),
        "format_version": _data.FORMAT_VERSION,
    }

    def read() -> tuple[list[dict], dict]:
        episodes, per_task = expert_episodes(names, n_demos, int(seed), attempts)
        tried = sorted({s for p in per_task.values() for s in range(p["seeds_tried"][0], p["seeds_tried"][1] + 1)})
        return episodes, {
            "task_names": list(DMC_TASKS),
            "instructions": {t: INSTRUCTIONS[t] for t in names},
            "per_task": per_task,
            "variation_seeds": tried,
            "seed": int(seed),
            "n_demos": n_demos,
            "success": {t: f"||to_target|| < {_THRESHOLD[t]}" for t in names},
            "action_target": "the expert's action, in [-1, 1]",
            "versions": {"dm_control": _data.package_version("dm-control"), "mujoco": _data.package_version("mujoco")},
        }

    stem = "+".join(t.split("-")[0] for t in names)
    return import_folder(root, NAME_PREFIX, stem, settings, read, verbose)


class DMControlSuite(Suite):
    """dm_control's point_mass-easy and reacher-easy with scripted experts (module docstring)."""

    name = "dm_control"
    max_horizon = MAX_HORIZON
    longest_demo = MAX_HORIZON  # the experts' episodes run at most this long (expert_episodes)
    action_dim = ACTION_DIM
    sources = ("dm_control",)
    task_names = DMC_TASKS
    instructions = INSTRUCTIONS

    def resolve(self, spec: Sequence[str]) -> list[str]:
        return resolve_tasks(spec)

    def demo_seeds(self, seed: int, n_demos: int) -> set[int]:
        return set(range(seed, seed + max_attempts(n_demos)))

    def eval_seeds(self, seed: int, rollouts: int) -> set[int]:
        return set(range(seed, seed + rollouts))

    def check_seeds(self, seed: int, n_demos: int, spec: EvalSpec) -> None:
        check_disjoint(seed, max_attempts(n_demos), spec.seed, spec.rollouts)

    def check_dataset(self, dataset, spec: EvalSpec) -> None:
        clash = sorted(set(dataset.metadata["variation_seeds"]) & self.eval_seeds(spec.seed, spec.rollouts))
        if clash:
            raise ValueError(f"the dataset's demonstrations used evaluation seeds {clash[:5]}")

    def build_dataset(self, data, tasks: Sequence[str], n_demos: int, seed: int, progress: bool):
        return build_dataset(data.root, tasks, n_demos, seed, data.chunk_horizon, data.history, verbose=progress)

    def evaluate(self, spec: EvalSpec, actor, tasks: Sequence[str], progress: bool, shard: tuple[int, int], pool):
        # (``pool`` unused: the rollouts run in this process)
        return evaluate(actor, tasks, spec.rollouts, seed=spec.seed, horizon=spec.horizon, shard=shard)
