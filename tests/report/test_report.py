"""tar-rl report (tar_rl.report) on synthetic run directories with hand-chosen rollouts.

The run directories are written here, file by file, per the recipe's run-directory format; every
expected number is worked out by hand in the comments.
"""

from __future__ import annotations

import math

import pandas as pd
import pytest
from run_helpers import PNG_MAGIC, ROLLOUTS, F, S, write_run

from tar_rl import report
from tar_rl.report import compare, expand_run_dirs, first_gripper_close, load_run, main, plot_weights


@pytest.fixture
def sweep(tmp_path):
    root = tmp_path / "sweep"
    for (objective, seed), rollouts in ROLLOUTS.items():
        # An earlier evaluation where everything failed: the final one (largest step) must be used.
        early = {t: [(F, 100)] * 4 for t in rollouts} if seed == 0 else None
        write_run(root, objective, seed, rollouts, early=early)
    return root


def load_all(root):
    return [load_run(p) for p in expand_run_dirs([root])]


def row(table, objective, policy="mlp"):
    match = table[(table["objective"] == objective) & (table["policy"] == policy)]
    assert len(match) == 1
    return match.iloc[0]


# ---------------------------------------------------------------- load_run


def test_load_run_recomputes_final_metrics_from_largest_step(sweep):
    run = load_run(sweep / "uniform-mlp-s0-deadbeef")
    assert (run.name, run.objective, run.policy, run.seed, run.finished) == (
        "uniform-mlp-s0-deadbeef",
        "uniform",
        "mlp",
        0,
        True,
    )
    assert run.final_step == 1000 and run.steps == 1000 and run.git_commit == "0123456789abcdef"
    overall = run.final.set_index("name").loc["overall"]
    # uniform seed 0 (see the top): .375 / .35 / 6.1 / 3; the early all-failure evaluation would give 0 / 1 / inf.
    assert overall["success"] == pytest.approx(0.375)
    assert overall["fast20"] == pytest.approx(0.35)
    assert overall["neps"] == pytest.approx(6.1 / 3)
    assert overall["n_rollouts"] == 8
    assert run.eval_settings == {
        "tasks": ("assembly", "reach"),
        "eval.rollouts": 4,
        "eval.seed": 1000,
        "eval.horizon": 100,
    }
    assert run.weights is None and list(run.metrics.columns) == ["step", "phase", "name", "value"]


def test_load_run_notes_summary_disagreeing_with_rollouts(tmp_path):
    records = [{"level": "overall", "name": "overall", "n_tasks": 2, "n_rollouts": 8, "success": 0.99, "fast20": 0.1,
                "neps": "inf"}]  # fmt: skip
    run = load_run(write_run(tmp_path, "tar", 0, ROLLOUTS[("tar", 0)], final_records=records))
    # tar seed 0 recomputed: overall success .75.
    assert any("0.9900" in n and "0.7500" in n for n in run.notes)


# ---------------------------------------------------------------- compare


def test_compare_pools_seeds_in_percent(sweep, capsys):
    table = compare(load_all(sweep))
    assert list(table["objective"]) == ["uniform", "tar"]  # uniform first, then tar
    uni, tar = row(table, "uniform"), row(table, "tar")
    assert uni["n_seeds"] == 2 and uni["seeds"] == "0,1" and tar["n_seeds"] == 2
    # uniform: success 37.5 and 62.5 -> mean 50, sample std 25 / sqrt(2) = 17.678.
    assert uni["success_overall_mean"] == pytest.approx(50.0)
    assert uni["success_overall_std"] == pytest.approx(17.6777, abs=1e-3)
    # Fast20 35 and 25 -> 30, std 10 / sqrt(2); NEPS 203.333 and 98 -> 150.667.
    assert uni["fast20_overall_mean"] == pytest.approx(30.0)
    assert uni["fast20_overall_std"] == pytest.approx(7.0711, abs=1e-3)
    assert uni["neps_overall_mean"] == pytest.approx(150.6667, abs=1e-3)
    # tar: success 75 and 75 -> 75, std 0; Fast20 20 and 25 -> 22.5; NEPS 63.333 and 58.333 -> 60.833.
    assert tar["success_overall_mean"] == pytest.approx(75.0)
    assert tar["success_overall_std"] == pytest.approx(0.0)
    assert tar["fast20_overall_mean"] == pytest.approx(22.5)
    assert tar["neps_overall_mean"] == pytest.approx(60.8333, abs=1e-3)
    assert capsys.readouterr().out == ""  # nothing left out, nothing to note


