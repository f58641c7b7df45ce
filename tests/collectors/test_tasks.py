"""The MetaWorld task registry (tar_rl.collectors.metaworld.tasks): names, ordering, groups, instructions, variations.

Expected group members are typed from the TAR paper's 28/11/6/5 grouping of MetaWorld's tasks,
not copied from the module. Only the last tests build MetaWorld objects
(one ``MT1`` costs about a second).
"""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from tar_rl.collectors.metaworld import tasks
from tar_rl.collectors.metaworld.tasks import (
    DIFFICULTY_GROUPS,
    GROUPS,
    INSTRUCTIONS,
    TASKS,
    check_disjoint,
    group_of,
    resolve_tasks,
    task_index,
    variation,
    variation_seeds,
)

# Typed from metaworld.md, with the -v3 suffix added by hand.
MEDIUM = {
    "basketball-v3",
    "bin-picking-v3",
    "box-close-v3",
    "coffee-pull-v3",
    "coffee-push-v3",
    "hammer-v3",
    "peg-insert-side-v3",
    "push-wall-v3",
    "soccer-v3",
    "sweep-v3",
    "sweep-into-v3",
}
HARD = {"assembly-v3", "hand-insert-v3", "pick-out-of-hole-v3", "pick-place-v3", "push-v3", "push-back-v3"}
VERY_HARD = {"shelf-place-v3", "disassemble-v3", "stick-pull-v3", "stick-push-v3", "pick-place-wall-v3"}
SOME_EASY = {"button-press-v3", "dial-turn-v3", "peg-unplug-side-v3", "reach-v3", "window-open-v3", "faucet-close-v3"}


# ---------------------------------------------------------------- names and ordering


def test_tasks_are_the_50_metaworld_v3_names_sorted():
    from metaworld.env_dict import ALL_V3_ENVIRONMENTS

    assert len(TASKS) == 50
    assert len(set(TASKS)) == 50
    assert list(TASKS) == sorted(TASKS)
    assert set(TASKS) == set(ALL_V3_ENVIRONMENTS)
    assert GROUPS["mt50"] == TASKS


def test_task_index_is_alphabetical():
    # Alphabetically: assembly < basketball < bin-picking < box-close < ... < window-close < window-open.
    assert task_index("assembly") == 0
    assert task_index("assembly-v3") == 0
    assert task_index("basketball") == 1
    assert task_index("bin-picking-v3") == 2
    assert task_index("window-close") == 48
    assert task_index("window-open-v3") == 49
    assert [task_index(t) for t in TASKS] == list(range(50))


# ---------------------------------------------------------------- groups


def test_difficulty_groups_match_the_paper():
    assert DIFFICULTY_GROUPS == ("easy", "medium", "hard", "very_hard")
    assert [len(GROUPS[g]) for g in DIFFICULTY_GROUPS] == [28, 11, 6, 5]
    assert set(GROUPS["medium"]) == MEDIUM
    assert set(GROUPS["hard"]) == HARD
    assert set(GROUPS["very_hard"]) == VERY_HARD
    assert SOME_EASY <= set(GROUPS["easy"])
    # Disjoint (sizes add up to 50 with no repeats) and together all tasks.
    members = [t for g in DIFFICULTY_GROUPS for t in GROUPS[g]]
    assert len(members) == len(set(members)) == 50
    assert set(members) == set(TASKS)
    assert set(GROUPS["easy"]) == set(TASKS) - MEDIUM - HARD - VERY_HARD


def test_mt10_is_metaworlds_mt10():
    from metaworld.env_dict import MT10_V3

    assert len(GROUPS["mt10"]) == 10
    assert set(GROUPS["mt10"]) == set(MT10_V3)
    assert {"reach-v3", "push-v3", "pick-place-v3", "window-close-v3"} <= set(GROUPS["mt10"])


def test_group_of():
    assert group_of("reach") == "easy"
    assert group_of("sweep-v3") == "medium"
    assert group_of("push") == "hard"
    assert group_of("push-back-v3") == "hard"
    assert group_of("stick-push-v3") == "very_hard"
    for task in TASKS:
        assert task in GROUPS[group_of(task)]
    with pytest.raises(ValueError, match="not a MetaWorld task name"):
        group_of("no-such-task")


