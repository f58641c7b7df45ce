"""The R3 diagnosis (``benchmarks/r3_diagnosis.py``): switch detection, phase shares, switch ratios and per-task
Δ on hand-made recordings and runs against values worked out by hand, its refusals, and its committed outputs."""

from __future__ import annotations

import math
import sys

import numpy as np
import pandas as pd
import pytest
import yaml
from paths import REPO
from run_helpers import write_run

sys.path.insert(0, str(REPO / "benchmarks"))  # r3_diagnosis.py
import r3_diagnosis as diag

COMMITTED = REPO / "benchmarks" / "results" / "regimes" / "diagnosis"
S, F = True, False
# Gripper actions of the hand-made demonstrations (T = 10 each).
# reach: closing (> 0) at t 4-6 only: switch steps t 4 and 7; phases (c = 4, w = 1, k = 2): approach t 0-2,
#   contact onset t 3-4, transport t 5-7, completion t 8-9.
# assembly: never closing: no switch; approach t 0-7, completion t 8-9.
# basketball: closing from the first step: no switch.
GRIPPER = {
    "reach": [0, 0, 0, 0, 1, 1, 1, -1, -1, -1],
    "assembly": [-1] * 10,
    "basketball": [0.5] * 10,
}


def _weights(tasks, emphasis: bool) -> pd.DataFrame:
    """Recordings at R3's two steps; weight 3 at reach's switch steps (t 4, 7) with ``emphasis``, else 1; loss 0.1 w."""
    rows = []
    for step in (1872, 3743):
        for task in tasks:
            for t, g in enumerate(GRIPPER[task]):
                w = 3.0 if emphasis and task == "reach" and t in (4, 7) else 1.0
                rows.append(
                    {"step": step, "task": task, "episode": 0, "t": t, "loss": 0.1 * w, "weight": w, "gripper": g}
                )
    return pd.DataFrame(rows)


def test_switch_steps_treat_zero_as_open_and_never_flag_the_first_step():
    got = diag.switch_steps([0.3, 0, 0, 1, 0.5, -1, 0, 0.2])
    # closing: T F F T T F F T -> changes at 1, 3, 5, 7; -1 -> 0 is no change (both open)
    assert got.tolist() == [F, S, F, S, F, S, F, S]
    assert diag.switch_steps([1.0]).tolist() == [F]
    assert diag.near(np.array([F, F, S, F, F, F, F]), 1).tolist() == [F, S, S, S, F, F, F]
    assert diag.near(np.array([S, F, F, F, F, F, S]), 2).tolist() == [S, S, S, F, S, S, S]


def _labelled_by_hand() -> pd.DataFrame:
    parts = []
    for seed, emphasis in ((0, True), (1, False)):
        w = diag.label_steps(_weights(["reach", "assembly"], emphasis))
        parts.append(w.assign(objective="tar", seed=seed))
    df = pd.concat(parts, ignore_index=True)
    return df.assign(at=df["step"].map({1872: "full", 3743: "last"}))


def test_phase_table_pools_over_tasks_then_averages_over_seeds():
    table = diag.phase_table(_labelled_by_hand())
    last = table[table["at"] == "last"].set_index("phase")
    assert list(last.index) == ["approach", "contact_onset", "transport", "completion"]
    # steps of the 20: approach 3 + 8, onset 2, transport 3, completion 2 + 2
    assert last["step_share"].tolist() == pytest.approx([11 / 20, 2 / 20, 3 / 20, 4 / 20])
    # seed 0: total weight 24; onset 1 + 3, transport 1 + 1 + 3. Seed 1: weight shares = step shares.
    seed0 = {"approach": 11 / 24, "contact_onset": 4 / 24, "transport": 5 / 24, "completion": 4 / 24}
    seed1 = {"approach": 11 / 20, "contact_onset": 2 / 20, "transport": 3 / 20, "completion": 4 / 20}
    for phase in seed0:
        assert last.loc[phase, "weight_share"] == pytest.approx((seed0[phase] + seed1[phase]) / 2)
        assert last.loc[phase, "weight_share_sd"] == pytest.approx(abs(seed0[phase] - seed1[phase]) / math.sqrt(2))
    # mean weight per phase: seed 0 onset (1 + 3) / 2 = 2, transport 5 / 3; seed 1 all 1
    assert last.loc["contact_onset", "mean_weight"] == pytest.approx((2 + 1) / 2)
    assert last.loc["transport", "mean_weight"] == pytest.approx((5 / 3 + 1) / 2)
    assert last.loc["contact_onset", "ratio"] == pytest.approx((4 / 24 + 0.1) / 2 / 0.1)
    assert (last["seeds"] == 2).all()


