"""The R3 diagnosis (``python -m benchmarks.analysis diagnosis | dims``): switch detection, phase shares, switch
ratios and per-task Δ on hand-made recordings and runs against values worked out by hand, its refusals, and its
committed outputs."""

from __future__ import annotations

import json
import math

import numpy as np
import pandas as pd
import pytest
import yaml
from paths import REPO
from run_helpers import write_run

from benchmarks.analysis import diagnosis as diag
from benchmarks.analysis import dims as dims_module
from benchmarks.analysis.pairs import DEFAULT_RUNS, STEP_KEYS, WINDOW
from benchmarks.analysis.rebuild import training_demos
from tar_rl.report import phases

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
    got = phases.switch_steps([0.3, 0, 0, 1, 0.5, -1, 0, 0.2])
    # closing: T F F T T F F T -> changes at 1, 3, 5, 7; -1 -> 0 is no change (both open)
    assert got.tolist() == [F, S, F, S, F, S, F, S]
    assert phases.switch_steps([1.0]).tolist() == [F]
    assert phases.near(np.array([F, F, S, F, F, F, F]), 1).tolist() == [F, S, S, S, F, F, F]
    assert phases.near(np.array([S, F, F, F, F, F, S]), 2).tolist() == [S, S, S, F, S, S, S]


def _labelled_by_hand() -> pd.DataFrame:
    parts = []
    for seed, emphasis in ((0, True), (1, False)):
        w = phases.label_steps(_weights(["reach", "assembly"], emphasis), STEP_KEYS, WINDOW)
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


def _hand_dims(root) -> pd.DataFrame:
    """Each action dim's loss for the hand-made runs at the last step: 0.1 on every dim, the gripper dim 0.3 at
    reach's switch steps (t 4, 7): xyz share 0.3 / 0.4 = 0.75, and 0.3 / 0.6 = 0.5 at the switch steps."""
    parts = []
    for path in sorted(root.iterdir()):
        objective, _, seed, _ = path.name.split("-")
        w = _weights(list(GRIPPER), objective == "tar" and seed == "s0")
        w = w[w["step"] == 3743]
        switch = (w["task"] == "reach") & w["t"].isin([4, 7])
        dims = {c: 0.1 for c in dims_module.XYZ_COLUMNS} | {"loss_dim3": np.where(switch, 0.3, 0.1)}
        parts.append(w.assign(run=path.name, objective=objective, seed=int(seed[1:]), **dims))
    return pd.concat(parts, ignore_index=True)[list(dims_module.DIMS_COLUMNS)]


def test_xyz_share_by_hand():
    frame = pd.DataFrame({"loss_dim0": [1.0, 3.0, 0.0], "loss_dim1": [1.0, 0.0, 0.0], "loss_dim2": [2.0, 0.0, 0.0]})
    frame["loss_dim3"] = [4.0, 1.0, 2.0]
    # (1 + 1 + 2) / 8, 3 / 4, 0 / 2
    assert dims_module.xyz_share(frame).tolist() == pytest.approx([0.5, 0.75, 0.0])
    row = dims_module._dims_row(frame.assign(weight=1.0, loss=0.0, xyz_share=dims_module.xyz_share(frame)))
    assert row["xyz_share"] == pytest.approx(1.25 / 3)  # the mean of the steps' shares
    assert row["xyz_mass"] == pytest.approx(7 / 14)  # the arm's share of the summed loss: (4 + 3 + 0) / (8 + 4 + 2)
    assert math.isnan(dims_module.xyz_share(frame.assign(loss_dim3=0.0)).iloc[2])  # no loss at all: no share


