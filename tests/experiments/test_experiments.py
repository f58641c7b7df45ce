"""The paper's experiments (``python -m benchmarks.studies paper``) and the report functions they use.

* Statistics (paired t, Table I's paired differences) against hand-computed values: t quantiles from
  a printed table, p-values from the closed forms of Student's t with 1 and 2 degrees of freedom.
* Phases from hand-made gripper signals, weight-mass shares from hand-made weights.
* Every command at the ``ci`` scale (two tasks, 2 steps, one 20-step rollout), end to end on real
  MetaWorld, sharing one output folder and dataset; then a second call that must train nothing.
"""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pandas as pd
import pytest
import yaml
from run_helpers import ROLLOUTS, write_run

from benchmarks.studies import cli, paper
from benchmarks.studies.core import Planner, seed_major
from benchmarks.studies.writers import controls_markdown, pending_lines, table_one_markdown
from tar_rl.report import PHASES, compare, expand_run_dirs, load_run, paired_t, paired_table, phase_labels
from tar_rl.report.figures import (
    plot_critical_windows,
    plot_group_deltas,
    plot_heatmaps,
    plot_lines,
    plot_radar,
    plot_weight_phases,
)
from tar_rl.report.weight_phases import critical_windows, phase_weight_mass
from tar_rl.runs import config_differences

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"

# Two-sided 95% quantiles t_{0.975, df} from a printed table of Student's t.
T_TABLE = {1: 12.706, 2: 4.303, 3: 3.182, 4: 2.776}


def _p_df1(t: float) -> float:
    """Two-sided p of Student's t with 1 df (the Cauchy distribution): 1 - (2 / pi) atan |t|."""
    return 1 - 2 / math.pi * math.atan(abs(t))


def _p_df2(t: float) -> float:
    """Two-sided p of Student's t with 2 df: 1 - |t| / sqrt(t^2 + 2)."""
    return 1 - abs(t) / math.sqrt(t * t + 2)


def main(argv: list[str]) -> int:
    """``python -m benchmarks.studies paper ...``: a stage's name (or ``all``) runs it, other commands as they are."""
    command, rest = argv[0], argv[1:]
    return cli.main(["paper", *(["run", command] if command in paper.STUDY.stages else [command]), *rest])


# -- paired_t ------------------------------------------------------------------------------------------


def test_paired_t_two_pairs():
    # [1, 3]: mean 2, sd sqrt(2), se 1, t = 2 (1 df); CI 2 -+ 12.706.
    s = paired_t([1.0, 3.0])
    assert s["n"] == 2 and s["mean"] == pytest.approx(2.0)
    assert s["std"] == pytest.approx(math.sqrt(2))
    assert s["t"] == pytest.approx(2.0)
    assert s["ci_low"] == pytest.approx(2 - T_TABLE[1], abs=1e-3)
    assert s["ci_high"] == pytest.approx(2 + T_TABLE[1], abs=1e-3)
    assert s["p_value"] == pytest.approx(_p_df1(2.0), abs=1e-9)  # 0.295167


def test_paired_t_three_and_five_pairs():
    # [2, 4, 6]: mean 4, sd 2, se 2 / sqrt(3) = 1.154701, t = 3.464102 (2 df).
    s = paired_t([2.0, 4.0, 6.0])
    se = 2 / math.sqrt(3)
    assert s["std"] == pytest.approx(2.0)
    assert s["t"] == pytest.approx(4 / se)
    assert s["ci_low"] == pytest.approx(4 - T_TABLE[2] * se, abs=1e-3)
    assert s["ci_high"] == pytest.approx(4 + T_TABLE[2] * se, abs=1e-3)
    assert s["p_value"] == pytest.approx(_p_df2(4 / se), abs=1e-9)  # 0.074180
    # [1..5]: mean 3, sd sqrt(2.5), se sqrt(0.5); CI 3 -+ 2.776 * 0.707107 = [1.037, 4.963].
    s = paired_t([1.0, 2.0, 3.0, 4.0, 5.0])
    assert s["ci_low"] == pytest.approx(3 - T_TABLE[4] * math.sqrt(0.5), abs=1e-3)
    assert s["ci_high"] == pytest.approx(3 + T_TABLE[4] * math.sqrt(0.5), abs=1e-3)
    assert 0.01 < s["p_value"] < 0.02  # t = 4.243 with 4 df: between the tabled 3.747 (0.02) and 4.604 (0.01)