# ---------------------------------------------------------------- instructions


def test_instructions():
    assert set(INSTRUCTIONS) == set(TASKS)
    for task in TASKS:
        assert isinstance(INSTRUCTIONS[task], str)
        assert INSTRUCTIONS[task].strip(), task
    assert INSTRUCTIONS["push-v3"] != INSTRUCTIONS["push-back-v3"]
    # Text conditioning needs one text per task.
    assert len(set(INSTRUCTIONS.values())) == 50


# ---------------------------------------------------------------- resolve_tasks


@pytest.mark.parametrize(
    ("spec", "expected"),
    [
        # A group, returned in TASKS (alphabetical) order: push-back-v3 < push-v3 ("b" < "v").
        ("hard", ("assembly-v3", "hand-insert-v3", "pick-out-of-hole-v3", "pick-place-v3", "push-back-v3", "push-v3")),
        # Names with and without -v3, spaces, a duplicate; comma-separated.
        ("reach, push ,push-v3", ("push-v3", "reach-v3")),
        ("pick-place-v3", ("pick-place-v3",)),
        # A list mixing a group and a task already in it: pick-place-v3 < pick-place-wall-v3.
        (
            ["very_hard", "pick-place", "stick-push-v3"],
            (
                "disassemble-v3",
                "pick-place-v3",
                "pick-place-wall-v3",
                "shelf-place-v3",
                "stick-pull-v3",
                "stick-push-v3",
            ),
        ),
        (("window-open", "assembly"), ("assembly-v3", "window-open-v3")),
    ],
)
def test_resolve_tasks(spec, expected):
    assert resolve_tasks(spec) == expected


def test_resolve_tasks_groups():
    assert resolve_tasks("mt50") == TASKS
    assert resolve_tasks("easy,medium,hard,very_hard") == TASKS
    mt10 = resolve_tasks("mt10")
    assert len(mt10) == 10
    assert list(mt10) == sorted(mt10)


@pytest.mark.parametrize("spec", ["nope", "reach,nope", "", ["reach", ""], [], "reach-v2", "Hard"])
def test_resolve_tasks_unknown(spec):
    with pytest.raises(ValueError) as err:
        resolve_tasks(spec)
    message = str(err.value)
    for expected in ("easy", "very_hard", "mt10", "mt50", "assembly", "window-open"):
        assert expected in message
    if spec == "reach,nope":
        assert "nope" in message


def test_task_index_unknown():
    with pytest.raises(ValueError, match="window-open"):
        task_index("nope")


def test_task_index_group_name_is_valueerror():
    with pytest.raises(ValueError, match="'easy' is not a MetaWorld task name"):
        task_index("easy")
    with pytest.raises(ValueError, match="not a MetaWorld task name"):
        group_of("mt10")
    with pytest.raises(ValueError, match="start at 0"):
        variation("reach-v3", 1000, -1)


# ---------------------------------------------------------------- seeds


def test_variation_seeds():
    assert tasks.VARIATIONS_PER_SEED == 50
    # Episodes 0..49 use seed base; 50 uses base + 1; n_episodes = 0 uses none.
    assert variation_seeds(1000, 50) == (1000,)
    assert variation_seeds(1000, 51) == (1000, 1001)
    assert variation_seeds(1000, 100) == (1000, 1001)  # episodes 0..99 -> 99 // 50 = 1
    assert variation_seeds(1000, 101) == (1000, 1001, 1002)  # episode 100 -> 100 // 50 = 2
    assert variation_seeds(5, 0) == ()
    assert variation_seeds(5, -3) == ()


def test_check_disjoint():
    demo = variation_seeds(0, 1000)  # seeds 0..19
    assert check_disjoint(demo, variation_seeds(1000, 50)) is None
    assert check_disjoint([1, 2], []) is None
    with pytest.raises(ValueError, match=r"\[19\]"):
        check_disjoint(demo, variation_seeds(19, 60))  # seeds 19, 20
    with pytest.raises(ValueError, match=r"\[1000, 1001\]"):
        check_disjoint((1001, 1000, 7), [1000, 1001, 1002])


