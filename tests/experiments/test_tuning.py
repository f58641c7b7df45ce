"""TAR's tuning in R3 (``python -m benchmarks.studies tuning``): the plan, the selection rule on hand-made
numbers, and the commands at the ci scale."""

from __future__ import annotations

import json
import math

import pandas as pd
import pytest
from paths import REPO
from run_helpers import ROLLOUTS, write_run

from benchmarks.studies import cli
from benchmarks.studies import tuning as tuning_study

BENCH = REPO / "benchmarks"


@pytest.fixture(scope="module")
def tuning():
    return tuning_study


def main(args: list[str]) -> int:
    """``python -m benchmarks.studies tuning ...``: a stage's name runs it, other commands as they are."""
    command, rest = args[0], args[1:]
    return cli.main(["tuning", *(["run", command] if command in tuning_study.STUDY.stages else [command]), *rest])


def test_the_plan_is_the_pre_registered_grid(tuning):
    cpu = tuning.SIZES["cpu"]
    names = list(tuning.settings(cpu))
    cells = [n for n in names if n.startswith("tar-")]
    assert len(cells) == 12 and names[12:] == ["tar_arm", "tar_dimnorm", "uniform"]
    assert "tar-g1-paper-w3" in cells and "tar-g0.25-exact-w1.5" in cells
    assert cpu.tune_seeds == (0, 1, 2, 3) and cpu.final_seeds == tuple(range(8))
    assert (cpu.tune_eval_seed, cpu.final_eval_seed) == (2000, 1000)
    # R3's settings without its evaluation seed: MT50, 50 demonstrations, 3,743 steps
    assert "data.tasks=[mt50]" in cpu.r3 and "data.n_demos=50" in cpu.r3 and "optim.steps=3743" in cpu.r3
    assert not any(o.startswith("eval.seed=") for o in cpu.r3)


def test_distance_to_the_paper_defaults(tuning):
    d = tuning.distance
    assert d("tar-g1-paper-w3") == (0, 0.0)
    assert d("tar-g0.5-paper-w3") == (1, 1.0)
    assert d("tar-g0.25-paper-w3") == (1, 2.0)
    assert d("tar-g1-exact-w3") == (1, 1.0)
    assert d("tar-g1-paper-w1.5") == (1, 1.0)
    assert d("tar-g0.5-exact-w1.5") == (3, 3.0)


def _success(deltas: dict[str, float]) -> dict[str, dict[int, float]]:
    """Per setting, seeds 0-3 at uniform's values (80, 82, 84, 86) plus the setting's difference."""
    uniform = {0: 80.0, 1: 82.0, 2: 84.0, 3: 86.0}
    return {"uniform": uniform, **{name: {s: v + d for s, v in uniform.items()} for name, d in deltas.items()}}


def test_select_takes_the_highest_mean_paired_difference(tuning):
    success = _success({"tar-g1-paper-w3": -2.0, "tar-g0.5-exact-w1.5": 1.0, "tar_arm": 0.5, "tar_dimnorm": -1.0})
    chosen = tuning.select(success)
    assert chosen["cell"] == "tar-g0.5-exact-w1.5" and chosen["variant"] == "tar_arm"
    assert chosen["deltas"]["tar-g1-paper-w3"] == pytest.approx(-2.0)


def test_a_tie_within_a_quarter_point_goes_to_the_setting_nearest_the_paper(tuning):
    # 1.0 vs 0.8: a tie; g0.5 (one setting changed) is nearer than g0.5 + exact (two)
    success = _success({"tar-g0.5-exact-w3": 1.0, "tar-g0.5-paper-w3": 0.8, "tar-g0.25-paper-w3": 0.9})
    success.update({"tar_arm": success["uniform"], "tar_dimnorm": success["uniform"]})
    assert tuning.select(success)["cell"] == "tar-g0.5-paper-w3"
    # 1.0 vs 0.7: no tie
    success = _success({"tar-g0.5-exact-w3": 1.0, "tar-g0.5-paper-w3": 0.7, "tar_arm": 0, "tar_dimnorm": 0})
    assert tuning.select(success)["cell"] == "tar-g0.5-exact-w3"
    # the variants tie at 0.2 apart: the first listed; 0.3 apart: the better
    for gap, variant in ((0.2, "tar_arm"), (0.3, "tar_dimnorm")):
        success = _success({"tar-g1-paper-w3": 0, "tar_arm": 0.0, "tar_dimnorm": gap})
        assert tuning.select(success)["variant"] == variant