def test_paired_t_degenerate_cases():
    one = paired_t([2.5])
    assert one["n"] == 1 and one["mean"] == 2.5
    assert all(math.isnan(one[k]) for k in ("std", "ci_low", "ci_high", "t", "p_value"))
    same = paired_t([1.0, 1.0, 1.0])
    assert (same["ci_low"], same["ci_high"], same["p_value"]) == (1.0, 1.0, 0.0) and same["t"] == math.inf
    zero = paired_t([0.0, 0.0])
    assert zero["p_value"] == 1.0 and math.isnan(zero["t"])
    empty = paired_t([])
    assert empty["n"] == 0 and math.isnan(empty["mean"])
    with pytest.raises(ValueError, match="finite"):
        paired_t([1.0, math.inf])
    with pytest.raises(ValueError, match="confidence"):
        paired_t([1.0, 2.0], confidence=1.5)


# -- paired_table and Table I on synthetic run directories ----------------------------------------------


@pytest.fixture
def sweep(tmp_path):
    """tests/report/test_report.py's four runs (uniform/tar x seeds 0, 1) and a tar seed 2 without a uniform partner."""
    root = tmp_path / "sweep"
    for (objective, seed), rollouts in ROLLOUTS.items():
        write_run(root, objective, seed, rollouts)
    write_run(root, "tar", 2, {"reach": [(False, 100)] * 4, "assembly": [(False, 100)] * 4})
    return [load_run(p) for p in expand_run_dirs([root])]


def _cell(paired, metric, level):
    match = paired[(paired["metric"] == metric) & (paired["level"] == level) & (paired["objective"] == "tar")]
    assert len(match) == 1
    return match.iloc[0]


def test_paired_table_hand_values(sweep):
    paired = paired_table(sweep)
    # Overall success (%): uniform 37.5, 62.5; tar 75, 75 -> deltas 37.5, 12.5: mean 25, sd 17.678, se 12.5,
    # t = 2 (1 df); seed 2 has no uniform run and is not paired.
    c = _cell(paired, "success", "overall")
    assert c["n_pairs"] == 2 and c["seeds"] == "0,1"
    assert c["baseline_mean"] == pytest.approx(50.0) and c["objective_mean"] == pytest.approx(75.0)
    assert c["delta_mean"] == pytest.approx(25.0) and c["delta_std"] == pytest.approx(12.5 * math.sqrt(2))
    assert c["ci_low"] == pytest.approx(25 - T_TABLE[1] * 12.5, abs=0.02)
    assert c["ci_high"] == pytest.approx(25 + T_TABLE[1] * 12.5, abs=0.02)
    assert c["p_value"] == pytest.approx(_p_df1(2.0), abs=1e-9)
    # Easy (reach): uniform 50, 75; tar 100, 75 -> deltas 50, 0: mean 25, se 25, t = 1, p = 0.5.
    e = _cell(paired, "success", "easy")
    assert e["delta_mean"] == pytest.approx(25.0) and e["p_value"] == pytest.approx(0.5)
    # Hard (assembly): uniform 25, 50; tar 50, 75 -> deltas 25, 25: sd 0, the CI is the point, p = 0.
    h = _cell(paired, "success", "hard")
    assert (h["ci_low"], h["ci_high"], h["p_value"]) == (25.0, 25.0, 0.0)
    # NEPS (x 100): uniform 6.1/3 = 203.33, 4.9/5 = 98; tar 3.8/6 = 63.33, 3.5/6 = 58.33 -> mean delta -89.83.
    n = _cell(paired, "neps", "overall")
    assert n["delta_mean"] == pytest.approx(((63.3333 - 203.3333) + (58.3333 - 98.0)) / 2, abs=1e-3)
    md = table_one_markdown(paired)
    assert "+25.00 [-133.83, +183.83]" in md and "| 0.295 |" in md and "| mlp | tar | 2 |" in md
    # Table III pools each objective over all its seeds (tar: 0, 1, 2): easy 100, 75, 0 -> 58.3, sd
    # sqrt((41.67^2 + 16.67^2 + 58.33^2) / 2) = 52.0; hard 50, 75, 0 -> 41.7 ± 38.2; overall 75, 75, 0 -> 50.0 ± 43.3.
    controls = controls_markdown(paired, compare(sweep), "mlp")
    row = "| tar | 3 | 58.3 ± 52.0 | 41.7 ± 38.2 | 50.0 ± 43.3 | +25.00 [-133.83, +183.83] (n=2) | 0.295 |"
    assert row in controls and "| uniform | 2 | 62.5 ± 17.7 | 37.5 ± 17.7 | 50.0 ± 17.7 | - | - |" in controls