def test_compare_group_columns(sweep):
    table = compare(load_all(sweep))
    uni, tar = row(table, "uniform"), row(table, "tar")
    # Groups present: easy (reach) and hard (assembly); no medium / very_hard columns.
    assert "success_easy_mean" in table.columns and "neps_hard_std" in table.columns
    assert not any("medium" in c or "very_hard" in c for c in table.columns)
    # easy success: uniform 50 and 75 -> 62.5; tar 100 and 75 -> 87.5.
    assert uni["success_easy_mean"] == pytest.approx(62.5)
    assert tar["success_easy_mean"] == pytest.approx(87.5)
    # hard success: uniform 25 and 50 -> 37.5; tar 50 and 75 -> 62.5.
    assert uni["success_hard_mean"] == pytest.approx(37.5)
    assert tar["success_hard_mean"] == pytest.approx(62.5)
    # easy NEPS: uniform 2.6 / 2 = 130 and 1.9 / 3 = 63.333 -> 96.667; easy Fast20: 20 and 10 -> 15.
    assert uni["neps_easy_mean"] == pytest.approx(96.6667, abs=1e-3)
    assert uni["fast20_easy_mean"] == pytest.approx(15.0)


def test_compare_paired_differences(sweep):
    # A shuffle run with seed 0 (matched by uniform seed 0) and seed 7 (no uniform seed 7): one pair.
    # shuffle seed 0 = tar seed 1's rollouts: success 75, Fast20 25, NEPS 58.333.
    write_run(sweep, "shuffle", 0, ROLLOUTS[("tar", 1)])
    write_run(sweep, "shuffle", 7, ROLLOUTS[("tar", 0)])
    table = compare(load_all(sweep))
    assert list(table["objective"]) == ["uniform", "tar", "shuffle"]
    uni, tar, shuffle = row(table, "uniform"), row(table, "tar"), row(table, "shuffle")
    # tar - uniform: seed 0: 75 - 37.5 = 37.5; seed 1: 75 - 62.5 = 12.5 -> mean 25 over 2 pairs.
    assert tar["n_pairs"] == 2
    assert tar["delta_success"] == pytest.approx(25.0)
    # Fast20: 20 - 35 = -15 and 25 - 25 = 0 -> -7.5; NEPS: 63.333 - 203.333 = -140 and 58.333 - 98 = -39.667 -> -89.833.
    assert tar["delta_fast20"] == pytest.approx(-7.5)
    assert tar["delta_neps"] == pytest.approx(-89.8333, abs=1e-3)
    # shuffle - uniform on seed 0 only: 75 - 37.5 = 37.5.
    assert shuffle["n_pairs"] == 1
    assert shuffle["delta_success"] == pytest.approx(37.5)
    assert uni["n_pairs"] == 0 and math.isnan(uni["delta_success"])