def test_select_refuses_a_setting_without_a_shared_seed(tuning):
    success = _success({"tar-g1-paper-w3": 0, "tar_arm": 0, "tar_dimnorm": 0})
    success["tar_arm"] = {7: 50.0}
    with pytest.raises(SystemExit, match="shares no seed with uniform"):
        tuning.select(success)


def test_the_tuning_table_by_hand(tuning):
    ci = tuning.SIZES["cpu"]
    success = _success({"tar-g1-paper-w3": -2.0, "tar_arm": 0.5, "tar_dimnorm": 1.0})
    success["tar_dimnorm"][2] += 4.0  # differences 1, 1, 5, 1: mean 2
    md, df = tuning.tuning_table(success, ci)
    rows = df.set_index("setting")
    assert rows.loc["tar_dimnorm", "delta"] == pytest.approx(2.0)
    assert rows.loc["tar_dimnorm", "success"] == pytest.approx((81 + 83 + 89 + 87) / 4)
    assert rows.loc["tar-g1-paper-w3", "delta"] == pytest.approx(-2.0)
    assert rows.loc["uniform", "seed3"] == 86.0
    assert "| tar_arm | 83.5 | +0.50" in md


def test_the_fit_section_by_hand(tuning):
    from types import SimpleNamespace

    def run(weight_max, ess, heldout):
        # 100 steps; the metrics at step 100 lie in the last 5%, those at step 50 do not
        rows = [(50, "train", "weight_max", 99.0), (100, "train", "weight_max", weight_max)]
        rows += [(100, "train", "weight_ess", ess)] if ess is not None else []
        metrics = pd.DataFrame(rows, columns=["step", "phase", "name", "value"])
        fit = {"final_uniform_loss": 0.02, "heldout": {"loss": heldout}, "alignment": {"spearman": 0.1}}
        return SimpleNamespace(finished=True, steps=100, summary={"fit": fit}, metrics=metrics)

    # Δ 1, 2, 3, 4; largest weight 4, 3, 2, 1 (rho -1); ESS ranks 1, 2, 4, 3 (rho 1 - 6 x 2 / 60 = 0.8);
    # held-out loss of the fourth setting missing from one of its two runs: the mean of the other run's
    deltas = pd.DataFrame(
        {"setting": ["a", "b", "c", "d", "uniform"], "delta": [1.0, 2.0, 3.0, 4.0, 0.0], "n_pairs": [2, 2, 2, 2, 2]}
    )
    loaded = {
        "a": [run(4.0, 0.1, 0.04)],
        "b": [run(3.0, 0.2, 0.03)],
        "c": [run(2.0, 0.4, 0.02)],
        "d": [run(1.0, 0.3, 0.01), run(1.0, None, float("nan"))],
        "uniform": [run(1.0, 1.0, 0.01)],
    }
    lines, fit = tuning.fit_section(deltas, loaded)
    fit = fit.set_index("setting")
    assert fit.loc["d", "weight_ess"] == pytest.approx(0.3) and fit.loc["d", "heldout_loss"] == pytest.approx(0.01)
    assert fit.loc["a", "weight_max"] == 4.0  # step 50's 99 is outside the last 5%
    text = "\n".join(lines)
    assert "with the largest weight over 4 TAR settings: -1.00" in text
    assert "with the ESS fraction over 4 TAR settings: +0.80" in text
    assert "with the held-out loss over 4 TAR settings: -1.00" in text
    assert "| a | 0.0200 | 0.0400 | +0.10 | 4.00 | 0.10 |" in text
    loaded = {name: [run(2.0, 0.5, 0.02)] for name in deltas["setting"]}  # constant: no correlation is defined
    assert "Spearman" not in "\n".join(tuning.fit_section(deltas, loaded)[0])