def test_paired_table_skips_infinite_neps_pairs(tmp_path):
    root = tmp_path / "r"
    write_run(root, "uniform", 0, {"reach": [(False, 100)] * 4})  # no success: NEPS inf
    write_run(root, "tar", 0, {"reach": [(True, 50)] * 4})
    write_run(root, "uniform", 1, {"reach": [(True, 50)] * 4})
    write_run(root, "tar", 1, {"reach": [(True, 25)] * 4})
    paired = paired_table([load_run(p) for p in expand_run_dirs([root])])
    n = _cell(paired, "neps", "overall")
    assert n["n_pairs"] == 1 and n["seeds"] == "1" and n["delta_mean"] == pytest.approx(-25.0)
    assert _cell(paired, "success", "overall")["n_pairs"] == 2


# -- Phases and critical windows -----------------------------------------------------------------------


def test_phase_labels_hand_made_signals():
    # T = 20, closes at c = 8: w = ceil(2) = 2, k = ceil(3) = 3.
    labels = phase_labels([-1.0] * 8 + [1.0] * 12)
    expected = ["approach"] * 6 + ["contact_onset"] * 4 + ["transport"] * 7 + ["completion"] * 3
    assert list(labels) == expected
    # Never closing (T = 10, k = ceil(1.5) = 2), or closed from the start: no anchor.
    assert list(phase_labels([-1.0] * 10)) == ["approach"] * 8 + ["completion"] * 2
    assert list(phase_labels([1.0] * 10)) == ["approach"] * 8 + ["completion"] * 2
    # Closing at the last step: the onset window [8, 10) leaves no room for completion.
    assert list(phase_labels([-1.0] * 9 + [1.0])) == ["approach"] * 8 + ["contact_onset"] * 2
    # Closing at step 1 with a wide window: the onset window starts at 0.
    assert list(phase_labels([0.0, 1.0, 1.0, 1.0], onset=0.5, completion=0.0)) == ["contact_onset"] * 3 + ["completion"]
    with pytest.raises(ValueError, match="empty"):
        phase_labels([])
    with pytest.raises(ValueError, match="onset"):
        phase_labels([0.0], onset=2.0)


def _weights_rows(task, episode, gripper, weight, loss=None):
    T = len(gripper)
    return pd.DataFrame(
        {
            "step": 10,
            "task": task,
            "episode": episode,
            "t": np.arange(T),
            "loss": np.linspace(0.1, 0.2, T) if loss is None else loss,
            "weight": weight,
            "gripper": gripper,
        }
    )