def test_high_weight_steps_and_deciles_by_hand():
    # one run of 20 steps (reach's gripper twice), weights 0.1 .. 2.0 in a shuffled order; x carries the loss
    # below weight 1.85 and the gripper dim above it
    weights = np.array([7, 19, 2, 11, 0, 15, 5, 18, 9, 13, 1, 16, 3, 10, 6, 17, 12, 4, 14, 8], dtype=float) / 10 + 0.1
    high = weights > 1.85
    frame = pd.DataFrame(
        {
            "run": "r",
            "objective": "tar",
            "seed": 0,
            "step": 3743,
            "task": "reach",
            "episode": np.repeat([0, 1], 10),
            "t": np.tile(np.arange(10), 2),
            "loss": 0.25,
            "weight": weights,
            "gripper": GRIPPER["reach"] * 2,
            "loss_dim0": np.where(high, 0.0, 1.0),
            "loss_dim1": 0.0,
            "loss_dim2": 0.0,
            "loss_dim3": np.where(high, 1.0, 0.0),
        }
    )
    labelled = dims_module.label_dims(frame)
    # the 90th percentile of 0.1 .. 2.0 (linear): 0.1 + 0.9 * 19 * 0.1 = 1.81, so the weights 1.9 and 2.0 are high
    assert sorted(labelled.loc[labelled["high"], "weight"]) == pytest.approx([1.9, 2.0])
    by_decile = labelled.groupby("decile")["weight"].agg(["min", "max"]).to_numpy()
    assert by_decile == pytest.approx(np.array([[0.1 + 0.2 * k, 0.2 + 0.2 * k] for k in range(10)]))
    groups = dims_module.dims_group_table(labelled).set_index(["split", "group"])
    assert groups.loc[("weight", "high"), "xyz_share"] == 0.0 and groups.loc[("weight", "rest"), "xyz_share"] == 1.0
    assert groups.loc[("all", "all"), "xyz_share"] == pytest.approx(18 / 20)
    # switch steps of reach: t 4 and 7 in both episodes; their weights 0.1, 1.9 (episode 0) and 0.7, 0.5 (episode 1)
    assert groups.loc[("switch", "switch"), "steps"] == 4
    assert groups.loc[("switch", "switch"), "mean_weight"] == pytest.approx((0.1 + 1.9 + 0.7 + 0.5) / 4)
    assert groups.loc[("switch", "switch"), "xyz_share"] == pytest.approx(3 / 4)
    deciles = dims_module.dims_decile_table(labelled).set_index("decile")
    assert deciles["xyz_share"].tolist() == [1.0] * 9 + [0.0]


def test_the_command_with_a_per_dimension_recording(tmp_path):
    _write_r3(tmp_path / "runs")
    dims_module.write_dims(_hand_dims(tmp_path / "runs"), tmp_path / "dims.csv.gz")
    args = ["--runs", str(tmp_path / "runs"), "--out", str(tmp_path / "out"), "--dims", str(tmp_path / "dims.csv.gz")]
    assert diag.main(args) == 0
    groups = pd.read_csv(tmp_path / "out" / "dims_groups.csv").set_index(["objective", "seed", "split", "group"])
    for objective in ("tar", "uniform"):
        for seed in (0, 1):
            one = groups.loc[(objective, seed)]
            assert one.loc[("switch", "switch"), ["steps", "xyz_share"]].tolist() == pytest.approx([2, 0.5])
            assert one.loc[("switch", "other"), ["steps", "xyz_share"]].tolist() == pytest.approx([28, 0.75])
            assert one.loc[("all", "all"), "xyz_share"] == pytest.approx((2 * 0.5 + 28 * 0.75) / 30)
            assert one.loc[("all", "all"), "xyz_mass"] == pytest.approx(30 * 0.3 / (28 * 0.4 + 2 * 0.6))
            # ties at the 90th percentile count as high: with 28 weights of 1, every step is high
            assert one.loc[("weight", "high"), "steps"] == 30
    md = (tmp_path / "out" / "diagnosis.md").read_text()
    assert "## Per action dimension" in md and "Not analysed" not in md
    assert (tmp_path / "out" / "dims_time.png").is_file()
    assert "## Per action dimension" not in diag.diagnose(tmp_path / "runs").markdown  # without the recording
    other = _hand_dims(tmp_path / "runs").replace({"run": {"tar-mlp-s1-deadbeef": "tar-mlp-s1-cafecafe"}})
    dims_module.write_dims(other, tmp_path / "other.csv.gz")
    with pytest.raises(SystemExit, match=r"other runs than R3's pairs \(lacking \['tar-mlp-s1-deadbeef'\]"):
        diag.diagnose(tmp_path / "runs", tmp_path / "other.csv.gz")


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


