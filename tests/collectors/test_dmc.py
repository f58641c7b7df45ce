"""dm_control tasks: observation and success, experts through the evaluator, demonstrations, the recipe end to end."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModuleBase

from tar_rl.collectors import dmc


def test_resolve_tasks():
    assert dmc.resolve_tasks(["dm_control"]) == ["point_mass-easy", "reacher-easy"]
    assert dmc.resolve_tasks(["reacher-easy", "point_mass-easy"]) == ["point_mass-easy", "reacher-easy"]
    with pytest.raises(ValueError, match=r"unknown dm_control task 'reach'; valid: \['point_mass-easy'"):
        dmc.resolve_tasks(["reach"])


@pytest.mark.parametrize(
    ("task", "raw", "observation", "success"),
    [
        # point_mass: to_target = -position; inside the target (radius 0.015) or not
        ("point_mass-easy", {"position": [0.01, 0.0], "velocity": [0.5, -0.5]}, [0.01, 0, -0.01, 0, 0.5, -0.5], True),
        (
            "point_mass-easy",
            {"position": [0.012, 0.012], "velocity": [0.0, 0.0]},
            [0.012, 0.012, -0.012, -0.012, 0, 0],
            False,
        ),
        # reacher-easy: ||to_target|| < 0.05 + 0.01; (0.05, 0.03) -> 0.0583, (0.05, 0.04) -> 0.0640
        (
            "reacher-easy",
            {"position": [1, 2], "to_target": [0.05, 0.03], "velocity": [3, 4]},
            [1, 2, 0.05, 0.03, 3, 4],
            True,
        ),
        (
            "reacher-easy",
            {"position": [1, 2], "to_target": [0.05, 0.04], "velocity": [3, 4]},
            [1, 2, 0.05, 0.04, 3, 4],
            False,
        ),
    ],
)
def test_task_observation_and_success_by_hand(task, raw, observation, success):
    t = dmc.TaskObservation(task)
    td = TensorDict({k: torch.tensor([v], dtype=torch.float64) for k, v in raw.items()}, [1])
    nxt = td.clone()
    nxt.update({"terminated": torch.zeros(1, 1, dtype=torch.bool), "done": torch.zeros(1, 1, dtype=torch.bool)})
    out = t._step(td, nxt)
    np.testing.assert_allclose(out["observation"][0].numpy(), observation, rtol=1e-6)
    assert out["observation"].dtype == torch.float32
    assert bool(out["success"][0, 0]) is success
    assert bool(out["terminated"][0, 0]) is success and bool(out["done"][0, 0]) is success


def test_success_agrees_with_the_suites_physics():
    # Independent reference: dm_control's own distances (mass_to_target_dist, finger_to_target_dist)
    # against the target's (and fingertip's) radius, along an expert episode of each task.
    expert = dmc.DMCExpert()
    for task in dmc.DMC_TASKS:
        env = dmc.make_env(task, 7)
        physics = env.base_env._env.physics
        td = env.reset()
        seen = set()
        for _ in range(200):
            td = env.step(expert(td)).get("next")
            if task == "point_mass-easy":
                inside = physics.mass_to_target_dist() < physics.named.model.geom_size["target", 0]
            else:
                inside = physics.finger_to_target_dist() < physics.named.model.geom_size[["target", "finger"], 0].sum()
            assert bool(td["success"]) == inside
            seen.add(bool(inside))
            if inside:
                break
        assert True in seen, f"{task}: the expert never reached the target"
        env.close()


def test_expert_through_the_evaluator():
    df = dmc.evaluate(dmc.DMCExpert(), ["dm_control"], rollouts_per_task=3, seed=1000, horizon=300, batch=4)
    assert list(df["task"]) == ["point_mass-easy"] * 3 + ["reacher-easy"] * 3
    assert df["success"].all() and (df["failure"] == "").all()
    assert list(df["variation_seed"]) == [1000, 1001, 1002] * 2 and list(df["variation_index"]) == [0, 1, 2] * 2
    assert (df["group"] == "dm_control").all() and list(df["task_id"]) == [0] * 3 + [1] * 3
    assert (df["steps"] >= 1).all() and (df["steps"] < 300).all()
    np.testing.assert_allclose(df["rho"], df["steps"] / 300)
    # rows depend only on (task, seed): another batch size gives the same rollouts
    again = dmc.evaluate(dmc.DMCExpert(), ["dm_control"], rollouts_per_task=3, seed=1000, horizon=300, batch=2)
    assert again[["steps", "success"]].equals(df[["steps", "success"]])
    # a share of the rollouts, as one rank of a distributed job runs it
    part = dmc.evaluate(dmc.DMCExpert(), ["reacher-easy"], rollouts_per_task=3, seed=1000, horizon=300, shard=(1, 2))
    assert list(part["variation_seed"]) == [1001]


class _Constant(TensorDictModuleBase):
    in_keys, out_keys = ["observation"], ["action"]

    def __init__(self, value, width=dmc.ACTION_DIM):
        super().__init__()
        self.value, self.width = value, width

    def forward(self, td):
        td.set("action", torch.full((td.shape[0], self.width), self.value))
        return td


def test_a_bad_policy_is_named():
    with pytest.raises(ValueError, match=r"shape \(2, 3\) at step 1 of \['reacher-easy', 'reacher-easy'\]"):
        dmc.evaluate(_Constant(0.0, width=3), ["reacher-easy"], rollouts_per_task=2, horizon=5)
    with pytest.raises(ValueError, match="non-finite actions for point_mass-easy at step 1"):
        dmc.evaluate(_Constant(math.nan), ["point_mass-easy"], rollouts_per_task=1, horizon=5)


def test_a_failing_simulation_is_recorded_and_the_others_go_on(monkeypatch):
    real = dmc.make_env

    def unstable(task, seed):
        env = real(task, seed)
        if seed == 1001:
            inner = env.base_env._env
            step = inner.step
            calls = {"n": 0}

            def failing(action):
                calls["n"] += 1
                if calls["n"] > 3:
                    raise RuntimeError("physics became unstable")
                return step(action)

            inner.step = failing
        return env

    monkeypatch.setattr(dmc, "make_env", unstable)
    df = dmc.evaluate(_Constant(0.0), ["reacher-easy"], rollouts_per_task=3, seed=1000, horizon=20, batch=3)
    assert list(df["variation_seed"]) == [1000, 1001, 1002]
    bad = df.iloc[1]
    assert not bad["success"] and bad["steps"] == 20 and "physics became unstable" in bad["failure"]
    assert (df.iloc[[0, 2]]["failure"] == "").all()


def test_demonstrations_dataset(tmp_path, monkeypatch):
    ds = dmc.build_dataset(tmp_path, ["dm_control"], 2, seed=0, chunk_horizon=4, history=2, verbose=False)
    m = ds.metadata
    assert m["source"] == "dm_control" and m["tasks"] == list(dmc.DMC_TASKS)
    assert m["task_names"] == ["point_mass-easy", "reacher-easy"]
    assert m["task_ids"] == {"point_mass-easy": 0, "reacher-easy": 1} and m["total_episodes"] == 4
    data = ds.data
    assert data["observation"].shape[1] == 6 and data["action"].shape[1] == 2
    assert float(data["action"].abs().max()) <= 1.0
    ends = np.flatnonzero(data["next", "done"][:, 0].numpy())
    assert len(ends) == 4 and data["next", "terminated"][ends].all()  # every demonstration ends in success
    assert set(m["variation_seeds"]) >= {0, 1} and max(m["variation_seeds"]) < dmc.max_attempts(2)
    # the same settings load the folder again, without collecting
    monkeypatch.setattr(dmc, "expert_episodes", lambda *a, **k: pytest.fail("collected again"))
    assert (
        dmc.build_dataset(tmp_path, ["dm_control"], 2, seed=0, chunk_horizon=4, history=2, verbose=False).path
        == ds.path
    )


def test_disjoint_seeds():
    dmc.check_disjoint(0, 12, 1000, 50)
    with pytest.raises(ValueError, match="overlap"):
        dmc.check_disjoint(0, 12, 11, 3)


def _dmc_config(tmp_path, *overrides):
    from recipe_helpers import compose_config

    return compose_config(
        "data.suite=dm_control",
        "data.tasks=[dm_control]",
        "data.n_demos=2",
        f"data.root={tmp_path / 'datasets'}",
        "data.batch_segments=8",
        "data.slice_len=8",
        "policy.hidden=[32,32]",
        "optim.steps=20",
        "optim.warmup=2",
        "logging.every=5",
        "logging.checkpoint_every=10",
        "logging.progress=false",
        "eval.rollouts=2",
        "eval.horizon=50",
        f"runs_root={tmp_path / 'runs'}",
        *overrides,
    )


def test_recipe_trains_and_evaluates_on_dm_control(tmp_path):
    from tar_rl.recipes import evaluate_checkpoint, train

    run = train(_dmc_config(tmp_path))
    summary = json.loads((run / "summary.json").read_text())
    groups = {row["name"]: row for row in summary["final"]}
    assert set(groups) == {"dm_control", "overall"} and 0 <= groups["overall"]["success"] <= 1
    rollouts = (run / "eval_rollouts.csv").read_text()
    assert rollouts.count("point_mass-easy") == 2 and rollouts.count("reacher-easy") == 2
    # the saved policy evaluates again through the same suite
    df = evaluate_checkpoint(run / "checkpoint.pt", rollouts=1, progress=False, out=tmp_path / "e.csv")
    assert list(df["task"]) == list(dmc.DMC_TASKS)


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("data.suite=bogus", r"data.suite='bogus' is not valid; choose one of \['metaworld', 'dm_control', 'libero'\]"),
        ("data.tasks=[reach]", "data.tasks: unknown dm_control task 'reach'"),
        ("data.image_size=32", "the dm_control suite has no image observations"),
        ("data.seed=1001", "data.seed=1001 and eval.seed=1000: demonstration seeds 1001..1012 overlap"),
        ("eval.horizon=1001", "eval.horizon must be an integer between 1 and 1000"),
    ],
)
def test_dm_control_settings_refused_before_work(tmp_path, override, message):
    from tar_rl.recipes import ConfigError, train

    with pytest.raises(ConfigError, match=message):
        train(_dmc_config(tmp_path, override))
    assert not (tmp_path / "datasets").exists()