def test_compare_policies_are_separate_and_need_their_own_uniform(tmp_path):
    write_run(tmp_path, "uniform", 0, ROLLOUTS[("uniform", 0)], policy="mlp")
    write_run(tmp_path, "tar", 0, ROLLOUTS[("tar", 0)], policy="mlp")
    write_run(tmp_path, "tar", 0, ROLLOUTS[("tar", 1)], policy="chunk")
    table = compare(load_all(tmp_path))
    assert list(zip(table["policy"], table["objective"])) == [("chunk", "tar"), ("mlp", "uniform"), ("mlp", "tar")]
    # mlp: 75 - 37.5 = 37.5 (one pair); chunk has no uniform run: no pair.
    assert row(table, "tar", "mlp")["delta_success"] == pytest.approx(37.5)
    assert row(table, "tar", "chunk")["n_pairs"] == 0 and math.isnan(row(table, "tar", "chunk")["delta_success"])
    # One seed: no standard deviation.
    assert math.isnan(row(table, "tar", "mlp")["success_overall_std"])


def test_compare_infinite_neps(tmp_path):
    # No success at all: NEPS inf; with a finite seed the mean is inf and the std undefined (nan).
    none = {"reach": [(F, 100)] * 4, "assembly": [(F, 100)] * 4}
    write_run(tmp_path, "uniform", 0, none)
    write_run(tmp_path, "uniform", 1, ROLLOUTS[("uniform", 1)])
    write_run(tmp_path, "tar", 0, ROLLOUTS[("tar", 0)])
    table = compare(load_all(tmp_path))
    uni, tar = row(table, "uniform"), row(table, "tar")
    assert math.isinf(uni["neps_overall_mean"]) and math.isnan(uni["neps_overall_std"])
    # success 0 and 62.5 -> 31.25; tar - uniform on seed 0: NEPS 63.333 - inf = -inf, success 75 - 0 = 75.
    assert uni["success_overall_mean"] == pytest.approx(31.25)
    assert tar["delta_neps"] == -math.inf and tar["delta_success"] == pytest.approx(75.0)
    report.plot_success_vs_neps(table, tmp_path / "fig.png")  # the inf point is left out, without a warning
    assert (tmp_path / "fig.png").read_bytes().startswith(PNG_MAGIC)


def test_compare_leaves_out_unfinished_runs_with_a_note(sweep, capsys):
    write_run(sweep, "shuffle", 0, ROLLOUTS[("tar", 0)], finished=False, name="stopped")
    write_run(sweep, "shuffle", 1, ROLLOUTS[("tar", 0)], finished=None, name="training")
    write_run(sweep, "invert", 0, {}, name="no-eval")  # finished, but no final evaluation rows
    runs = load_all(sweep)
    assert {r.name: r.finished for r in runs if r.objective in ("shuffle", "invert")} == {
        "stopped": False,
        "training": False,
        "no-eval": False,
    }
    table = compare(runs)
    assert list(table["objective"]) == ["uniform", "tar"]
    assert sorted(table.attrs["excluded"]) == ["no-eval", "stopped", "training"]
    out = capsys.readouterr().out
    assert "stopped" in out and "finished: false" in out
    assert "training" in out and "no summary.json" in out
    assert "no-eval" in out and "no final evaluation rows" in out


def test_compare_no_finished_run(tmp_path, capsys):
    write_run(tmp_path, "tar", 0, ROLLOUTS[("tar", 0)], finished=False)
    with pytest.raises(ValueError, match="no finished run"):
        compare(load_all(tmp_path))
    assert "left out" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"horizon": 200}, r"eval\.horizon is 200 in tar-.* but 100 in uniform-"),
        ({"eval_seed": 2000}, r"eval\.seed is 2000 in tar-.* but 1000 in uniform-"),
    ],
)
def test_compare_rejects_different_eval_settings(tmp_path, kwargs, message):
    write_run(tmp_path, "uniform", 0, ROLLOUTS[("uniform", 0)])
    write_run(tmp_path, "tar", 0, ROLLOUTS[("tar", 0)], **kwargs)
    with pytest.raises(ValueError, match=message):
        compare(load_all(tmp_path))


