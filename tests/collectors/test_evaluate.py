"""The evaluation collector on real MetaWorld: expert rollouts match a plain gymnasium loop, errors are clear."""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import signal
import time
from concurrent.futures.process import BrokenProcessPool

import numpy as np
import pandas as pd
import pytest
import torch
from tensordict.nn import TensorDictModuleBase

from tar_rl.collectors.metaworld import evaluate as ev
from tar_rl.collectors.metaworld import tasks
from tar_rl.collectors.metaworld.envs import make_metaworld_env
from tar_rl.collectors.metaworld.evaluate import ExpertPolicy, RolloutPool, evaluate

EASY = ["reach-v3", "button-press-topdown-v3", "drawer-close-v3"]


class ConstPolicy(TensorDictModuleBase):
    """Writes a constant action; records the task ids and first observations it sees."""

    in_keys = ["observation", "task_id"]
    out_keys = ["action"]

    def __init__(self, value=0.0, dim=4, nan_at_step=None):
        super().__init__()
        self.value, self.dim, self.nan_at_step = value, dim, nan_at_step
        self.calls = 0
        self.task_ids: list[list[int]] = []
        self.first_obs: list[np.ndarray] = []

    def forward(self, td):
        self.calls += 1
        n = td.batch_size[0]
        if self.calls == 1:
            self.first_obs.append(td["observation"].numpy().copy())
        self.task_ids.append(td["task_id"].tolist())
        action = torch.full((n, self.dim), self.value)
        if self.nan_at_step is not None and self.calls == self.nan_at_step:
            action[0, 0] = float("nan")
        td.set("action", action)
        return td


def plain_expert_rollout(task, seed, k, horizon):
    """The expert on a bare gymnasium env: float32 observations and actions, clipped, stop at first success."""
    env = tasks.make_env(task)
    env.set_task(tasks.variation(task, seed, k))
    policy = tasks.expert(task)
    obs, _ = env.reset()
    total = 0.0
    for t in range(1, horizon + 1):
        seen = obs.astype(np.float32).astype(np.float64)
        action = np.clip(policy.get_action(seen), -1.0, 1.0).astype(np.float32)
        obs, reward, _, _, info = env.step(action)
        total += float(reward)  # float64 sum (some tasks give numpy float32 rewards)
        if info["success"]:
            return True, t, total
    return False, horizon, total


@pytest.fixture(scope="module")
def expert_rows():
    return evaluate(ExpertPolicy(), EASY, rollouts_per_task=2, seed=1000, horizon=200, workers=1, progress=False)


@pytest.fixture(scope="module")
def rows_without_pool():
    """The expert's rows from two workers of an evaluation given no pool, and the workers it left running."""
    before = {p.pid for p in _evaluation_workers()}  # those of a pool another test keeps open
    df = evaluate(ExpertPolicy(), EASY, rollouts_per_task=2, seed=1000, horizon=200, workers=2, progress=False)
    return df, [p for p in _evaluation_workers() if p.pid not in before]


_SHARED: list[RolloutPool] = []


@pytest.fixture
def open_pool():
    """The module's pool: its workers, once started, serve the next test that takes it; a test may close it."""
    if not _SHARED or _SHARED[-1].closed:
        _SHARED.append(RolloutPool())
    return _SHARED[-1]


@pytest.fixture(scope="module", autouse=True)
def _close_the_shared_pool():
    yield
    for pool in _SHARED:
        pool.close()