def test_the_final_table_by_hand(tuning, tmp_path):
    from tar_rl.report import load_run

    # overall success (run_helpers): uniform 37.5 and 62.5; the cell has tar's rollouts, 75 and 75 (differences
    # 37.5 and 12.5); the variant has uniform's rollouts with the seeds swapped (differences +25 and -25)
    runs = {
        "uniform": [write_run(tmp_path, "uniform", s, ROLLOUTS[("uniform", s)]) for s in (0, 1)],
        "tar-g0.5-paper-w3": [write_run(tmp_path, "tar", s, ROLLOUTS[("tar", s)]) for s in (0, 1)],
        "tar_arm": [write_run(tmp_path, "tar_arm", s, ROLLOUTS[("uniform", 1 - s)]) for s in (0, 1)],
    }
    loaded = {name: [load_run(p) for p in paths] for name, paths in runs.items()}
    selected = {"cell": "tar-g0.5-paper-w3", "variant": "tar_arm"}
    decision = tmp_path / "decision.csv"
    pd.DataFrame(
        [
            {"regime": "R1", "pairs": 8, "success_uniform": 1.0, "success_tar": 1.0, "d_success": 0.0},
            {
                **{"regime": "R3", "pairs": 8, "success_uniform": 88.9, "success_tar": 86.9, "d_success": -2.05},
                **{"d_success_ci_low": -4.17, "d_success_ci_high": 0.07, "p_success": 0.056, "mde_success": 2.9},
            },
        ]
    ).to_csv(decision, index=False)
    reference = tuning.paper_reference(decision)
    md, df = tuning.final_table(loaded, selected, reference, (3, 4))
    rows = df.set_index("role")
    cell, variant, paper = rows.loc["cell"], rows.loc["variant"], rows.loc["tar-rl defaults (R3)"]
    assert (cell.uniform, cell.setting_success, cell.delta) == pytest.approx((50.0, 75.0, 25.0))
    # n = 2: t = 25 / (17.678 / sqrt 2) = 2 with 1 df, p = 1 - 2 atan(2) / pi; the CI is 25 +- t_.975,1 x 12.5
    assert cell.p == pytest.approx(1 - 2 * math.atan(2) / math.pi, abs=1e-6)
    assert (cell.ci_low, cell.ci_high) == pytest.approx((25 - 12.7062 * 12.5, 25 + 12.7062 * 12.5), abs=0.01)
    assert cell.mde == pytest.approx((12.7062 + 1.37638) * 12.5, abs=0.01)  # (t_.975,1 + t_.8,1) sd / sqrt 2
    assert (variant.delta, variant.p) == pytest.approx((0.0, 1.0))
    assert (cell.holm_p, variant.holm_p) == pytest.approx((2 * cell.p, 1.0))  # Holm over the two only
    assert paper.setting == "tar-g1-paper-w3" and (paper.delta, paper.pairs, paper.mde) == (-2.05, 8, 2.9)
    assert math.isnan(paper.holm_p)
    row = "| tar-rl defaults (R3) | tar-g1-paper-w3 | 8 | 88.9 / 86.9 | -2.05 [-4.17, +0.07] | 0.056 | - | 2.90 |"
    assert row in md
    assert "in 3 of 4 seeds" in md
    assert tuning.paper_reference(tmp_path / "none.csv") is None
    pd.DataFrame([{"regime": "R1", "pairs": 8}]).to_csv(decision, index=False)
    assert tuning.paper_reference(decision) is None