def test_compare_rejects_different_rollouts_and_tasks(tmp_path):
    write_run(tmp_path / "a", "uniform", 0, ROLLOUTS[("uniform", 0)])
    five = {t: [*r, (F, 100)] for t, r in ROLLOUTS[("tar", 0)].items()}
    write_run(tmp_path / "a", "tar", 0, five)
    with pytest.raises(ValueError, match=r"eval\.rollouts is 5 in tar-.* but 4 in uniform-"):
        compare(load_all(tmp_path / "a"))
    write_run(tmp_path / "b", "uniform", 0, ROLLOUTS[("uniform", 0)])
    write_run(tmp_path / "b", "tar", 0, {**ROLLOUTS[("tar", 0)], "basketball": [(S, 50)] * 4})
    with pytest.raises(ValueError, match=r"different task sets.*\['basketball'\]"):
        compare(load_all(tmp_path / "b"))


def test_compare_rejects_two_runs_of_one_seed(tmp_path):
    write_run(tmp_path, "tar", 0, ROLLOUTS[("tar", 0)], name="tar-a")
    write_run(tmp_path, "tar", 0, ROLLOUTS[("tar", 1)], name="tar-b")
    with pytest.raises(ValueError, match=r"seed 0.*tar-a.*tar-b"):
        compare(load_all(tmp_path))


# ---------------------------------------------------------------- bad input


def test_bad_paths_are_rejected_naming_them(tmp_path):
    with pytest.raises(ValueError, match=r"nowhere.*no such directory"):
        load_run(tmp_path / "nowhere")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match=r"empty.*no config.yaml"):
        load_run(tmp_path / "empty")
    with pytest.raises(ValueError, match="holds no run directories"):
        expand_run_dirs([tmp_path / "empty"])


@pytest.mark.parametrize(
    ("file", "content", "message"),
    [
        ("summary.json", "{not json", "summary.json: cannot read"),
        ("summary.json", '{"run_name": "x"}', "summary.json: .*'finished'"),
        ("config.yaml", "objective: [unclosed", "config.yaml: cannot read"),
        ("config.yaml", "- a list\n", "config.yaml: .*mapping"),
        (
            "eval_rollouts.csv",
            "task,group,success,step\nreach,easy,True,5\n",
            r"eval_rollouts.csv: missing .*\['rho'\]",
        ),
        ("eval_rollouts.csv", "task,group,success,rho,step\nreach,easy,True,1.5,5\n", "eval_rollouts.csv: bad .*rho"),
        ("eval_rollouts.csv", "", "eval_rollouts.csv: the file is empty"),
        ("metrics.csv", "step,name\n1,loss\n", "metrics.csv: missing"),
        ("weights.csv", "step,task,t\n1,reach,0\n", r"weights.csv: missing .*'loss'"),
    ],
)
def test_corrupt_files_are_rejected_naming_them(tmp_path, file, content, message):
    path = write_run(tmp_path, "tar", 0, ROLLOUTS[("tar", 0)])
    (path / file).write_text(content)
    with pytest.raises(ValueError, match=message):
        load_run(path)


def test_finished_run_without_metrics_is_rejected(tmp_path):
    path = write_run(tmp_path, "tar", 0, ROLLOUTS[("tar", 0)])
    (path / "metrics.csv").unlink()
    with pytest.raises(ValueError, match=r"missing metrics.csv"):
        load_run(path)


# ---------------------------------------------------------------- sweep folders


def test_sweep_folder_expands_to_its_run_directories(sweep, tmp_path):
    (sweep / "not-a-run").mkdir()  # ignored: neither config.yaml nor summary.json
    single = write_run(tmp_path / "other", "tar", 5, ROLLOUTS[("tar", 0)])
    dirs = expand_run_dirs([single, sweep])
    assert [d.name for d in dirs] == [
        "tar-mlp-s5-deadbeef",
        "tar-mlp-s0-deadbeef",
        "tar-mlp-s1-deadbeef",
        "uniform-mlp-s0-deadbeef",
        "uniform-mlp-s1-deadbeef",
    ]