def test_expert_succeeds_and_matches_a_plain_loop(expert_rows):
    df = expert_rows
    assert list(df.columns) == list(ev.COLUMNS)
    assert len(df) == 6
    assert list(df["task"]) == sorted(EASY * 2)  # TASKS order is alphabetical
    for row in df.itertuples(index=False, name="Row"):
        success, steps, total = plain_expert_rollout(row.task, 1000, row.variation_index, 200)
        assert row.success is True and success
        assert row.steps == steps
        assert 10 < row.steps < 200
        assert row.rho == steps / 200
        assert row[ev.COLUMNS.index("return")] == total  # exact float64 sum of the same rewards
        assert row.failure == ""
        assert row.task_id == tasks.TASKS.index(row.task)
        assert row.group == "easy"
        assert row.variation_seed == 1000
    assert sorted(df.groupby("task")["variation_index"].apply(list).tolist()) == [[0, 1]] * 3


def test_zero_action_fails_on_reach_with_full_budget():
    df = evaluate(ConstPolicy(0.0), "reach", rollouts_per_task=2, horizon=30, workers=1, progress=False)
    assert (~df["success"]).all()
    assert (df["steps"] == 30).all()
    assert (df["rho"] == 1.0).all()
    assert (df["failure"] == "").all()


def reset_goal(task, k):
    env = tasks.make_env(task)
    env.set_task(tasks.variation(task, 1000, k))
    obs, _ = env.reset()
    return obs[36:39].astype(np.float32)  # the goal is visible in the observation


def test_policy_reads_task_id_per_env_and_variations_differ():
    policy = ConstPolicy(0.0)
    names = ["reach-v3", "drawer-close-v3"]
    evaluate(policy, names, rollouts_per_task=3, horizon=5, workers=1, envs_per_worker=6, progress=False)
    ids = policy.task_ids[0]  # one batch of the 6 rollouts
    assert all(step_ids == ids for step_ids in policy.task_ids)  # constant over the rollout
    assert sorted(ids) == sorted([tasks.TASKS.index(n) for n in names] * 3)
    goals = {n: [reset_goal(n, k) for k in range(3)] for n in names}
    for n in names:
        for a in range(3):
            for b in range(a + 1, 3):
                assert not np.allclose(goals[n][a], goals[n][b])  # distinct variations
    seen = {n: [] for n in names}
    for row, task_id in enumerate(ids):
        task = tasks.TASKS[task_id]
        goal = policy.first_obs[0][row, 36:39]
        matches = [k for k in range(3) if np.array_equal(goal, goals[task][k])]
        assert len(matches) == 1, f"row {row} has task_id {task_id} but not one of {task}'s goals"
        seen[task].extend(matches)
    assert {n: sorted(v) for n, v in seen.items()} == {n: [0, 1, 2] for n in names}


def test_wrong_action_shape_names_task_and_step():
    with pytest.raises(ValueError, match=r"shape \(1, 3\) at step 1 of tasks \['reach-v3'\]"):
        evaluate(ConstPolicy(0.0, dim=3), "reach", rollouts_per_task=1, horizon=5, workers=1, progress=False)


def test_nan_action_names_task_and_step():
    with pytest.raises(ValueError, match=r"non-finite actions for reach-v3 \(rollout 0\) at step 3"):
        evaluate(ConstPolicy(0.0, nan_at_step=3), "reach", rollouts_per_task=2, horizon=10, workers=1, progress=False)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"rollouts_per_task": 0}, "rollouts_per_task must be >= 1, got 0"),
        ({"horizon": 0}, "horizon must be between 1 and 500, got 0"),
        ({"horizon": 501}, "horizon must be between 1 and 500, got 501"),
        ({"tasks_spec": "reach,not-a-task"}, "unknown MetaWorld task or group"),
    ],
)
def test_bad_arguments_fail_before_any_work(monkeypatch, kwargs, message):
    def no_env(task):
        raise AssertionError("an environment was built")

    monkeypatch.setattr(tasks, "make_env", no_env)
    args = {"tasks_spec": "reach", **kwargs}
    with pytest.raises(ValueError, match=message):
        evaluate(ConstPolicy(), progress=False, workers=1, **args)


def test_not_a_tensordict_module():
    with pytest.raises(TypeError, match="policy must be a TensorDictModule"):
        evaluate(lambda td: td, "reach", workers=1, progress=False)