@pytest.fixture(scope="module")
def committed():
    """The diagnosis of the committed runs and per-dimension recording."""
    return diag.diagnose(DEFAULT_RUNS, dims_module.DEFAULT_DIMS)


def test_committed_diagnosis_equals_what_the_command_computes(committed):
    """benchmarks/results/regimes/diagnosis is recomputed from the committed runs and per-dimension recording."""
    result = committed
    assert (COMMITTED / "diagnosis.md").read_text() == result.markdown
    assert {"dims_groups.csv", "dims_deciles.csv"} <= set(result.csv_texts())
    for name, text in result.csv_texts().items():
        assert (COMMITTED / name).read_text() == text, name


def test_committed_r4_diagnosis_equals_what_the_command_computes():
    """benchmarks/results/regimes/diagnosis_act is recomputed from the committed R4 runs (weights: seed 0's)."""
    out = diag.default_out("R4")
    assert out == COMMITTED.parent / "diagnosis_act"
    result = diag.diagnose(DEFAULT_RUNS, label="R4")
    assert result.pairs.weighted == (0,) and len(result.pairs.runs) == 8
    assert (out / "diagnosis.md").read_text() == result.markdown
    for name, text in result.csv_texts().items():
        assert (out / name).read_text() == text, name


def test_committed_per_dimension_recording_agrees_with_the_committed_runs(committed):
    """dims.csv.gz holds each R3 run's last recording (the committed weights.csv, to its 6 significant digits)
    with four dim losses whose mean is the step loss (the MLP head's loss is the mean over the action dims)."""
    assert dims_module.DEFAULT_DIMS.stat().st_size < 8e6
    dims = committed.dims
    keys = ["run", "task", "episode", "t"]
    own = pd.concat(
        [run.weights.assign(run=run.name) for slot in committed.pairs.runs.values() for run in slot.values()]
    )
    own = own[own["step"] == 3743]
    both = own.merge(dims, on=keys, suffixes=("", "_dims"), validate="one_to_one")
    assert len(both) == len(own) == len(dims) == 16 * 11203
    for column in ("loss", "weight", "gripper"):
        np.testing.assert_allclose(both[f"{column}_dims"], both[column], rtol=1e-5, atol=1e-9, err_msg=column)
    mean = dims[list(dims_module.DIM_COLUMNS)].mean(axis=1)
    np.testing.assert_allclose(mean, dims["loss"], rtol=2e-5, atol=1e-9)


def test_the_training_data_is_opened_by_load_dataset_and_an_old_format_refused(tmp_path):
    """The analyses find the run's dataset by its settings and opens it with tar_rl.data.load_dataset, which refuses a
    format it no longer reads (R3's datasets were of format 2) with how to build it again."""
    from types import SimpleNamespace

    settings = {"tasks": ["reach-v3"], "n_demos": 2, "seed": 0, "chunk_horizon": 1, "history": 1}
    cfg = SimpleNamespace(data=SimpleNamespace(**{k: v for k, v in settings.items() if k != "tasks"}))
    with pytest.raises(SystemExit, match="0 datasets under"):
        training_demos(tmp_path, cfg, ("reach-v3",), {"obs_mean": [0.0]}, "dims")
    (tmp_path / "old").mkdir()
    (tmp_path / "old" / "metadata.json").write_text(json.dumps({**settings, "format_version": 2}))
    with pytest.raises(SystemExit, match=r"format version 2, which this tar-rl no longer reads.*build it again"):
        training_demos(tmp_path, cfg, ("reach-v3",), {"obs_mean": [0.0]}, "dims")


# -- R4: a chunked-heads regime, weights kept for seed 0 only ------------------------------------------------------