# ---------------------------------------------------------------- weights figure


def synthetic_weights() -> pd.DataFrame:
    # One demonstration of 20 steps at step 1000 (and an older recording at step 500): weight above 1
    # on t = 3..5 and 12..14, the gripper opens (-1) until t = 7 and closes (+1) from t = 8.
    rows = []
    for step in (500, 1000):
        for t in range(20):
            weight = 2.0 if (3 <= t <= 5 or 12 <= t <= 14) else 0.5
            rows.append((step, "reach", 0, t, 0.1 * weight, weight, 1.0 if t >= 8 else -1.0))
    return pd.DataFrame(rows, columns=["step", "task", "episode", "t", "loss", "weight", "gripper"])


def test_first_gripper_close():
    assert first_gripper_close([-1, -1, 0, 0.5, 1, -1, 1]) == 3  # first step > 0 after one <= 0
    assert first_gripper_close(synthetic_weights()["gripper"].iloc[:20]) == 8
    assert first_gripper_close([1, 1, -1]) is None  # closing from the first step: no onset
    assert first_gripper_close([-1, -1]) is None


def test_plot_weights_writes_png(tmp_path):
    out = plot_weights(synthetic_weights(), tmp_path / "figs" / "w.png", caption="run x | git: abc")
    data = out.read_bytes()
    assert data.startswith(PNG_MAGIC) and len(data) > 1000
    assert [p.name for p in (tmp_path / "figs").iterdir()] == ["w.png"]  # no temporary file left
    with pytest.raises(ValueError, match=r"task 'push'.*\['reach'\]"):
        plot_weights(synthetic_weights(), tmp_path / "x.png", task="push")
    with pytest.raises(ValueError, match=r"step 7.*\[500, 1000\]"):
        plot_weights(synthetic_weights(), tmp_path / "x.png", step=7)


# ---------------------------------------------------------------- main