def test_switch_table_per_seed_and_pooled():
    table = diag.switch_table(_labelled_by_hand())
    last = table[table["at"] == "last"].set_index("seed")
    assert list(last.index) == ["0", "1", "all"]
    # seed 0: switch steps weigh 3, the 18 others 1; within +-2: reach t 2-9 (3 + 3 + 6 ones) / 8 = 1.5,
    # outside: reach t 0-1 and assembly's 10 steps, all 1
    assert last.loc["0", "switch_steps"] == 2
    assert last.loc["0", "switch_ratio"] == pytest.approx(3.0)
    assert last.loc["0", "near_ratio"] == pytest.approx(1.5)
    assert last.loc["0", "loss_switch_ratio"] == pytest.approx(3.0)
    assert last.loc["1", "switch_ratio"] == pytest.approx(1.0)
    # pooled: switch steps (3 + 3 + 1 + 1) / 4 = 2 against 36 ones
    assert last.loc["all", "switch_steps"] == 4
    assert last.loc["all", "weight_switch"] == pytest.approx(2.0)
    assert last.loc["all", "switch_ratio"] == pytest.approx(2.0)


# Success per run (2 rollouts per task): Δ reach ((100 - 50) + (50 - 0)) / 2 = +50, assembly ((50 - 100) + 0) / 2
# = -25, basketball 0; uniform's mean: reach 25, assembly 100, basketball 25.
RUNS = {
    ("uniform", 0): {"reach": [(S, 50), (F, 100)], "assembly": [(S, 50), (S, 50)], "basketball": [(F, 100), (F, 100)]},
    ("tar", 0): {"reach": [(S, 50), (S, 50)], "assembly": [(S, 50), (F, 100)], "basketball": [(F, 100), (F, 100)]},
    ("uniform", 1): {"reach": [(F, 100), (F, 100)], "assembly": [(S, 50), (S, 50)], "basketball": [(S, 50), (F, 100)]},
    ("tar", 1): {"reach": [(S, 50), (F, 100)], "assembly": [(S, 50), (S, 50)], "basketball": [(S, 50), (F, 100)]},
}


def _write_r3(root, skip=(), weights_steps=(1872, 3743)):
    """The hand-made R3 runs (configs made R3's: MT50, 50 demonstrations, 3743 steps)."""
    for (objective, seed), rollouts in RUNS.items():
        if (objective, seed) in skip:
            continue
        weights = _weights(list(GRIPPER), objective == "tar" and seed == 0)
        path = write_run(
            root, objective, seed, rollouts, steps=3743, weights=weights[weights["step"].isin(weights_steps)]
        )
        config = yaml.safe_load((path / "config.yaml").read_text())
        config["data"].update(tasks=["mt50"], n_demos=50)
        (path / "config.yaml").write_text(yaml.safe_dump(config))


def test_the_command_on_hand_made_runs(tmp_path):
    _write_r3(tmp_path / "runs")
    assert diag.main(["--runs", str(tmp_path / "runs"), "--out", str(tmp_path / "out")]) == 0
    tasks = pd.read_csv(tmp_path / "out" / "tasks.csv").set_index("task")
    assert tasks.loc["reach", "delta"] == pytest.approx(50.0)
    assert tasks.loc["assembly", "delta"] == pytest.approx(-25.0)
    assert tasks.loc["basketball", "delta"] == pytest.approx(0.0)
    assert tasks["uniform"].to_dict() == pytest.approx({"reach": 25.0, "assembly": 100.0, "basketball": 25.0})
    assert tasks.loc["reach", "pairs_higher"] == 2 and tasks.loc["assembly", "pairs_lower"] == 1
    assert tasks["switch_share"].to_dict() == pytest.approx({"reach": 0.2, "assembly": 0.0, "basketball": 0.0})
    md = (tmp_path / "out" / "diagnosis.md").read_text()
    assert "TAR higher: reach (+50.0)." in md and "TAR lower: assembly (-25.0)." in md and "Equal: basketball." in md
    for name in ("phases.csv", "switches.csv", "scatter.png", "weights_time.png"):
        assert (tmp_path / "out" / name).is_file(), name
    again = diag.diagnose(tmp_path / "runs")
    assert again.markdown == md
    for name, text in again.csv_texts().items():
        assert (tmp_path / "out" / name).read_text() == text, name


def test_refusals_name_what_is_missing(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(SystemExit, match=r"no R3 runs in .*data.tasks \[.mt50.\], data.n_demos 50"):
        diag.diagnose(tmp_path / "empty")
    write_run(tmp_path / "other", "uniform", 0, RUNS[("uniform", 0)])  # not R3: eight-task settings
    with pytest.raises(SystemExit, match="no R3 runs"):
        diag.diagnose(tmp_path / "other")
    _write_r3(tmp_path / "half", skip=[("tar", 1)])
    with pytest.raises(SystemExit, match=r"pair of seed 1 is incomplete: no tar run \(uniform-mlp-s1-deadbeef\)"):
        diag.diagnose(tmp_path / "half")
    _write_r3(tmp_path / "short", weights_steps=(3743,))
    with pytest.raises(SystemExit, match=r"has no recorded weights at training step\(s\) \[1872\]"):
        diag.diagnose(tmp_path / "short")


def test_committed_diagnosis_equals_what_the_command_computes():
    """benchmarks/results/regimes/diagnosis is recomputed from the committed runs."""
    result = diag.diagnose(diag.DEFAULT_RUNS)
    assert (COMMITTED / "diagnosis.md").read_text() == result.markdown
    for name, text in result.csv_texts().items():
        assert (COMMITTED / name).read_text() == text, name