# Gripper actions of R4's hand-made demonstrations (T = 10): reach as R3's (switch steps t 4, 7); assembly never
# closing (no switch); basketball closing from t 2 on (switch step t 2).
R4_GRIPPER = {"reach": GRIPPER["reach"], "assembly": [-1] * 10, "basketball": [-1, -1] + [1] * 8}
# Success per run (2 rollouts per task, so 0, 50 or 100 %), seeds 0 and 1:
#   uniform  reach 0 / 50,    assembly 100 / 100, basketball 50 / 0   -> means 25, 100, 25
#   tar      reach 100 / 100, assembly 100 / 50,  basketball 50 / 50  -> Δ reach (100 + 50) / 2 = +75,
#            assembly (0 - 50) / 2 = -25, basketball (0 + 50) / 2 = +25
#   gentle   reach 50 / 50,   assembly 50 / 100,  basketball 50 / 0   -> Δ reach +25, assembly -25, basketball 0
_RATE = {0: [(F, 100), (F, 100)], 50: [(S, 50), (F, 100)], 100: [(S, 50), (S, 50)]}
R4_SUCCESS = {
    ("uniform", 0): (0, 100, 50),
    ("uniform", 1): (50, 100, 0),
    ("tar", 0): (100, 100, 50),
    ("tar", 1): (100, 50, 50),
    ("tar_gentle", 0): (50, 50, 50),
    ("tar_gentle", 1): (50, 100, 0),
}
# The uniform run's per-step loss per task (its recorded demonstrations), and TAR's weights in seed 0's tar run:
# 3 at reach's switch steps, 2 at basketball's, 1 elsewhere; the other runs' weights are all 1.
R4_LOSS = {"reach": 0.3, "assembly": 0.2, "basketball": 0.1}
R4_EMPHASIS = {("reach", 4): 3.0, ("reach", 7): 3.0, ("basketball", 2): 2.0}
# Each run's fit diagnostics over two bins of episode time: (weight_by_bin, heldout_loss_by_bin, spearman).
R4_FIT = {
    ("uniform", 0): ([1.2, 0.8], [0.2, 0.1], 1.0),
    ("uniform", 1): ([1.4, 0.6], [0.4, 0.1], 1.0),
    ("tar", 0): ([1.5, 0.5], [0.2, 0.1], 1.0),
    ("tar", 1): ([1.3, 0.7], [0.1, 0.3], -1.0),
    ("tar_gentle", 0): ([1.1, 0.9], [0.3, 0.2], 1.0),
    ("tar_gentle", 1): ([1.1, 0.9], [0.3, 0.2], 1.0),
}
GENTLE = {"gamma": 0.5, "cap": "exact", "w_max": 1.5}


def _r4_weights(objective: str) -> pd.DataFrame:
    rows = []
    for step in (1872, 3743):
        for task, gripper in R4_GRIPPER.items():
            for t, g in enumerate(gripper):
                w = R4_EMPHASIS.get((task, t), 1.0) if objective == "tar" else 1.0
                loss = R4_LOSS[task] if objective == "uniform" else 0.1
                rows.append({"step": step, "task": task, "episode": 0, "t": t, "loss": loss, "weight": w, "gripper": g})
    return pd.DataFrame(rows)


def _write_r4(root, weights_seeds=(0,)):
    """The hand-made R4 runs: configs made R4's (act, MT50, 50 demonstrations, 3743 steps), the tar_gentle run with
    the preset's settings, weights for ``weights_seeds`` only, and each run's fit diagnostics in its summary."""
    for (arm, seed), rates in R4_SUCCESS.items():
        objective = "uniform" if arm == "uniform" else "tar"
        rollouts = {task: _RATE[rate] for task, rate in zip(R4_GRIPPER, rates)}
        name = f"{objective}-act-s{seed}-{'cafecafe' if arm == 'tar_gentle' else 'deadbeef'}"
        weights = _r4_weights(arm) if seed in weights_seeds else None
        path = write_run(root, objective, seed, rollouts, policy="act", name=name, steps=3743, weights=weights)
        config = yaml.safe_load((path / "config.yaml").read_text())
        config["data"].update(tasks=["mt50"], n_demos=50)
        config["objective"].update(GENTLE if arm == "tar_gentle" else {"cap": "paper"})
        config.update(logging={"record_episodes": 1}, diagnostics={"train_episodes": 10, "heldout_demos": 3})
        (path / "config.yaml").write_text(yaml.safe_dump(config))
        summary = json.loads((path / "summary.json").read_text())
        w, loss, rho = R4_FIT[(arm, seed)]
        summary["config"] = config
        summary["fit"] = {"alignment": {"bins": 2, "spearman": rho, "weight_by_bin": w, "heldout_loss_by_bin": loss}}
        (path / "summary.json").write_text(json.dumps(summary))