def test_uniform_reproduced_counts_the_final_runs_equal_to_r3s(tuning, tmp_path):
    final, r3 = tmp_path / "final", tmp_path / "r3"
    same = write_run(final, "uniform", 0, ROLLOUTS[("uniform", 0)], name="uniform-mlp-s0-aaaa")
    write_run(r3, "uniform", 0, ROLLOUTS[("uniform", 0)], name="uniform-mlp-s0-aaaa")
    other = write_run(final, "uniform", 1, ROLLOUTS[("uniform", 1)], name="uniform-mlp-s1-aaaa")
    write_run(r3, "uniform", 1, ROLLOUTS[("uniform", 0)], name="uniform-mlp-s1-aaaa")  # other rollouts
    alone = write_run(final, "uniform", 2, ROLLOUTS[("uniform", 0)], name="uniform-mlp-s2-aaaa")  # none in R3
    assert tuning.uniform_reproduced([same, other, alone], r3) == (1, 2)


@pytest.mark.slow
def test_the_commands_at_the_ci_scale(tuning, tmp_path, data_root, capsys):
    out = tmp_path / "tuning"
    common = ["--scale", "ci", "--out", str(out), "--data-root", str(data_root)]
    with pytest.raises(SystemExit, match=r"no .*selected\.json yet"):
        main(["final", *common])
    with pytest.raises(SystemExit, match="4 tuning run"):
        main(["select", *common])
    assert main(["tune", *common]) == 0
    summaries = [json.loads(p.read_text()) for p in (out / "runs").glob("*/summary.json")]
    assert len(summaries) == 4 and all(s["config"]["eval"]["seed"] == 2000 for s in summaries)
    assert sorted(s["objective"] for s in summaries) == ["tar", "tar_arm", "tar_dimnorm", "uniform"]
    assert main(["select", *common]) == 0
    selected = json.loads((out / "selected.json").read_text())
    assert selected["cell"] == "tar-g0.5-paper-w3" and selected["variant"] in ("tar_arm", "tar_dimnorm")
    capsys.readouterr()
    assert main(["final", *common, "--dry-run"]) == 0
    plan = capsys.readouterr().out
    assert "3 runs: 0 finished" in plan and plan.count("eval.seed=1000") == 3
    assert main(["table", *common]) == 0
    assert main(["table", *common, "--tables", str(tmp_path / "tables")]) == 0
    assert (tmp_path / "tables" / "tuning.md").read_text() == (out / "tuning.md").read_text()
    table = pd.read_csv(out / "tuning.csv")
    assert sorted(table.setting) == sorted(["tar-g0.5-paper-w3", "tar_arm", "tar_dimnorm", "uniform"])
    assert not (out / "final.md").exists()  # no final run has finished
    # a sweep cut short before uniform's run finished: the table shows the finished settings without a difference
    uniform = next(p for p in (out / "runs").iterdir() if p.name.startswith("uniform-"))
    (uniform / "summary.json").rename(uniform / "summary.json.away")
    assert main(["table", *common, "--tables", str(tmp_path / "partial")]) == 0
    partial = pd.read_csv(tmp_path / "partial" / "tuning.csv").set_index("setting")
    assert (
        partial.loc["tar_arm", "n_pairs"] == 0
        and partial.loc["tar_arm", "success"] == table.set_index("setting").loc["tar_arm", "success"]
    )
    assert "| uniform | - | - | 0 |" in (tmp_path / "partial" / "tuning.md").read_text()


def test_committed_tables_equal_what_the_table_command_computes(tuning, tmp_path):
    """The tables under benchmarks/results/regimes/tuning are recomputed from its committed runs."""
    assert main(["table", "--tables", str(tmp_path)]) == 0
    committed = BENCH / "results" / "regimes" / "tuning"
    for name in ("tuning.md", "tuning.csv", "final.md", "final.csv"):
        assert (tmp_path / name).is_file() == (committed / name).is_file(), name
        if (committed / name).is_file():
            assert (tmp_path / name).read_text() == (committed / name).read_text(), name