def test_env_error_and_instability_are_recorded_and_the_rest_continue(monkeypatch):
    real = tasks.make_env
    built = []

    def patched(task):
        env = real(task)
        built.append(env)
        which = len(built)
        inner = env.step
        count = [0]

        def step(action):
            count[0] += 1
            if which == 1 and count[0] == 4:
                raise RuntimeError("boom in env 1")
            out = inner(action)
            if which == 2 and count[0] == 6:
                env._did_see_sim_exception = True  # what MetaWorld sets on a MuJoCo instability
            return out

        env.step = step
        return env

    monkeypatch.setattr(tasks, "make_env", patched)
    df = evaluate(ExpertPolicy(), "reach", rollouts_per_task=3, horizon=150, workers=1, progress=False)
    assert list(df["failure"][:2]) == ["RuntimeError: boom in env 1", "MuJoCo simulation became unstable"]
    assert list(df["success"]) == [False, False, True]
    assert list(df["steps"][:2]) == [150, 150]
    _, steps, total = plain_expert_rollout("reach-v3", 1000, 2, 150)
    assert (df["steps"][2], df["return"][2], df["failure"][2]) == (steps, total, "")


def test_reset_error_is_recorded_and_the_rest_continue(monkeypatch):
    real = tasks.make_env
    built = []

    def patched(task):
        env = real(task)
        built.append(env)
        if len(built) == 1:  # the first env built fails its first reset only
            inner, calls = env.reset, [0]

            def reset(**kwargs):
                calls[0] += 1
                if calls[0] == 1:
                    raise RuntimeError("boom on reset")
                return inner(**kwargs)

            env.reset = reset
        return env

    monkeypatch.setattr(tasks, "make_env", patched)
    df = evaluate(ExpertPolicy(), "reach", rollouts_per_task=3, horizon=150, workers=1, progress=False)
    assert list(df["failure"]) == ["reset failed: RuntimeError: boom on reset", "", ""]
    assert list(df["success"]) == [False, True, True]
    assert df["steps"][0] == 150
    for k in (1, 2):
        _, steps, total = plain_expert_rollout("reach-v3", 1000, k, 150)
        assert (df["steps"][k], df["return"][k]) == (steps, total)


@pytest.mark.parametrize("envs_per_worker", [1, 2, 6])
def test_slot_count_does_not_change_the_rows(expert_rows, envs_per_worker):
    # With fewer slots than rollouts, finished slots get the next rollout (often of another task).
    df = evaluate(
        ExpertPolicy(),
        EASY,
        rollouts_per_task=2,
        seed=1000,
        horizon=200,
        workers=1,
        envs_per_worker=envs_per_worker,
        progress=False,
    )
    pd.testing.assert_frame_equal(df, expert_rows)


@pytest.mark.slow
def test_two_workers_give_the_same_rows(expert_rows, rows_without_pool):
    df, _ = rows_without_pool
    pd.testing.assert_frame_equal(df, expert_rows)


def test_make_metaworld_env_entries():
    env = make_metaworld_env("reach", tasks.variation("reach-v3", 1000, 0))
    td = env.reset()
    assert td["observation"].dtype == torch.float32 and td["observation"].shape == (39,)
    assert td["task_id"].item() == tasks.TASKS.index("reach-v3") and td["task_id"].dtype == torch.int64
    td["action"] = torch.zeros(4)
    nxt = env.step(td)["next"]
    assert nxt["success"].dtype == torch.bool and nxt["success"].shape == ()
    assert nxt["task_id"].item() == tasks.TASKS.index("reach-v3")
    assert nxt["reward"].dtype == torch.float64
    with pytest.raises(ValueError, match="nope"):
        make_metaworld_env("nope")