def test_phase_weight_mass_and_critical_windows():
    grip = np.array([-1.0] * 8 + [1.0] * 12)
    w = np.ones(20)
    w[6:10] = 2.0  # the contact-onset window weighs double: total 16 + 8 = 24
    demo = _weights_rows("pick-place-v3", 0, grip, w)
    flat = _weights_rows("pick-place-v3", 1, grip, np.ones(20))
    reach = _weights_rows("reach-v3", 5, np.full(10, -1.0), np.r_[np.zeros(8), np.ones(2)])
    mass = phase_weight_mass(pd.concat([demo, flat, reach]))
    one = mass[(mass["episode"] == 0)].set_index("phase")
    assert one.loc["approach", "weight_share"] == pytest.approx(6 / 24)
    assert one.loc["contact_onset", "weight_share"] == pytest.approx(8 / 24)
    assert one.loc["transport", "weight_share"] == pytest.approx(7 / 24)
    assert one.loc["completion", "weight_share"] == pytest.approx(3 / 24)
    assert one.loc["contact_onset", "step_share"] == pytest.approx(4 / 20) and one["anchor"].iloc[0] == 8
    windows = critical_windows(mass).set_index("task")
    pp = windows.loc["pick-place-v3"]
    assert pp["demos"] == 2 and pp["with_anchor"] == 2
    # Mean over the two demos of the onset weight share: (8/24 + 4/20) / 2; step share 0.2.
    assert pp["contact_onset_weight"] == pytest.approx((8 / 24 + 0.2) / 2)
    assert pp["contact_onset_ratio"] == pytest.approx((8 / 24 + 0.2) / 2 / 0.2)
    assert pp["peak"] == "contact_onset"
    r = windows.loc["reach-v3"]
    assert r["with_anchor"] == 0 and r["completion_weight"] == pytest.approx(1.0) and r["peak"] == "completion"
    assert math.isnan(r["transport_ratio"])
    with pytest.raises(ValueError, match="no positive weight"):
        phase_weight_mass(_weights_rows("x", 0, grip, np.zeros(20)))


def test_phase_figures_and_curves_are_pngs(tmp_path):
    grip = np.array([-1.0] * 8 + [1.0] * 12)
    w = np.r_[np.full(6, 0.5), np.full(4, 2.5), np.full(10, 0.8)]
    rows = pd.concat([_weights_rows("pick-place-v3", 0, grip, w), _weights_rows("reach-v3", 1, -np.ones(10), 1.0)])
    windows = critical_windows(phase_weight_mass(rows))
    paths = [
        plot_weight_phases(rows, tmp_path / "fig5.png", ["pick-place-v3", "reach-v3"], caption="test"),
        plot_critical_windows(windows, tmp_path / "cw.png", caption="test"),
        plot_lines(
            pd.DataFrame({"objective": ["uniform", "tar"] * 2, "n": [1, 1, 10, 10], "mean": [1, 2, 3, 4], "std": 1.0}),
            tmp_path / "budget.png",
            "n",
            "demos",
            "success",
            "t",
        ),
        plot_heatmaps(
            pd.DataFrame({"g": [1, 2, 1, 2], "w": [3, 3, 5, 5], "cap": "paper", "d": [1.0, -1.0, np.nan, 0.5]}),
            tmp_path / "heat.png",
            "g",
            "w",
            "cap",
            "d",
            "t",
        ),
    ]
    for p in paths:
        assert p.read_bytes()[:8] == PNG_MAGIC
    with pytest.raises(ValueError, match="no weights for task 'push-v3'"):
        plot_weight_phases(rows, tmp_path / "x.png", ["push-v3"])


def test_radar_draws_with_infinite_neps(sweep, tmp_path):
    table = compare(sweep)
    table.loc[table["objective"] == "uniform", "neps_overall_mean"] = math.inf
    assert plot_radar(table, tmp_path / "radar.png").read_bytes()[:8] == PNG_MAGIC
    paired = paired_table(sweep)
    assert plot_group_deltas(paired, tmp_path / "deltas.png").read_bytes()[:8] == PNG_MAGIC
    with pytest.raises(ValueError, match="no paired rows for objective 'shuffle'"):
        plot_group_deltas(paired, tmp_path / "d2.png", "shuffle")
    with pytest.raises(ValueError, match="no policy has both"):
        plot_radar(table[table["objective"] == "tar"], tmp_path / "r2.png")


# -- The commands at the ci scale ------------------------------------------------------------------------


@pytest.fixture(scope="module")
def bench():
    return paper


@pytest.fixture(scope="module")
def ci_out(tmp_path_factory, bench):
    """Every stage at the ci scale once, in one folder (shared dataset and runs), then every report."""
    out = tmp_path_factory.mktemp("paper")
    argv = ["all", "--scale", "ci", "--out", str(out / "res"), "--data-root", str(out / "data")]
    assert main(argv) == 0
    assert main(["table", *argv[1:]]) == 0
    return out / "res", argv