def test_main_prints_and_writes_files(sweep, tmp_path, capsys):
    (sweep / "tar-mlp-s0-deadbeef" / "weights.csv").write_text(synthetic_weights().to_csv(index=False))
    write_run(sweep, "shuffle", 3, ROLLOUTS[("tar", 0)], finished=False, name="stopped-run")
    out = tmp_path / "out"
    assert main([str(sweep), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "uniform-mlp-s1-deadbeef" in printed and "stopped-run" in printed and "left out" in printed
    assert "62.5" in printed  # uniform seed 1's overall success in the per-run table
    assert "50.0 ± 17.7" in printed  # uniform pooled over seeds
    assert "25.00" in printed  # tar - uniform paired success difference
    files = sorted(p.name for p in out.iterdir())
    assert files == ["comparison.csv", "group_success.png", "success_vs_neps.png", "weights_tar-mlp-s0-deadbeef.png"]
    for name in files[1:]:
        data = (out / name).read_bytes()
        assert data.startswith(PNG_MAGIC) and len(data) > 1000
    table = pd.read_csv(out / "comparison.csv")
    assert list(table["objective"]) == ["uniform", "tar"]
    assert table["success_overall_mean"].tolist() == pytest.approx([50.0, 75.0])
    assert table["n_pairs"].tolist() == [0, 2]


def test_main_default_out_and_errors(sweep, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main([str(sweep / "tar-mlp-s0-deadbeef")]) == 0
    assert (tmp_path / "report" / "comparison.csv").is_file()
    with pytest.raises(SystemExit, match=r"tar-rl report: .*missing.*no such directory"):
        main([str(tmp_path / "missing")])
    write_run(tmp_path / "mixed", "uniform", 0, ROLLOUTS[("uniform", 0)])
    write_run(tmp_path / "mixed", "tar", 0, ROLLOUTS[("tar", 0)], horizon=200)
    with pytest.raises(SystemExit, match=r"eval.horizon"):
        main([str(tmp_path / "mixed")])
    with pytest.raises(SystemExit):
        main([])
    assert "RUN_DIR" in capsys.readouterr().err


def test_main_fails_when_no_run_is_finished(tmp_path, capsys):
    write_run(tmp_path / "runs", "tar", 0, ROLLOUTS[("tar", 0)], finished=False)
    write_run(tmp_path / "runs", "uniform", 0, ROLLOUTS[("uniform", 0)], finished=None)  # still training
    assert main([str(tmp_path / "runs"), "--out", str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith(f"tar-rl report: no finished run among the 2 run(s) of {tmp_path / 'runs'}")
    assert "nothing to compare" in err[-1]


def test_phase_column_labels_each_demonstration_in_time_order_aligned_with_the_rows():
    from tar_rl.report.phases import phase_column

    # Two demonstrations of T = 10, rows shuffled. Episode 0 closes at t 4 (c = 4, w = ceil(1.0) = 1, k = 2):
    # approach t 0-2, contact onset t 3-4, transport t 5-7, completion t 8-9. Episode 1 never closes: approach t 0-7,
    # completion t 8-9.
    rows = [(0, t, 1.0 if t >= 4 else -1.0) for t in range(10)] + [(1, t, -1.0) for t in range(10)]
    order = [13, 4, 0, 19, 7, 2, 9, 11, 5, 17, 1, 8, 3, 15, 6, 10, 12, 14, 16, 18]
    steps = pd.DataFrame([rows[i] for i in order], columns=["episode", "t", "gripper"])
    got = dict(zip(zip(steps["episode"], steps["t"]), phase_column(steps, ["episode"])))
    expected0 = ["approach"] * 3 + ["contact_onset"] * 2 + ["transport"] * 3 + ["completion"] * 2
    assert [got[(0, t)] for t in range(10)] == expected0
    assert [got[(1, t)] for t in range(10)] == ["approach"] * 8 + ["completion"] * 2


def test_label_steps_sorts_and_flags_switches_and_their_neighbours_per_demonstration():
    from tar_rl.report.phases import label_steps

    # Episode 0: gripper -1 -1 1 1 -1 (switches at t 2 and 4); episode 1: 1 1 1 1 1 (none: closed from the start).
    gripper = {0: [-1, -1, 1, 1, -1], 1: [1, 1, 1, 1, 1]}
    steps = pd.DataFrame(
        [(e, t, g) for e in (1, 0) for t, g in reversed(list(enumerate(gripper[e])))],
        columns=["episode", "t", "gripper"],
    )
    df = label_steps(steps, ["episode"], window=1)
    assert df[["episode", "t"]].values.tolist() == [[e, t] for e in (0, 1) for t in range(5)]
    assert df["switch"].tolist() == [False, False, True, False, True] + [False] * 5
    assert df["near_switch"].tolist() == [False, True, True, True, True] + [False] * 5
    assert set(df.columns) >= {"phase", "switch", "near_switch"}


# ---------------------------------------------------------------- paired differences at a glance

# Per-seed paired differences. A: 1, 2, 6 -> mean 3, sd sqrt((4 + 1 + 9) / 2) = sqrt(7), se sqrt(7 / 3); the 97.5%
# t quantile with 2 degrees of freedom is 4.302653 (t tables): CI 3 -+ 4.302653 sqrt(7 / 3). B: -1, -3 -> mean -2,
# sd sqrt(2), se 1, t(0.975, 1) = 12.706205: CI -2 -+ 12.706205. C: one seed, 0: no interval, neither higher nor lower.
PAIRED = pd.DataFrame(
    {
        "label": ["A", "A", "A", "B", "B", "C"],
        "group": ["R4", "R4", "R4", "R5", "R5", "R6"],
        "seed": [0, 1, 2, 0, 1, 3],
        "delta": [1.0, 2.0, 6.0, -1.0, -3.0, 0.0],
    }
)
HALF_A = 4.302653 * math.sqrt(7 / 3)


def test_paired_summary_against_hand_values():
    got = report.paired_summary(PAIRED).set_index("label")
    assert list(got.index) == ["A", "B", "C"]
    assert got["n"].tolist() == [3, 2, 1]
    assert got["mean"].tolist() == pytest.approx([3.0, -2.0, 0.0])
    assert got.loc["A", ["ci_low", "ci_high"]].tolist() == pytest.approx([3 - HALF_A, 3 + HALF_A], abs=1e-5)
    assert got.loc["B", ["ci_low", "ci_high"]].tolist() == pytest.approx([-2 - 12.706205, -2 + 12.706205], abs=1e-5)
    assert math.isnan(got.loc["C", "ci_low"]) and math.isnan(got.loc["C", "ci_high"])
    assert got["higher"].tolist() == [3, 0, 0] and got["lower"].tolist() == [0, 2, 0]
    assert got["seeds"].tolist() == ["0,1,2", "0,1", "3"] and got["group"].tolist() == ["R4", "R5", "R6"]
    with pytest.raises(ValueError, match=r"missing the column\(s\) \['delta'\]"):
        report.paired_summary(PAIRED.drop(columns="delta"))
    with pytest.raises(ValueError, match=r"a seed appears twice in one label: \[\('A', 1\)\]"):
        report.paired_summary(pd.concat([PAIRED, PAIRED.iloc[[1]]]))
    with pytest.raises(ValueError, match="must be finite"):
        report.paired_summary(PAIRED.assign(delta=[1.0, math.inf, 6.0, -1.0, -3.0, 0.0]))


def test_the_paired_figure_draws_its_summary_on_one_axis(tmp_path):
    from tar_rl.report.plots import draw_paired_deltas, new_figure

    fig = new_figure(8.0, 3.0)
    summary = draw_paired_deltas(fig, PAIRED, "Δ success")
    assert len(fig.axes) == 1
    ax = fig.axes[0]
    assert [t.get_text() for t in ax.get_yticklabels()] == [
        "A (3 of 3 higher)",
        "B (0 of 2 higher)",
        "C (0 of 1 higher)",
    ]
    # the means as diamonds at rows 0, -1, -2; the intervals as the thick bars (C has none); the zero line
    means = [line for line in ax.get_lines() if line.get_marker() == "D"]
    assert [line.get_xdata()[0] for line in means] == pytest.approx([3, -2, 0])
    assert [line.get_ydata()[0] for line in means] == [0, -1, -2]
    bars = [line for line in ax.get_lines() if line.get_linewidth() == pytest.approx(2.6)]
    assert [x for line in bars for x in line.get_xdata()] == pytest.approx(
        [3 - HALF_A, 3 + HALF_A, -2 - 12.706205, -2 + 12.706205], abs=1e-5
    )
    assert any(list(line.get_xdata()) == [0.0, 0.0] for line in ax.get_lines())  # axvline at 0
    # every seed's dot: x the difference, y its row spread by seed order
    dots = [c.get_offsets() for c in ax.collections]
    assert [list(d[:, 0]) for d in dots] == [[1.0, 2.0, 6.0], [-1.0, -3.0], [0.0]]
    assert list(dots[0][:, 1]) == pytest.approx([-0.18, 0.0, 0.18]) and list(dots[2][:, 1]) == [-2.0]
    assert summary["mean"].tolist() == pytest.approx([3.0, -2.0, 0.0])
    texts = [t.get_text() for t in ax.texts]
    assert texts[0] == f"+3.00 [{3 - HALF_A:+.2f}, {3 + HALF_A:+.2f}]" and texts[2] == "+0.00"
    out = report.plot_paired_deltas(PAIRED, tmp_path / "figs" / "paired.png", caption="runs x | git: abc")
    assert out.read_bytes()[:8] == PNG_MAGIC