def test_batched_env_gives_the_bare_observations_in_float32():
    from tar_rl.collectors.metaworld.envs import make_batched_env

    names = ["reach-v3", "drawer-close-v3"]
    bare, ref = [], []
    for name in names:  # a twin of each env, stepped by hand with numpy (the reference)
        for group in (bare, ref):
            env = tasks.make_env(name)
            env.set_task(tasks.variation(name, 1000, 0))
            group.append(env)
    env, _ = make_batched_env(bare, names)
    assert env.observation_spec["observation"].dtype == torch.float32
    td = env.reset()
    expected = np.stack([e.reset()[0] for e in ref]).astype(np.float32)  # float64 -> float32, to nearest
    assert td["observation"].dtype == torch.float32
    assert np.array_equal(td["observation"].numpy(), expected)
    action = np.array([[0.5, -0.2, 0.1, 1.0], [-0.3, 0.4, 0.0, -1.0]], dtype=np.float32)
    td["action"] = torch.from_numpy(action)
    nxt = env.step(td)["next"]
    expected = np.stack([e.step(a)[0] for e, a in zip(ref, action)]).astype(np.float32)
    assert nxt["observation"].dtype == torch.float32
    assert np.array_equal(nxt["observation"].numpy(), expected)
    assert nxt["task_id"].tolist() == [tasks.TASKS.index(n) for n in names]


def test_policy_training_mode_is_restored():
    policy = ConstPolicy(0.0)
    policy.train()
    evaluate(policy, "reach", rollouts_per_task=1, horizon=2, workers=1, progress=False)
    assert policy.training


def _bench_eval():
    """``benchmarks.bench_eval`` (its spawned workers import it by that name)."""
    from benchmarks import bench_eval

    return bench_eval


def test_bench_eval_interleaved_raw_side_runs_every_step(monkeypatch):
    # The interleaved raw side must execute exactly the steps it is given, on the evaluator's
    # schedule: 3 slots over 5 rollouts of 2 tasks; each env step and each reset is counted.
    bench = _bench_eval()
    counts = {"built": 0, "step": 0, "reset": 0}
    real = tasks.make_env

    def counting(name):
        counts["built"] += 1
        env = real(name)
        step, reset = env.step, env.reset
        env.step = lambda a: counts.__setitem__("step", counts["step"] + 1) or step(a)
        env.reset = lambda *a, **k: counts.__setitem__("reset", counts["reset"] + 1) or reset(*a, **k)
        return env

    monkeypatch.setattr(tasks, "make_env", counting)
    monkeypatch.setattr(bench, "_RAW_IDLE", {})
    reach, drawer = "reach-v3", "drawer-close-v3"
    shard = [(reach, 0, 4), (reach, 1, 1), (reach, 2, 7), (drawer, 0, 2), (drawer, 1, 3)]
    assert bench.raw_interleaved_shard(shard, batch=3) == 17
    # a finished slot whose task has rollouts left keeps its env: 3 envs for the 3 slots, kept for the next round
    assert counts == {"built": 3, "step": 17, "reset": 5}
    assert sum(map(len, bench._RAW_IDLE.values())) == 3


@pytest.mark.slow
def test_bench_eval_quick_writes_csv(tmp_path, monkeypatch, open_pool):
    bench = _bench_eval()
    # The benchmark's evaluations run on the module's pool, which stays open: its workers serve the next tests.
    monkeypatch.setattr(ev, "RolloutPool", lambda: contextlib.nullcontext(open_pool))
    out = tmp_path / "eval.csv"
    # Both sections: all_cores splits the rollouts over 2 workers, whose batches differ from one
    # process's (its rows may differ in the last bits of the returns, never in steps or success).
    bench.main(["--quick", "--workers", "2", "--out", str(out), "--cache", str(tmp_path / "cache")])
    df = pd.read_csv(out)
    assert list(df.columns) == bench.COLUMNS
    assert list(df["section"]) == ["one_process"] * 2 + ["all_cores"] * 2
    assert list(df["rep"].astype(str)) == ["0", "median"] * 2
    for col in ("raw_steps_per_s", "raw_interleaved_steps_per_s", "eval_steps_per_s"):
        assert (df[col] > 0).all()
    assert np.allclose(df["ratio"], df["eval_steps_per_s"] / df["raw_steps_per_s"])
    assert np.allclose(df["ratio_interleaved"], df["eval_steps_per_s"] / df["raw_interleaved_steps_per_s"])
    assert df["success_rate"].between(0, 1).all() and (df["mean_steps"] >= 1).all()
    assert any((tmp_path / "cache").glob("mlp-*.pt"))  # the trained policy is cached