@pytest.mark.slow
def test_ci_scale_writes_every_table_and_figure(ci_out):
    res, _ = ci_out
    expected = {
        "table": [
            "table_I.md",
            "table_I.csv",
            "paired.csv",
            "fig3_success_vs_neps.png",
            "fig3c_group_deltas.png",
            "fig4_radar.png",
        ],
        "controls": ["table_III.md", "table_III.csv", "paired.csv"],
        "critical_windows": ["critical_windows.md", "critical_windows.csv", "critical_windows.png", "fig5_weights.png"],
        "budget": ["budget.md", "budget.csv", "budget.png"],
        "sensitivity": ["sensitivity.md", "sensitivity.csv", "sensitivity.png"],
    }
    for folder, files in expected.items():
        prov = json.loads((res / folder / "provenance.json").read_text())
        assert prov["scale"] == "ci" and prov["cores"] >= 1 and prov["torch"] and prov["hostname"]
        assert prov["command"].startswith("python -m benchmarks.studies paper table --scale ci")
        for name in files:
            path = res / folder / name
            assert path.is_file(), path
            if name.endswith(".png"):
                assert path.read_bytes()[:8] == PNG_MAGIC
            if name.endswith(".md"):
                text = path.read_text()
                assert "Git commit" in text and "Machine" in text and "scale: `ci`" in text
    table = pd.read_csv(res / "table" / "table_I.csv")
    assert sorted(table["objective"]) == ["tar", "uniform"] and set(table["n_seeds"]) == {2}
    controls = pd.read_csv(res / "controls" / "table_III.csv")
    assert set(controls["objective"]) == {
        "uniform",
        "tar",
        "shuffle",
        "random",
        "invert",
        "perturb_high",
        "perturb_low",
    }
    budget = pd.read_csv(res / "budget" / "budget.csv")
    assert sorted(set(budget["n_demos"])) == [1, 2] and set(budget["objective"]) == {"uniform", "tar"}
    windows = pd.read_csv(res / "critical_windows" / "critical_windows.csv")
    assert sorted(windows["task"]) == ["basketball-v3", "reach-v3"]
    assert {f"{p}_weight" for p in PHASES} <= set(windows.columns)
    sens = pd.read_csv(res / "sensitivity" / "sensitivity.csv")
    assert sorted(sens["gamma"]) == [1.0, 2.0] and set(sens["n_pairs"]) == {1}
    assert "eval.seed = 2000" in (res / "sensitivity" / "sensitivity.md").read_text()


@pytest.mark.slow
def test_ci_pairs_differ_only_in_objective_and_tuning_uses_its_own_eval_seed(ci_out):
    res, _ = ci_out
    configs = {}
    for path in (res / "runs").iterdir():
        config = yaml.safe_load((path / "config.yaml").read_text())
        configs[path.name] = config
    protocol = [c for c in configs.values() if c["eval"]["seed"] == 1000 and c["data"]["n_demos"] == 2]
    by_seed = {}
    for c in protocol:
        by_seed.setdefault(c["seed"], {})[c["objective"]["name"]] = c
    tar_params = {"gamma": 1.0, "w_max": 3.0, "eps": 1e-8, "cap": "paper"}  # tar's own, at their defaults
    for seed in (0, 1):
        tar = by_seed[seed]["tar"]
        assert {key: tar["objective"][key] for key in tar_params} == tar_params
        tar = {**tar, "objective": {k: v for k, v in tar["objective"].items() if k not in tar_params}}
        diff = config_differences(by_seed[seed]["uniform"], tar)
        assert diff == ["objective.name: 'uniform' -> 'tar'"], diff
    tuning = [c for c in configs.values() if c["eval"]["seed"] == 2000]
    assert len(tuning) == 3 and {c["objective"]["name"] for c in tuning} == {"uniform", "tar"}


@pytest.mark.slow
def test_ci_second_call_trains_nothing(ci_out, bench, capsys):
    res, argv = ci_out
    before = {p: p.stat().st_mtime_ns for p in (res / "runs").glob("*/summary.json")}
    assert main(["protocol", *argv[1:]]) == 0
    assert main(["budget", *argv[1:]]) == 0
    out = capsys.readouterr().out
    assert "4 runs: 4 finished (skipped), 0 to run" in out
    assert {p: p.stat().st_mtime_ns for p in (res / "runs").glob("*/summary.json")} == before
    assert len(before) == 14  # 4 protocol + 5 controls + 2 budget (1 demo) + 3 sensitivity