def test_the_r4_command_on_hand_made_runs(tmp_path):
    _write_r4(tmp_path / "runs")
    out = tmp_path / "out"
    assert diag.main(["--regime", "R4", "--runs", str(tmp_path / "runs"), "--out", str(out)]) == 0
    result = diag.diagnose(tmp_path / "runs", label="R4")  # what the command wrote, unrounded (checked below)
    tasks = result.tasks.set_index("task")
    assert tasks["delta"].to_dict() == pytest.approx({"reach": 75.0, "assembly": -25.0, "basketball": 25.0})
    assert tasks["uniform"].to_dict() == pytest.approx({"reach": 25.0, "assembly": 100.0, "basketball": 25.0})
    assert tasks["tar"].to_dict() == pytest.approx({"reach": 100.0, "assembly": 75.0, "basketball": 50.0})
    gentle = result.extra["tasks_tar_gentle"].set_index("task")
    assert gentle["delta"].to_dict() == pytest.approx({"reach": 25.0, "assembly": -25.0, "basketball": 0.0})
    # the weight statistics of seed 0's tar run: switch steps reach t 4, 7 (weight 3), basketball t 2 (weight 2)
    assert tasks["switch_share"].to_dict() == pytest.approx({"reach": 0.2, "assembly": 0.0, "basketball": 0.1})
    assert tasks.loc["reach", "weight_switch"] == pytest.approx(3.0)
    assert tasks.loc["basketball", "weight_switch"] == pytest.approx(2.0)
    assert math.isnan(tasks.loc["assembly", "weight_switch"])  # no switch step
    assert tasks["weight_max"].to_dict() == pytest.approx({"reach": 3.0, "assembly": 1.0, "basketball": 2.0})
    # ESS fraction (sum w)^2 / (T sum w^2): reach 14^2 / (10 x 26), basketball 11^2 / (10 x 13), assembly 1
    assert tasks["weight_ess"].to_dict() == pytest.approx(
        {"reach": 196 / 260, "assembly": 1.0, "basketball": 121 / 130}
    )
    assert tasks["uniform_loss"].to_dict() == pytest.approx(R4_LOSS)
    # Spearman over the 3 tasks (Δ ranks reach 3, assembly 1, basketball 2): switch share, largest weight the same
    # order (+1); ESS the reverse (-1); uniform loss ranks 3, 2, 1: 1 - 6 x 2 / 24 = 0.5, p 2/3 (t = 0.5 sqrt(1 / 0.75)
    # = 1 / sqrt(3) on 1 degree of freedom: 1 - 2 atan(1 / sqrt(3)) / pi); uniform success ranks 1.5, 3, 1.5:
    # -1.5 / sqrt(2 x 1.5) = -sqrt(3) / 2, p 1/3 (t = -sqrt(3)); weight at switches: 2 tasks, no ranking.
    corr = result.extra["correlations"].set_index(["arm", "statistic"])
    tar = corr.loc["tar"]
    assert tar["rho"].to_dict() == pytest.approx(
        {
            "switch_share": 1.0,
            "weight_switch": math.nan,
            "weight_max": 1.0,
            "weight_ess": -1.0,
            "uniform_loss": 0.5,
            "uniform": -math.sqrt(3) / 2,
        },
        nan_ok=True,
    )
    assert tar.loc["weight_switch", "tasks"] == 2 and tar.loc["uniform", "tasks"] == 3
    assert tar.loc["uniform_loss", "p"] == pytest.approx(2 / 3)
    assert tar.loc["uniform", "p"] == pytest.approx(1 / 3)
    # Holm over the 5 p-values (0, 0, 0, 1/3, 2/3): the fourth (5 - 3) x 1/3, the fifth max(2/3, 1 x 2/3)
    assert tar.loc["uniform", "holm_p"] == pytest.approx(2 / 3)
    assert tar.loc["uniform_loss", "holm_p"] == pytest.approx(2 / 3)
    assert tar.loc["switch_share", "holm_p"] == pytest.approx(0.0, abs=1e-12)
    # tar_gentle's weights are all 1: its weight statistics do not rank the tasks
    assert corr.loc[("tar_gentle", "weight_max"), ["rho", "p"]].isna().all()
    assert corr.loc[("tar_gentle", "uniform_loss"), "rho"] == pytest.approx(0.5)
    # the weight over episode time: every seed's summary, mean and sd over the two seeds
    bins = result.extra["bins"].set_index(["arm", "bin"])
    assert bins.loc[("tar", 0), "weight"] == pytest.approx(1.4)
    assert bins.loc[("tar", 0), "weight_sd"] == pytest.approx(0.2 / math.sqrt(2))
    assert bins.loc[("tar", 1), "heldout_loss"] == pytest.approx(0.2)
    assert bins.loc[("tar", 0), "alignment"] == pytest.approx(0.0)  # (+1 - 1) / 2
    assert bins.loc[("uniform", 0), "heldout_loss"] == pytest.approx(0.3) and (bins["seeds"] == 2).all()
    # phases and switches: seed 0 only, said so
    phases_ = result.phases
    assert (phases_["seeds"] == 1).all() and set(phases_["objective"]) == {"uniform", "tar", "tar_gentle"}
    switches = result.switches.set_index(["objective", "at", "seed"])
    # tar at the last step: switch steps weigh (3 + 3 + 2) / 3, the 27 others 1
    assert switches.loc[("tar", "last", "0"), "switch_ratio"] == pytest.approx(8 / 3)
    md = (out / "diagnosis.md").read_text()
    assert "only seed 0 of the 2 keep their recorded weights" in md
    assert "# R4 diagnosis (`act`)" in md and "`tar` higher: reach (+75.0), basketball (+25.0)." in md
    assert "`tar_gentle` lower: assembly (-25.0)." in md
    assert "at Holm p < 0.05: switch_share, weight_max, weight_ess." in md
    for name in ("scatter.png", "bins.png", "weights_time.png"):
        assert (out / name).read_bytes()[:4] == b"\x89PNG", name
    assert result.markdown == md
    assert set(result.csv_texts()) == {f"{n}.csv" for n in ("phases", "switches", "tasks", "tasks_tar_gentle")} | {
        "correlations.csv",
        "bins.csv",
    }
    for name, text in result.csv_texts().items():
        assert (out / name).read_text() == text, name


def test_r4_refusals_name_the_regime_and_what_is_missing(tmp_path):
    _write_r3(tmp_path / "r3")
    with pytest.raises(SystemExit, match=r"no R4 runs in .*r3 \(runs whose config has policy.name act, data.tasks"):
        diag.diagnose(tmp_path / "r3", label="R4")
    _write_r4(tmp_path / "r4", weights_seeds=())
    with pytest.raises(SystemExit, match=r"no R4 seed has weights recorded by every arm at training steps"):
        diag.diagnose(tmp_path / "r4", label="R4")
    with pytest.raises(SystemExit, match="no R3 runs"):
        diag.diagnose(tmp_path / "r4")
    _write_r4(tmp_path / "dims")
    with pytest.raises(SystemExit, match="per-dimension recording is R3's; R4 has none"):
        diag.diagnose(tmp_path / "dims", tmp_path / "dims.csv.gz", label="R4")
    with pytest.raises(SystemExit, match="no regime 'R9'"):
        diag.diagnose(tmp_path / "dims", label="R9")
