"""The baselines from the literature in R3 (``python -m benchmarks.studies baselines``): the plan, the
reproduction check and the commands at the ci scale."""

from __future__ import annotations

import gzip
import shutil

import pandas as pd
import pytest
from paths import REPO

from benchmarks.studies import baselines as baselines_study
from benchmarks.studies import cli, records

BENCH = REPO / "benchmarks"


@pytest.fixture(scope="module")
def baselines():
    return baselines_study


def main(args: list[str]) -> int:
    """``python -m benchmarks.studies baselines ...``: ``run`` runs the stage, other commands as they are."""
    command, rest = args[0], args[1:]
    return cli.main(["baselines", *(["run", "baselines"] if command == "run" else [command]), *rest])


def _rollouts(path, rows):
    path.mkdir(parents=True, exist_ok=True)
    columns = ["task", "variation_seed", "variation_index", "success", "steps", "step"]
    pd.DataFrame(rows, columns=columns).to_csv(path / "eval_rollouts.csv", index=False)


def test_reproduction_compares_the_final_evaluation_rollout_by_rollout(baselines, tmp_path):
    first = [("reach", 1000, 0, True, 40, 5), ("reach", 1000, 1, False, 500, 5)]
    final = [("reach", 1000, 1, False, 500, 10), ("reach", 1000, 0, True, 40, 10)]
    _rollouts(tmp_path / "a", first + final)
    _rollouts(tmp_path / "b", list(reversed(final)))  # another order, no intermediate evaluation
    assert records.reproduces(tmp_path / "a", tmp_path / "b") == (True, "0 of 2 rollouts differ")
    _rollouts(tmp_path / "c", [("reach", 1000, 0, True, 41, 10), ("reach", 1000, 1, False, 500, 10)])
    assert records.reproduces(tmp_path / "a", tmp_path / "c") == (False, "1 of 2 rollouts differ")
    # a committed run's rollouts are gzip-compressed
    (tmp_path / "d").mkdir()
    with gzip.open(tmp_path / "d" / "eval_rollouts.csv.gz", "wb") as f:
        f.write((tmp_path / "b" / "eval_rollouts.csv").read_bytes())
    assert records.reproduces(tmp_path / "a", tmp_path / "d")[0]
    missing = records.reproduces(tmp_path / "a", tmp_path / "missing")
    assert missing == (False, "one of the two runs has no evaluation")


def test_the_plan_is_every_baseline_at_r3s_settings(baselines, capsys, tmp_path):
    assert baselines.WEIGHTINGS == ("tilted", "truncate", "keyframe", "focal", "dro_time")
    # an empty results folder: the plan lists every run (the committed folder's finished ones are not listed)
    out = ["--out", str(tmp_path), "--data-root", "datasets"]
    assert main(["run", "--dry-run", *out, "--seeds", "0,1"]) == 0
    plan = capsys.readouterr().out
    assert "11 runs" in plan  # uniform's seed 0 again, then 5 baselines x 2 seeds (8 by default)
    lines = [line for line in plan.splitlines() if "to run:" in line]
    assert "objective=uniform" in lines[0] and "seed=0" in lines[0]
    assert all("data.tasks=[mt50]" in line and "eval.seed=1000" in line for line in lines)
    assert [line.split("objective=")[1] for line in lines[1:6]] == list(baselines.WEIGHTINGS)
    with pytest.raises(SystemExit):
        main(["run", "--dry-run", "--weightings", "tilted,tar"])