def test_dry_run_plans_without_training(bench, tmp_path, capsys):
    out = tmp_path / "res"
    assert main(["all", "--scale", "ci", "--out", str(out), "--data-root", str(tmp_path), "--dry-run"]) == 0
    text = capsys.readouterr().out
    assert "4 runs: 0 finished (skipped), 4 to run" in text  # protocol: 2 objectives x 2 seeds
    assert "7 runs: 0 finished (skipped), 7 to run" in text  # controls: every weighting, 1 seed
    assert "policy=mlp eval.seed=2000 seed=0 objective=tar objective.gamma=2.0" in text
    assert not (out / "runs").exists()


def test_bad_arguments_are_refused_naming_the_choices(bench, tmp_path):
    common = ["--out", str(tmp_path / "o"), "--data-root", str(tmp_path), "--dry-run"]
    with pytest.raises(SystemExit, match=r"--scale='huge' is not valid; choose one of \['ci', 'cpu', 'paper'\]"):
        main(["table", "--scale", "huge", *common])
    with pytest.raises(SystemExit, match=r"not registered policy heads; registered: \[.*'mlp'"):
        main(["protocol", "--scale", "ci", "--families", "nosuchhead", *common])
    with pytest.raises(SystemExit, match="no finished protocol run"):
        main(["table", "--scale", "ci", "--out", str(tmp_path / "o"), "--data-root", str(tmp_path)])
    with pytest.raises(SystemExit, match=r"optim\.stepz"):
        main(["protocol", "--scale", "ci", "--set", "optim.stepz=3", *common])


def test_scales_pair_objectives_and_paper_scale_is_the_papers_protocol(bench, tmp_path):
    sizes = bench.SIZES["paper"]
    assert set(bench.PAPER_FAMILIES) == set(sizes.families) and len(sizes.families) == 5
    cpu = bench.SIZES["cpu"]
    assert len(cpu.scale.seeds) >= 5 and cpu.families == ("mlp",)
    assert cpu.sens_eval_seed != cpu.scale.value("eval.seed") and cpu.scale.value("eval.seed") == "1000"
    one_seed = dataclasses.replace(cpu, scale=dataclasses.replace(cpu.scale, seeds=(0,)))
    specs = [
        s
        for grid in bench.protocol_grids(one_seed)
        for s in seed_major(grid.specs(Planner(one_seed.scale, tmp_path, str(tmp_path))))
    ]
    assert len(specs) == 2
    a, b = specs[0].config, specs[1].config
    # uniform has no parameters and tar has TAR's four, at their defaults: otherwise the pair is the same job
    tar_params = {"gamma": 1.0, "w_max": 3.0, "eps": 1e-8, "cap": "paper"}
    assert {key: b["objective"][key] for key in tar_params} == tar_params
    b_objective = {key: value for key, value in b["objective"].items() if key not in tar_params}
    assert config_differences(a, {**b, "objective": b_objective}) == ["objective.name: 'uniform' -> 'tar'"]
    assert a["eval"]["seed"] == 1000 and a["optim"]["steps"] == 8000 and len(a["data"]["tasks"]) == 8
    c = Planner(sizes.scale, tmp_path, str(tmp_path)).spec("policy=mlp", "objective=tar").config
    assert c["optim"]["steps"] == 100_000 and c["eval"]["rollouts"] == 50 and c["eval"]["seed"] == 1000
    assert c["data"]["tasks"] == ["mt50"]
    assert c["objective"]["start"] == 0.2 and c["objective"]["ramp"] == 0.3


def test_pending_lines_name_each_stage_with_runs_left_and_at_most_four_runs():
    missing = {"placement": [], "perturb": ["a", "b", "c", "d", "e"], "tune": ["x"]}
    assert pending_lines(missing) == [
        "",
        "## Not finished yet",
        "",
        "- perturb: 5 run(s) (a, b, c, d, ...)",
        "- tune: 1 run(s) (x)",
    ]
    assert pending_lines({"placement": []}) == []
