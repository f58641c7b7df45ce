"""Success rate, Fast20 and NEPS (tar_rl.metrics) against values computed by hand in the comments."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
import torch

from tar_rl import metrics
from tar_rl.metrics import as_percent, fast20, neps, success_rate, summarize

# ---------------------------------------------------------------- success rate


@pytest.mark.parametrize(
    ("success", "expected"),
    [
        ([True, False, True, True], 0.75),  # 3 / 4
        ([1, 0, 0, 0, 0], 0.2),  # 1 / 5
        ([0.0, 1.0], 0.5),  # info["success"] is a float 0.0 / 1.0: 1 / 2
        (np.zeros(50, dtype=bool), 0.0),  # 0 / 50
        (torch.tensor([True, True, False]), 2 / 3),  # 2 / 3
    ],
)
def test_success_rate(success, expected):
    assert success_rate(success) == pytest.approx(expected)


# ---------------------------------------------------------------- Fast20


def test_fast20_paper_n50_averages_ten_smallest():
    # N = 50 -> K = ceil(0.2 * 50) = 10. rho = 1/50 .. 50/50 (shuffled):
    # Fast20 = (1 + 2 + ... + 10) / 50 / 10 = 55 / 500 = 5.5 / 50 = 0.11.
    rho = np.random.default_rng(0).permutation(np.arange(1, 51) / 50)
    assert fast20(rho) == pytest.approx(0.11)
    assert metrics.fast20_k(50) == 10


def test_fast20_n7_rounds_k_up():
    # N = 7 -> K = ceil(1.4) = 2: the two smallest are 0.1 and 0.2 -> (0.1 + 0.2) / 2 = 0.15
    # (K = 1 would give 0.1, K = 3 would give 0.2).
    assert fast20([0.7, 0.1, 0.5, 0.2, 0.9, 0.3, 1.0]) == pytest.approx(0.15)


def test_fast20_k_small_n():
    # N = 15 -> K = ceil(3.0) = 3: rho = 1/15 .. 15/15 -> (1 + 2 + 3) / 15 / 3 = 2/15
    # (K = 4 would give 2.5/15, K = 2 would give 1.5/15).
    assert metrics.fast20_k(15) == 3
    assert fast20(np.arange(1, 16) / 15) == pytest.approx(2 / 15)
    # K = ceil(N / 5): N = 1 -> 1, 5 -> 1, 6 -> 2, 10 -> 2, 11 -> 3.
    assert [metrics.fast20_k(n) for n in (1, 5, 6, 10, 11)] == [1, 1, 2, 2, 3]


def test_fast20_ties():
    # N = 10 -> K = 2; sorted: 0.2, 0.2, 0.5, 0.5, 0.5, 1 x 5 -> (0.2 + 0.2) / 2 = 0.2.
    assert fast20([0.5, 1.0, 0.2, 0.5, 1.0, 1.0, 0.2, 0.5, 1.0, 1.0]) == pytest.approx(0.2)
    # A tie across the K boundary: sorted 0.1, 0.3, 0.3, 0.3, 1 x 6 -> (0.1 + 0.3) / 2 = 0.2.
    assert fast20([0.3, 1.0, 0.3, 0.1, 1.0, 0.3, 1.0, 1.0, 1.0, 1.0]) == pytest.approx(0.2)


def test_fast20_ignores_success_and_single_rollout():
    # All failures at the horizon: Fast20 = 1 (the fastest 20 % are failures too).
    assert fast20(np.ones(50)) == pytest.approx(1.0)
    # N = 1 -> K = 1 -> the value itself.
    assert fast20([0.42]) == pytest.approx(0.42)


def test_fast20_accepts_torch():
    # N = 5 -> K = 1 -> the smallest, 0.2.
    assert fast20(torch.tensor([0.6, 0.2, 1.0, 0.4, 0.8], requires_grad=True)) == pytest.approx(0.2)


# ---------------------------------------------------------------- NEPS


def test_neps_by_hand():
    # sum(rho) = 0.1 + 0.3 + 1.0 + 1.0 = 2.4; S = 2 -> NEPS = 2.4 / 2 = 1.2
    # (= E[rho] / r = 0.6 / 0.5).
    assert neps([0.1, 0.3, 1.0, 1.0], [1, 1, 0, 0]) == pytest.approx(1.2)
    # All succeed: NEPS = mean(rho) = (0.2 + 0.4) / 2 = 0.3.
    assert neps(np.array([0.2, 0.4]), np.array([True, True])) == pytest.approx(0.3)
    # torch inputs: (0.5 + 1.0 + 0.25) / 1 = 1.75.
    assert neps(torch.tensor([0.5, 1.0, 0.25]), torch.tensor([0, 0, 1])) == pytest.approx(1.75)


def test_neps_zero_successes_is_inf():
    assert neps([1.0, 1.0, 0.5], [0, 0, 0]) == math.inf
    assert neps(np.ones(50), np.zeros(50, dtype=bool)) == math.inf


# ---------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    ("call", "match"),
    [
        (lambda: success_rate([]), "empty"),
        (lambda: fast20([]), "empty"),
        (lambda: neps([], []), "empty"),
        (lambda: fast20([0.5, 0.0]), r"\(0, 1\]"),  # rho = 0 means no step was executed
        (lambda: fast20([0.5, 1.5]), r"\(0, 1\]"),
        (lambda: fast20([-0.1]), r"\(0, 1\]"),
        (lambda: fast20([0.5, math.inf]), r"\(0, 1\]"),
        (lambda: fast20([0.5, math.nan]), "NaN"),
        (lambda: neps([0.5, math.nan], [1, 1]), "NaN"),
        (lambda: success_rate([1.0, math.nan]), "NaN"),
        (lambda: success_rate([1, 2]), "0/1"),
        (lambda: success_rate([0.5]), "0/1"),
        (lambda: neps([0.5, 0.6, 0.7], [1, 0]), "3 and 2"),
        (lambda: fast20([[0.5, 0.6]]), "1-D"),
        (lambda: fast20(0.5), "1-D"),
        (lambda: fast20(["a", "b"]), "numeric"),
    ],
)
def test_bad_input_raises(call, match):
    with pytest.raises(ValueError, match=match):
        call()


# ---------------------------------------------------------------- summarize

# Three tasks, two groups; task "b" never succeeds.
#   c (hard), N = 10: rho 0.1 0.1 0.3 0.5 0.5 0.5 1 1 1 1, success 1 1 1 1 1 1 0 0 0 0
#       success = 6/10 = 0.6; K = 2 -> Fast20 = (0.1 + 0.1) / 2 = 0.1;
#       sum rho = 0.2 + 0.3 + 1.5 + 4 = 6.0 -> NEPS = 6.0 / 6 = 1.0
#   a (easy), N = 5: rho 0.2 0.4 0.6 1 1, success 1 1 1 0 0
#       success = 3/5 = 0.6; K = 1 -> Fast20 = 0.2; sum rho = 3.2 -> NEPS = 3.2 / 3
#   b (easy), N = 5: rho 1 1 1 1 1, success 0 0 0 0 0
#       success = 0; Fast20 = 1.0; NEPS = inf
_TASK_ROWS = {
    "c": ("hard", [0.1, 0.1, 0.3, 0.5, 0.5, 0.5, 1, 1, 1, 1], [1, 1, 1, 1, 1, 1, 0, 0, 0, 0]),
    "a": ("easy", [0.2, 0.4, 0.6, 1, 1], [1, 1, 1, 0, 0]),
    "b": ("easy", [1, 1, 1, 1, 1], [0, 0, 0, 0, 0]),
}


def _rollouts() -> pd.DataFrame:
    rows = [
        {"task": t, "group": g, "rho": float(r), "success": bool(s), "extra": 7}
        for t, (g, rhos, succ) in _TASK_ROWS.items()
        for r, s in zip(rhos, succ)
    ]
    # Shuffle the rows: the result must not depend on their order.
    order = np.random.default_rng(1).permutation(len(rows))
    return pd.DataFrame([rows[i] for i in order])


def _row(table, level, name):
    hit = table[(table.level == level) & (table.name == name)]
    assert len(hit) == 1, (level, name)
    return hit.iloc[0]


def test_summarize_by_hand():
    table = summarize(_rollouts())
    assert list(table.columns) == ["level", "name", "n_tasks", "n_rollouts", "success", "fast20", "neps"]
    # Tasks sorted by name, then groups in the paper's order (easy before hard), then overall.
    assert list(zip(table.level, table.name)) == [
        ("task", "a"),
        ("task", "b"),
        ("task", "c"),
        ("group", "easy"),
        ("group", "hard"),
        ("overall", "overall"),
    ]
    expected = {
        # level, name: n_tasks, n_rollouts, success, fast20, neps
        ("task", "a"): (1, 5, 0.6, 0.2, 3.2 / 3),
        ("task", "b"): (1, 5, 0.0, 1.0, math.inf),
        ("task", "c"): (1, 10, 0.6, 0.1, 1.0),
        # easy: success (0.6 + 0) / 2 = 0.3; Fast20 (0.2 + 1.0) / 2 = 0.6;
        # NEPS pooled (3.2 + 5.0) / (3 + 0) = 8.2 / 3 -- finite although task b has no success.
        ("group", "easy"): (2, 10, 0.3, 0.6, 8.2 / 3),
        ("group", "hard"): (1, 10, 0.6, 0.1, 1.0),
        # overall: success (0.6 + 0 + 0.6) / 3 = 0.4 (rollout-weighted would be 9/20 = 0.45);
        # Fast20 (0.2 + 1.0 + 0.1) / 3 = 1.3 / 3; NEPS (3.2 + 5.0 + 6.0) / (3 + 0 + 6) = 14.2 / 9.
        ("overall", "overall"): (3, 20, 0.4, 1.3 / 3, 14.2 / 9),
    }
    for (level, name), (n_tasks, n_rollouts, sr, f20, ne) in expected.items():
        row = _row(table, level, name)
        assert row.n_tasks == n_tasks
        assert row.n_rollouts == n_rollouts
        assert row.success == pytest.approx(sr)
        assert row.fast20 == pytest.approx(f20)
        assert row.neps == pytest.approx(ne)


def test_summarize_group_order_and_zero_success_group():
    df = _rollouts()
    table = summarize(df, groups=["hard", "easy"])
    assert list(table[table.level == "group"].name) == ["hard", "easy"]
    # A group whose only task never succeeds has NEPS inf; overall stays finite:
    # (3.2 + 5.0 + 6.0) / 9 = 14.2 / 9 whatever the grouping.
    df.loc[df.task == "b", "group"] = "very_hard"
    table = summarize(df)
    assert list(table[table.level == "group"].name) == ["easy", "hard", "very_hard"]
    assert _row(table, "group", "very_hard").neps == math.inf
    assert _row(table, "group", "easy").neps == pytest.approx(3.2 / 3)
    assert _row(table, "overall", "overall").neps == pytest.approx(14.2 / 9)


def test_summarize_bad_input():
    df = _rollouts()
    with pytest.raises(ValueError, match=r"'group'.*'rho'"):
        summarize(df.drop(columns=["group", "rho"]))
    with pytest.raises(ValueError, match="empty"):
        summarize(df.iloc[:0])
    with pytest.raises(ValueError, match="DataFrame"):
        summarize(df.to_dict("list"))
    bad = df.copy()
    bad.loc[bad.index[0], "rho"] = 0.0
    with pytest.raises(ValueError, match=r"\(0, 1\]"):
        summarize(bad)
    bad = df.copy()
    bad.loc[bad.task == "a", "group"] = ["easy", "hard", "easy", "easy", "easy"]
    with pytest.raises(ValueError, match="exactly one group"):
        summarize(bad)


# ---------------------------------------------------------------- as_percent


def test_as_percent():
    table = summarize(_rollouts())
    pct = as_percent(table)
    b = _row(pct, "task", "b")
    assert b.neps == math.inf  # inf stays inf
    easy = _row(pct, "group", "easy")
    # 100 x: success 0.3 -> 30, Fast20 0.6 -> 60, NEPS 8.2/3 -> 820/3.
    assert (easy.success, easy.fast20) == (pytest.approx(30.0), pytest.approx(60.0))
    assert easy.neps == pytest.approx(820 / 3)
    assert easy.n_rollouts == 10  # counts unchanged
    assert _row(table, "group", "easy").success == pytest.approx(0.3)  # the input is not modified
    with pytest.raises(ValueError, match="neps"):
        as_percent(table.drop(columns=["neps"]))