@pytest.mark.slow
def test_the_commands_at_the_ci_scale(baselines, tmp_path, data_root):
    study = tmp_path / "regimes"
    r3 = ["r3", "--scale", "ci", "--out", str(study), "--data-root", str(data_root), "--seeds", "0"]
    assert cli.main(["regimes", "run", *r3]) == 0
    out = tmp_path / "baselines"
    common = ["--scale", "ci", "--out", str(out), "--regimes", str(study), "--data-root", str(data_root)]
    common += ["--seeds", "0", "--weightings", "tilted,dro_time"]
    with pytest.raises(SystemExit, match="no finished baseline run"):
        main(["table", *common])
    assert main(["run", *common]) == 0
    assert main(["table", *common]) == 0
    assert main(["table", *common, "--tables", str(tmp_path / "tables")]) == 0
    for name in ("table.md", "table.csv", "paired.csv", "fit.csv"):  # --tables writes the same tables elsewhere
        assert (tmp_path / "tables" / name).read_text() == (out / name).read_text(), name
    md = (out / "table.md").read_text()
    assert "R3's committed runs (uniform's seed 0 trained again at the baselines' commit: 0 of" in md
    paired = pd.read_csv(out / "paired.csv")
    overall = paired[(paired.metric == "success") & (paired.level == "overall")].set_index("objective")
    assert set(overall.index) == {"tar", "tilted", "dro_time"}
    assert overall.loc["tar", "holm_p"] != overall.loc["tar", "holm_p"]  # NaN: Holm runs over the baselines only
    # a uniform run that does not reproduce: the baselines pair with the uniform runs trained beside them (here
    # every seed has one), and TAR's committed row is left out; without those runs the table is refused
    committed = next((study / "runs").glob("uniform-*"))
    rollouts = committed / "eval_rollouts.csv"
    df = pd.read_csv(rollouts)
    df.loc[df.index[-1], "steps"] += 1
    df.to_csv(rollouts, index=False)
    assert main(["table", *common]) == 0
    assert "uniform trained beside the baselines; TAR's row left out" in (out / "table.md").read_text()
    assert "tar" not in set(pd.read_csv(out / "paired.csv").objective)
    shutil.rmtree(next((out / "runs").glob("uniform-*")))
    with pytest.raises(SystemExit, match=r"does not reproduce R3's committed run .*run baselines --uniform"):
        main(["table", *common])


def test_committed_tables_equal_what_the_table_command_computes(baselines, tmp_path):
    """The tables under benchmarks/results/regimes/baselines are recomputed from its committed runs and R3's."""
    assert main(["table", "--tables", str(tmp_path)]) == 0
    committed = BENCH / "results" / "regimes" / "baselines"
    for name in ("table.md", "table.csv", "paired.csv", "fit.csv"):
        assert (tmp_path / name).read_text() == (committed / name).read_text(), name


def test_the_fit_table_by_hand(baselines):
    from types import SimpleNamespace

    def run(objective, fit, weights):
        # 200 training steps; weight_max logged every 10 steps: the last 5% (steps 191-200) hold the log at 200
        rows = [(step, "train", "weight_max", w) for step, w in zip(range(10, 201, 10), weights)]
        rows.append((200, "eval", "weight_max", 99.0))  # another phase: not read
        metrics = pd.DataFrame(rows, columns=["step", "phase", "name", "value"])
        return SimpleNamespace(objective=objective, finished=True, steps=200, summary={"fit": fit}, metrics=metrics)

    fit_a = {"final_uniform_loss": 0.02, "heldout": {"loss": 0.03}, "alignment": {"spearman": 0.5}}
    fit_b = {"final_uniform_loss": 0.04, "heldout": {"loss": 0.05}, "alignment": {"spearman": -0.1}}
    runs = [
        run("tilted", fit_a, [9.0] * 18 + [2.0, 4.0]),
        run("tilted", fit_b, [9.0] * 18 + [6.0, 6.0]),
        run("uniform", {}, [1.0] * 20),
    ]
    fit = baselines.fit_table(runs).set_index("objective")
    assert fit.loc["tilted", "runs"] == 2
    assert fit.loc["tilted", "train_loss"] == pytest.approx(0.03)
    assert fit.loc["tilted", "heldout_loss"] == pytest.approx(0.04)
    assert fit.loc["tilted", "alignment"] == pytest.approx(0.2)
    assert fit.loc["tilted", "weight_max"] == pytest.approx((4.0 + 6.0) / 2)  # step 190's 2.0 is not in the last 5%
    assert fit.loc["uniform", "weight_max"] == 1.0
    assert fit.loc["uniform", "train_loss"] != fit.loc["uniform", "train_loss"]  # no fit diagnostics: NaN
    assert fit.loc["tilted", "weight_ess"] != fit.loc["tilted", "weight_ess"]  # not logged: NaN