def test_variation_seed_and_index_arithmetic(monkeypatch):
    # Without MetaWorld: a fake benchmark whose variation i of seed s is (task, s, i).
    class Fake:
        def __init__(self, task, seed):
            self.train_tasks = [(task, seed, i) for i in range(50)]

    monkeypatch.setattr(tasks, "_benchmark", Fake)
    monkeypatch.setattr(tasks, "_VARIATIONS", {})  # nothing cached from real MT1 objects
    # Episode j uses variation j % 50 of seed base + j // 50.
    assert variation("reach-v3", 1000, 0) == ("reach-v3", 1000, 0)
    assert variation("reach-v3", 1000, 49) == ("reach-v3", 1000, 49)
    assert variation("reach-v3", 1000, 50) == ("reach-v3", 1001, 0)  # 50 // 50 = 1, 50 % 50 = 0
    assert variation("reach-v3", 1000, 123) == ("reach-v3", 1002, 23)  # 123 = 2 * 50 + 23


# ---------------------------------------------------------------- MetaWorld objects (slow-ish)


@pytest.fixture(scope="module")
def reach_variations():
    return variation("reach-v3", 1000, 0), variation("reach-v3", 1000, 1)


def test_variation_is_deterministic(reach_variations):
    import metaworld

    v0, v1 = reach_variations
    assert isinstance(v0, metaworld.Task)
    assert v0.env_name == "reach-v3"
    assert variation("reach-v3", 1000, 0) is v0  # cached: the same object for the same arguments
    assert v0.data != v1.data  # episodes j and j + 1 differ
    rand0, rand1 = (pickle.loads(v.data)["rand_vec"] for v in (v0, v1))
    assert not np.allclose(rand0, rand1)
    # The same values from an MT1 built independently with the same seed.
    fresh = metaworld.MT1("reach-v3", seed=1000).train_tasks[1]
    np.testing.assert_array_equal(pickle.loads(fresh.data)["rand_vec"], rand1)


def test_make_env_shows_the_variation_goal(reach_variations):
    v0, v1 = reach_variations
    env = tasks.make_env("reach-v3")
    env.set_task(v0)
    obs, _ = env.reset()
    assert obs.shape == (39,)
    goal = obs[36:39]
    assert np.abs(goal).sum() > 0
    # reach-v3's variation vector is (object xyz, goal xyz): the observation shows that goal.
    np.testing.assert_allclose(goal, pickle.loads(v0.data)["rand_vec"][3:6])
    env.set_task(v1)
    obs1, _ = env.reset()
    assert not np.allclose(obs1[36:39], goal)
    env.close()


def test_make_env_copies_the_compiled_model_and_steps_identically(reach_variations):
    from metaworld.env_dict import ALL_V3_ENVIRONMENTS

    first, second = tasks.make_env("reach-v3"), tasks.make_env("reach-v3")  # the second copies a compiled model
    fresh = ALL_V3_ENVIRONMENTS["reach-v3"]()  # MetaWorld's own construction, XML compiled again
    assert first.model is not second.model and first.data is not second.data
    actions = np.random.default_rng(0).uniform(-1, 1, (60, 4)).astype(np.float32)
    trajectories = []
    for env in (first, second, fresh):
        env.set_task(reach_variations[1])
        obs, _ = env.reset()
        steps = [obs] + [env.step(a)[0] for a in actions]
        trajectories.append(np.stack(steps))
        env.close()
    np.testing.assert_array_equal(trajectories[1], trajectories[2])
    np.testing.assert_array_equal(trajectories[0], trajectories[2])


def test_variations_handed_to_another_process_are_used(monkeypatch):
    monkeypatch.setattr(tasks, "_VARIATIONS", {})

    def no_mt1(task, seed):
        raise AssertionError("MT1 must not be built for received variations")

    monkeypatch.setattr(tasks, "_benchmark", no_mt1)
    received = {("reach-v3", 7): tuple(("v", i) for i in range(50))}
    tasks.add_variations(received)
    assert variation("reach-v3", 7, 3) == ("v", 3)
    assert tasks.cached_variations([("reach-v3", 7), ("reach-v3", 8)]) == received  # only what it holds
    with pytest.raises(ValueError, match="must be 50 tasks"):
        tasks.add_variations({("push-v3", 1): (1, 2)})