@pytest.mark.parametrize(
    ("rollouts", "horizon", "expected"),
    [(2500, 500, 32), (50, 500, 12), (100, 500, 17), (3, 500, 3), (10, 20, 4)],
)
def test_default_envs_per_worker(rollouts, horizon, expected):
    # sqrt(rollouts * horizon * 0.8e-3 / 0.14), within 4..32 and at most the rollouts: 50 * 500 -> 11.95
    assert ev.default_envs_per_worker(rollouts, horizon) == expected


def test_progress_bar_counts_rollouts(capsys):
    evaluate(ConstPolicy(0.0), "reach", rollouts_per_task=3, horizon=2, workers=1, envs_per_worker=2, progress=True)
    err = capsys.readouterr().err
    assert "evaluate" in err and "3/3" in err


@pytest.mark.slow
def test_a_worker_error_reaches_the_caller(open_pool):
    with pytest.raises(ValueError, match=r"non-finite actions for drawer-close-v3 \(rollout 0\) at step 2"):
        evaluate(
            ConstPolicy(0.0, nan_at_step=2),
            ["reach", "drawer-close"],
            1,
            horizon=5,
            workers=2,
            progress=False,
            pool=open_pool,
        )


def plain_const_rollout(task, k, value, horizon):
    """A constant action on a freshly built env: (success, steps, return) as the evaluator counts them."""
    env = tasks.make_env(task)
    env.set_task(tasks.variation(task, 1000, k))
    env.reset()
    total = 0.0
    for t in range(1, horizon + 1):
        _, reward, _, _, info = env.step(np.full(4, value, dtype=np.float32))
        total += float(reward)
        if info["success"]:
            return True, t, total
    return False, horizon, total


def test_reused_envs_give_the_rows_of_fresh_envs():
    # One slot: every rollout after the first refills it, keeping the env of its task (same-task
    # refill) or swapping it; the second call reuses the envs the first one kept in the pool.
    names = ["reach-v3", "drawer-close-v3"]
    with RolloutPool() as pool:
        runs = [
            evaluate(ConstPolicy(0.7), names, 3, horizon=40, workers=1, envs_per_worker=1, progress=False, pool=pool)
            for _ in range(2)
        ]
        assert len(pool.envs) > 0  # envs were kept for the next call
    pd.testing.assert_frame_equal(runs[0], runs[1])
    for row in runs[0].itertuples():
        success, steps, total = plain_const_rollout(row.task, row.variation_index, 0.7, 40)
        assert (row.success, row.steps, row[tuple(runs[0].columns).index("return") + 1]) == (success, steps, total)
    assert len(pool.envs) == 0  # closed with the pool


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def _evaluation_workers() -> list:
    return [p for p in multiprocessing.active_children() if p.name == "tar-rl-evaluate"]


def test_the_module_keeps_no_state_and_a_closed_pool_is_refused():
    for name in ("_POOL", "_IDLE", "_PROGRESS", "close_workers", "clear_env_cache"):
        assert not hasattr(ev, name)
    pool = RolloutPool()
    assert pool.pids == () and not pool.closed  # no process before an evaluation needs one
    pool.close()
    with pytest.raises(ValueError, match="closed"):
        evaluate(ConstPolicy(0.0), "reach", 1, horizon=2, workers=1, progress=False, pool=pool)
    with pytest.raises(ValueError, match="closed"), pool:
        pass


@pytest.mark.slow
def test_a_pool_keeps_its_workers_between_evaluations_and_close_ends_them(expert_rows, rows_without_pool, open_pool):
    with open_pool as pool:
        first = evaluate(ExpertPolicy(), EASY, 2, seed=1000, horizon=200, workers=2, progress=False, pool=pool)
        pids = pool.pids
        assert len(pids) == 2 and all(map(_alive, pids))
        with pytest.raises(ValueError, match="non-finite actions"):  # a worker's error leaves the pool usable
            evaluate(ConstPolicy(0.0, nan_at_step=2), EASY, 1, horizon=5, workers=2, progress=False, pool=pool)
        second = evaluate(ExpertPolicy(), EASY, 2, seed=1000, horizon=200, workers=2, progress=False, pool=pool)
        assert pool.pids == pids  # the same processes served the three evaluations
    pd.testing.assert_frame_equal(first, expert_rows)
    pd.testing.assert_frame_equal(second, expert_rows)
    assert pool.closed and pool.pids == ()
    assert not any(map(_alive, pids))
    # Without a pool, an evaluation's workers end before it returns.
    assert rows_without_pool[1] == []


@pytest.mark.slow
def test_an_exception_ends_the_workers_idle_or_running(monkeypatch, open_pool):
    with pytest.raises(RuntimeError, match="the job failed"), open_pool as pool:
        evaluate(ConstPolicy(0.0), "reach", 2, horizon=3, workers=2, progress=False, pool=pool)
        idle = pool.pids
        raise RuntimeError("the job failed")
    assert len(idle) == 2 and not any(map(_alive, idle))
    # Interrupted (Ctrl-C) while the workers run their shards: they are terminated, not waited for.
    running = []

    def interrupted(workers, progress):
        running.extend(w.process.pid for w in workers if w.busy)
        raise KeyboardInterrupt

    monkeypatch.setattr(ev, "_gather", interrupted)
    with pytest.raises(KeyboardInterrupt), RolloutPool() as pool:
        evaluate(ExpertPolicy(), EASY, 2, horizon=200, workers=2, progress=False, pool=pool)
    assert len(running) == 2 and not any(map(_alive, running))
    assert _evaluation_workers() == []


class _DiesInWorkers(TensorDictModuleBase):
    """Ends the process it runs in, unless that is the test's own."""

    in_keys = ["observation"]
    out_keys = ["action"]

    def __init__(self):
        super().__init__()
        self.parent = os.getpid()

    def forward(self, td):
        if os.getpid() != self.parent:
            os._exit(3)
        td.set("action", torch.zeros(td.batch_size[0], 4))
        return td


@pytest.mark.slow
def test_a_dead_worker_is_replaced(expert_rows, open_pool):
    with open_pool as pool:
        with pytest.raises(BrokenProcessPool, match="exit code 3"):
            evaluate(_DiesInWorkers(), "reach", 2, horizon=3, workers=2, progress=False, pool=pool)
        assert pool.pids == ()  # the other worker was ended too
        first = evaluate(ExpertPolicy(), EASY, 2, seed=1000, horizon=200, workers=2, progress=False, pool=pool)
        pids = pool.pids
        os.kill(pids[0], signal.SIGKILL)  # an idle worker killed between evaluations
        while pids[0] in [p.pid for p in _evaluation_workers()]:  # (active_children reaps it once it is dead)
            time.sleep(0.05)
        second = evaluate(ExpertPolicy(), EASY, 2, seed=1000, horizon=200, workers=2, progress=False, pool=pool)
        assert len(pool.pids) == 2 and pool.pids != pids
    pd.testing.assert_frame_equal(first, expert_rows)
    pd.testing.assert_frame_equal(second, expert_rows)
    assert _evaluation_workers() == []
