"""R7, TAR for a sampled loss (``benchmarks/studies/flow_signal.py``): the pre-registered selection rule on hand-made
numbers (ties, the 1-point eligibility of per-segment times, candidate (a) planning no R7 run), the plans against
R5's, the stages at the ci scale through the table (the noise analysis as a command, here or in a ``--tree``; the
selection from the committed table; the comparisons, Holm and the per-seed differences against hand-computed
values), the refusals, and the committed records (the plans' digests composed by hand; the selection recomputed from
the committed pilot)."""

from __future__ import annotations

import hashlib
import json
import math
import shutil
from pathlib import Path

import pandas as pd
import pytest
from run_helpers import committed_run

from benchmarks.studies import cli, flow_signal
from benchmarks.studies.flow_signal import select_candidate


def main(argv: list[str]) -> int:
    return cli.main(["flow_signal", *argv])


# -- The selection rule ------------------------------------------------------------------------------------

SAME = {"step": 70.0, "segment": 70.0}


def test_the_rule_takes_the_highest_correlation_of_tars_weights():
    assert select_candidate({"a": 0.1, "b": 0.3, "c": 0.2, "d": 0.25}, SAME, 1.0, 0.02)["candidate"] == "b"
    assert select_candidate({"a": 0.1, "b": 0.3, "c": 0.2, "d": 0.45}, SAME, 1.0, 0.02)["candidate"] == "d"
    # a candidate without a finite correlation is not eligible
    chosen = select_candidate({"a": 0.1, "b": math.nan, "c": 0.2, "d": 0.15}, SAME, 1.0, 0.02)
    assert chosen["candidate"] == "c" and chosen["eligible"] == ["a", "c", "d"]


def test_a_tie_within_two_hundredths_goes_to_the_candidate_that_changes_training_least():
    # 0.30 is exactly 0.02 below the highest, 0.32: a tie, and (a) comes first
    chosen = select_candidate({"a": 0.30, "b": 0.31, "c": 0.32, "d": 0.10}, SAME, 1.0, 0.02)
    assert chosen["candidate"] == "a" and chosen["tied"] == ["a", "b", "c"]
    # 0.299 is not within 0.02 of 0.32; 0.31 is
    assert select_candidate({"a": 0.299, "b": 0.31, "c": 0.32, "d": 0.10}, SAME, 1.0, 0.02)["candidate"] == "b"
    # within 0.02 of the highest, not of a neighbour: 0.28 ties with 0.30 but not with 0.32
    chosen = select_candidate({"a": 0.28, "b": 0.30, "c": 0.32, "d": 0.10}, SAME, 1.0, 0.02)
    assert chosen["candidate"] == "b" and chosen["tied"] == ["b", "c"]
    # (d) ties with (c) and loses the tie
    assert select_candidate({"a": 0.1, "b": 0.1, "c": 0.40, "d": 0.41}, SAME, 1.0, 0.02)["candidate"] == "c"


def test_segment_times_are_eligible_only_within_one_point_of_step_times():
    r = {"a": 0.10, "b": 0.20, "c": 0.15, "d": 0.60}
    # exactly one point below: eligible (64.15 - 1.0 is a little above 63.15 in binary; the rule reads decimals)
    chosen = select_candidate(r, {"step": 64.15, "segment": 63.15}, 1.0, 0.02)
    assert chosen["candidate"] == "d" and chosen["segment_eligible"]
    # above step times: eligible
    assert select_candidate(r, {"step": 70.0, "segment": 75.0}, 1.0, 0.02)["candidate"] == "d"
    # 1.05 points below: not eligible, and (d)'s correlation does not set the highest either
    chosen = select_candidate(r, {"step": 77.15, "segment": 76.10}, 1.0, 0.02)
    assert chosen["candidate"] == "b" and not chosen["segment_eligible"] and chosen["eligible"] == ["a", "b", "c"]
    assert chosen["highest"] == 0.20 and chosen["tied"] == ["b"]


def test_the_candidates_means_over_the_pilots_seeds_from_a_noise_table():
    rows = []
    for seed, shift in ((0, 0.0), (1, 0.2)):
        for times, signal, r in (
            ("step", "loss", 0.1),
            ("step", "action_error", 0.3),
            ("step", "time_normalized", 0.2),
            ("segment", "loss", 0.5),
        ):
            rows.append(
                {"run": f"r{seed}{times}", "head": "flow", "seed": seed, "time_sampling": times, "signal": signal}
                | {"draws": 1, "segments": 10, "steps": 100, "signal_r": r, "top_agree": r}
                | {"weight_r_tar": r + shift, "weight_r_tar_gentle": 0.0}
            )
    table = pd.DataFrame(rows)
    means = flow_signal.candidate_means(table, (0, 1))
    assert means["b"]["weight_r_tar"] == pytest.approx(0.4)  # (0.3 + 0.5) / 2
    assert means["d"]["weight_r_tar"] == pytest.approx(0.6) and means["a"]["signal_r"] == pytest.approx(0.1)
    with pytest.raises(
        SystemExit, match=r"\(c\) time_normalized, step times for seeds \[0\], not the pilot's \[0, 1\]"
    ):
        flow_signal.candidate_means(table.drop(index=[6]), (0, 1))


def test_the_study_reads_the_columns_the_noise_command_writes():
    from benchmarks.analysis import noise

    assert flow_signal.NOISE_COLUMNS == noise.SIGNAL_COLUMNS and flow_signal.NOISE_MEASURES == noise.SIGNAL_MEASURES


# -- The plans ---------------------------------------------------------------------------------------------


def _record(out: Path, key: str) -> None:
    c = flow_signal.BY_KEY[key]
    out.mkdir(parents=True, exist_ok=True)
    record = {"candidate": key, "signal": c.signal, "time_sampling": c.time_sampling, "train_r7": key != "a"}
    (out / "selection.json").write_text(json.dumps(record | {"note": "by hand"}))


def test_candidate_a_plans_no_r7_run(tmp_path, capsys):
    out = tmp_path / "r7"
    _record(out, "a")
    args = ["--scale", "ci", "--out", str(out)]
    assert main(["run", "r7", *args]) == 0
    assert "nothing to run" in capsys.readouterr().out
    assert not (out / "runs").exists() and not (out / "started.json").exists()
    assert main(["plan", *args]) == 0
    printed = capsys.readouterr().out
    assert "pilot: 2 runs, 0 finished" in printed and "r7:" not in printed


@pytest.fixture(scope="module")
def cpu_plans(tmp_path_factory):
    """R7's cpu plans with (b) and with (d) for seeds 0 and 1, the pilot's, and R5's uniform runs, composed once."""
    from benchmarks.studies import regimes

    out = tmp_path_factory.mktemp("cpu") / "r7"
    ctx = cli.context(flow_signal.STUDY, ["plan", "--seeds", "0,1", "--out", str(out)])
    r5 = cli.context(regimes.STUDY, ["plan", "--seeds", "0"])
    return {
        "pilot": flow_signal.pilot_grid(ctx.sizes).specs(ctx.planner),
        "b": flow_signal.r7_grid(ctx.sizes, "b").specs(ctx.planner),
        "d": flow_signal.r7_grid(ctx.sizes, "d").specs(ctx.planner),
        "r5": regimes.chunked_grid(r5.sizes, "R5").specs(r5.planner),
    }


def _diff(a: dict, b: dict, prefix: str = "") -> set[str]:
    keys = set(a) | set(b)
    out = set()
    for k in keys:
        if isinstance(a.get(k), dict) and isinstance(b.get(k), dict):
            out |= _diff(a[k], b[k], f"{prefix}{k}.")
        elif a.get(k) != b.get(k):
            out.add(f"{prefix}{k}")
    return out


def test_the_cpu_plans_are_r5_with_the_candidate(cpu_plans):
    """The pilot: uniform at R5's settings on evaluation seed 2000, seeds 0 and 1, step and segment times; R7 with
    (b): each arm R5's with ``objective.signal=action_error``, with (d): R5's with per-segment times."""
    pilot, r5 = cpu_plans["pilot"], cpu_plans["r5"]
    assert list(pilot) == ["step", "segment"]
    for times, group in pilot.items():
        assert [s.config["seed"] for s in group] == [0, 1]
        for s in group:
            differs = _diff(s.config, r5["uniform"][s.config["seed"]].config) if s.config["seed"] == 0 else None
            if differs is not None:
                expected = {"eval.seed", "runs_root"} | ({"policy.time_sampling"} if times == "segment" else set())
                assert differs == expected
            assert s.config["eval"]["seed"] == 2000 and s.config["policy"]["time_sampling"] == times
    for key, differs in (("b", {"objective.signal", "runs_root"}), ("d", {"policy.time_sampling", "runs_root"})):
        specs = cpu_plans[key]
        assert list(specs) == ["uniform", "tar", "tar_gentle"]
        for arm, group in specs.items():
            assert [s.config["seed"] for s in group] == [0, 1]
            assert _diff(group[0].config, r5[arm][0].config) == differs, (key, arm)
            assert group[0].config["eval"]["seed"] == 1000 and group[0].config["optim"]["steps"] == 3743
    assert flow_signal.SIZES["cpu"].scale.seeds == tuple(range(8))


# -- The stages at the ci scale ----------------------------------------------------------------------------

# Overall success injected into the R7 runs (1 rollout on each of the ci scale's two tasks: 0, 50 or 100%), by
# arm and seed, as (reach, push) successes.
INJECTED = {
    "uniform": {0: (False, False), 1: (True, False)},
    "tar": {0: (True, True), 1: (True, True)},
    "tar_gentle": {0: (True, False), 1: (True, False)},
}


def _r7_runs(out: Path) -> dict[str, dict[int, Path]]:
    """R7's runs (evaluation seed 1000) of ``out`` by arm (``tar`` at gamma 1, ``tar_gentle`` at 0.5) and seed."""
    import yaml

    found: dict[str, dict[int, Path]] = {}
    for run in sorted((out / "runs").iterdir()):
        config = yaml.safe_load((run / "config.yaml").read_text())
        if config["eval"]["seed"] != 1000:
            continue
        objective = config["objective"]
        arm = "tar_gentle" if objective["name"] == "tar" and objective["gamma"] == 0.5 else objective["name"]
        found.setdefault(arm, {})[config["seed"]] = run
    return found


def _inject(out: Path) -> None:
    for arm, by_seed in _r7_runs(out).items():
        for seed, run in by_seed.items():
            rollouts = pd.read_csv(run / "eval_rollouts.csv")
            final = rollouts["step"] == rollouts["step"].max()
            reach, push = INJECTED[arm][seed]
            rollouts.loc[final & (rollouts["task"] == "reach-v3"), "success"] = reach
            rollouts.loc[final & (rollouts["task"] == "push-v3"), "success"] = push
            rollouts.to_csv(run / "eval_rollouts.csv", index=False)


def _tree(tmp: Path) -> tuple[Path, Path]:
    """A checkout stand-in whose python records where it started and its arguments, and fails."""
    tree = tmp / "tree"
    (tree / ".venv" / "bin").mkdir(parents=True)
    (tree / "tar_rl").mkdir()
    started = tmp / "started_in"
    wrapper = tree / ".venv" / "bin" / "python"
    wrapper.write_text(f'#!/bin/sh\npwd > "{started}"\necho "$@" >> "{started}"\nexit 3\n')
    wrapper.chmod(0o755)
    return tree, started


@pytest.fixture(scope="module")
def study(tmp_path_factory, data_root):
    """The pilot (ci: seed 0), ``select`` in a ``--tree`` whose analysis fails, ``select`` twice (the noise table,
    then, with (b)'s correlation raised by hand in the table, the selection), R7 over seeds 0 and 1 with successes
    injected, and the table."""
    tmp = tmp_path_factory.mktemp("flow_signal")
    out = tmp / "r7"
    common = ["--scale", "ci", "--out", str(out), "--data-root", str(data_root)]
    tree, started_in = _tree(tmp)
    assert main(["run", "pilot", *common]) == 0
    with pytest.raises(SystemExit, match=f"the noise analysis failed in {tree}"):
        main(["run", "select", *common, "--tree", str(tree)])
    where, arguments = started_in.read_text().splitlines()
    words = arguments.split()
    assert where == str(tree) and words[:3] == ["-m", "benchmarks.analysis", "noise"]
    assert set(words[words.index("--runs") + 1].split(",")) == {p.name for p in (out / "runs").iterdir()}
    assert words[words.index("--signals") + 1] == "all" and words[words.index("--from") + 1] == str(out / "runs")
    assert not (out / "pilot_noise.csv").exists()
    assert main(["run", "select", *common]) == 0  # the analysis by this Python, in the repository
    assert not (out / "selection.json").exists()  # the table first
    with pytest.raises(SystemExit, match=r"R7 has no selection yet"):
        main(["table", "--complete", *common])
    noise = pd.read_csv(out / "pilot_noise.csv")
    table = noise.copy()
    table.loc[table["signal"] == "action_error", "weight_r_tar"] = 0.9
    table.to_csv(out / "pilot_noise.csv", index=False)
    assert main(["run", "select", *common]) == 0
    assert main(["run", "r7", *common]) == 0
    _inject(out)
    assert main(["table", *common]) == 0
    return out, common, noise


@pytest.mark.slow
def test_select_writes_the_pilots_noise_table_then_the_selection_from_it(study):
    import yaml

    out, _, noise = study
    configs = {p.name: yaml.safe_load((p / "config.yaml").read_text()) for p in (out / "runs").iterdir()}
    pilot = {name for name, config in configs.items() if config["eval"]["seed"] == 2000}
    assert {configs[name]["policy"]["time_sampling"] for name in pilot} == {"step", "segment"}
    assert set(noise["run"]) == pilot
    # every candidate once: three signals on the step run, the loss on the segment run
    measured = list(zip(noise["time_sampling"], noise["signal"], strict=True))
    assert measured == [("step", "loss"), ("step", "action_error"), ("step", "time_normalized"), ("segment", "loss")]
    record = json.loads((out / "selection.json").read_text())
    assert record["candidate"] == "b" and record["signal"] == "action_error" and record["train_r7"]
    assert record["means"]["b"]["weight_r_tar"] == 0.9
    assert record["table_sha256"] == hashlib.sha256((out / "pilot_noise.csv").read_bytes()).hexdigest()
    assert set(json.loads((out / "started.json").read_text())) == {"pilot", "r7"}
    r7 = _r7_runs(out)
    assert {arm: sorted(r) for arm, r in r7.items()} == {"uniform": [0, 1], "tar": [0, 1], "tar_gentle": [0, 1]}
    for by_seed in r7.values():
        for run in by_seed.values():
            assert configs[run.name]["objective"]["signal"] == "action_error"


@pytest.mark.slow
def test_the_table_against_hand_computed_statistics(study):
    """Injected successes (overall, %): uniform 0 and 50, tar 100 and 100, tar_gentle 50 and 50 over seeds 0 and 1.
    tar - uniform: 100, 50 (mean 75, sd 25 sqrt 2, t = 3 on 1 degree of freedom); tar_gentle - uniform: 50, 0 (mean
    25, t = 1). With one degree of freedom t is Cauchy: p = 1 - 2 atan(t) / pi, quantiles tan(pi (q - 1/2))."""
    out, _, _ = study
    rows = {r["comparison"]: r for r in pd.read_csv(out / "decision.csv").to_dict("records")}
    tar, gentle = rows["R7 tar - uniform"], rows["R7 tar_gentle - uniform"]
    p_tar, p_gentle = 1 - 2 * math.atan(3) / math.pi, 1 - 2 * math.atan(1) / math.pi  # 0.2048, 0.5
    se = 25 * math.sqrt(2) / math.sqrt(2)
    assert tar["d_success"] == pytest.approx(75) and gentle["d_success"] == pytest.approx(25)
    assert tar["p_success"] == pytest.approx(p_tar, abs=1e-6) and gentle["p_success"] == pytest.approx(0.5, abs=1e-6)
    # Holm over the two: 2 x 0.2048 = 0.4097 for the smaller, then max(0.4097, 1 x 0.5) = 0.5
    assert tar["holm_p"] == pytest.approx(2 * p_tar, abs=1e-6) and gentle["holm_p"] == pytest.approx(p_gentle, abs=1e-6)
    t975 = math.tan(math.pi * (0.975 - 0.5))
    assert tar["d_success_ci_low"] == pytest.approx(75 - t975 * se, abs=1e-4)
    assert tar["d_success_ci_high"] == pytest.approx(75 + t975 * se, abs=1e-4)
    mde = (t975 + math.tan(math.pi * (0.8 - 0.5))) * se
    assert tar["mde_success"] == pytest.approx(mde, abs=1e-4) and gentle["mde_success"] == pytest.approx(mde, abs=1e-4)
    assert (tar["higher"], gentle["higher"], tar["pairs"]) == (2, 1, 2)
    groups = pd.read_csv(out / "groups.csv")
    hard = groups[(groups["comparison"] == "R7 tar - uniform") & (groups["level"] == "hard")].iloc[0]
    assert hard["delta_mean"] == pytest.approx(100)  # push: 1 - 0 on both seeds
    paired = pd.read_csv(out / "paired.csv").sort_values(["label", "seed"])
    assert paired.to_dict("list") == {
        "label": ["R7 flow: tar", "R7 flow: tar", "R7 flow: tar_gentle", "R7 flow: tar_gentle"],
        "group": ["R7"] * 4,
        "seed": [0, 1, 0, 1],
        "delta": [100.0, 50.0, 50.0, 0.0],
    }
    md = (out / "decision.md").read_text()
    assert "| R7 tar - uniform | 2 | 100.0 / 25.0 | +75.00 [" in md
    assert "Selected: (b) action_error, step times" in md


@pytest.mark.slow
def test_the_regime_tables_paired_figure_reads_r7s_differences(study, tmp_path):
    from benchmarks.studies import regimes_table

    out, _, _ = study
    assert regimes_table.PAIRED_SOURCES[-1].__name__ == "_r7_source"
    ctx = type("Ctx", (), {"out": tmp_path})()
    assert regimes_table.PAIRED_SOURCES[-1](ctx, {}) == []
    shutil.copytree(out, tmp_path / "r7", ignore=shutil.ignore_patterns("runs"))
    rows = regimes_table.PAIRED_SOURCES[-1](ctx, {})
    assert [(r["label"], r["seed"], r["delta"]) for r in rows][:2] == [
        ("R7 flow: tar", 0, 100.0),
        ("R7 flow: tar", 1, 50.0),
    ]


@pytest.mark.slow
def test_refusals_once_r7_started_a_changed_plan_a_missing_run_and_a_mixed_pair(study, tmp_path):
    out, common, _ = study
    copy = tmp_path / "r7"
    shutil.copytree(out, copy, ignore=shutil.ignore_patterns("checkpoint.pt"))
    args = [*common[:2], "--out", str(copy), *common[4:]]
    with pytest.raises(SystemExit, match="R7's runs started with the selection"):
        main(["run", "select", *args])
    started = json.loads((copy / "started.json").read_text())
    (copy / "started.json").write_text(json.dumps({**started, "r7": "0123456789abcdef"}))
    for command in (["run", "r7"], ["table"]):
        with pytest.raises(SystemExit, match="r7's plan changed after its runs started"):
            main([*command, *args])
    (copy / "started.json").write_text(json.dumps(started))
    gentle = _r7_runs(copy)["tar_gentle"][1]
    summary = json.loads((gentle / "summary.json").read_text())
    summary["machine"]["device"] = "NVIDIA H200"
    (gentle / "summary.json").write_text(json.dumps(summary))
    with pytest.raises(SystemExit, match=r"seed 1 \(tar-flow-s1-\w+, uniform-flow-s1-\w+\) was trained at different "):
        main(["table", *args])
    shutil.rmtree(gentle)
    with pytest.raises(SystemExit, match=rf"r7 misses 1 run\(s\) of its plan: {gentle.name}"):
        main(["table", "--complete", *args])


def test_refusals_before_the_pilot_and_the_selection(tmp_path):
    args = ["--scale", "ci", "--out", str(tmp_path / "r7"), "--dry-run"]
    with pytest.raises(SystemExit, match="R7's runs are planned once the selection is recorded"):
        main(["run", "r7", *args])
    with pytest.raises(SystemExit, match=r"the pilot's runs are not all finished \(uniform-flow-s0-"):
        main(["run", "select", *args])
    with pytest.raises(SystemExit, match=r"pilot misses 2 run\(s\) of its plan: uniform-flow-s0-"):
        main(["table", "--complete", "--scale", "ci", "--out", str(tmp_path / "r7")])
    with pytest.raises(SystemExit, match=r"not a checkout of tar-rl with its own \.venv"):
        main(["run", "pilot", *args, "--tree", str(tmp_path)])


# -- The committed records ---------------------------------------------------------------------------------

R7 = cli.RESULTS / "regimes" / "r7"
#: R5's overrides as the harness printed them (the scale's shared ones first), written out by hand.
R5_BASE = [
    *("logging=quiet", "logging.record_episodes=3", "threads=1"),
    *("policy=flow", "data.tasks=[mt50]", "data.n_demos=50", "data.seed=0", "optim.steps=3743"),
    *("eval.rollouts=20", "eval.seed=1000", "logging.record_weights_at=[1872,-1]", "policy.compile=true"),
]


def test_the_committed_plans_are_the_ones_r7s_runs_started_with():
    """``regimes/r7/started.json`` holds the digest of each stage's overrides (the machine's folders left out),
    composed here by hand: the pilot's uniform per time sampling on the tuning seed, seeds 0 and 1; R7's three arms
    with the selected signal, seeds 0-7, each seed's arms in order."""

    def digest(plan: dict) -> str:
        return hashlib.sha256(json.dumps(plan, sort_keys=True).encode()).hexdigest()[:16]

    started = json.loads((R7 / "started.json").read_text())
    tune = ["eval.seed=2000", "objective=uniform"]
    pilot = {
        t: [[*R5_BASE, *tune, f"seed={s}", f"policy.time_sampling={t}"] for s in (0, 1)] for t in ("step", "segment")
    }
    r7 = {
        arm: [[*R5_BASE, f"seed={s}", f"objective={arm}", "objective.signal=action_error"] for s in range(8)]
        for arm in ("uniform", "tar", "tar_gentle")
    }
    assert set(started) <= {"pilot", "r7"}
    assert started["pilot"] == digest(pilot) == "886298723889e9cb"  # recorded when the pilot started, at 511a8f1
    if "r7" in started:
        assert started["r7"] == digest(r7)


def test_the_committed_selection_recomputes_from_the_committed_pilot():
    """``regimes/r7/selection.json`` is the plan's rule applied by hand to the committed noise table (read with
    pandas) and to uniform's success on the tuning seed (the share of successful final rollouts of each pilot run's
    ``eval_rollouts.csv.gz``), and it names the table by its SHA-256."""
    record = json.loads((R7 / "selection.json").read_text())
    table = pd.read_csv(R7 / "pilot_noise.csv")
    assert hashlib.sha256((R7 / "pilot_noise.csv").read_bytes()).hexdigest() == record["table_sha256"]
    flow = table[(table["head"] == "flow") & (table["draws"] == 1)]
    order = {"a": ("step", "loss"), "b": ("step", "action_error"), "c": ("step", "time_normalized")}
    order["d"] = ("segment", "loss")
    weight_r = {}
    for key, (times, signal) in order.items():
        rows = flow[(flow["time_sampling"] == times) & (flow["signal"] == signal)]
        assert sorted(rows["seed"]) == [0, 1], key
        weight_r[key] = rows["weight_r_tar"].mean()
        assert record["means"][key]["weight_r_tar"] == pytest.approx(weight_r[key], abs=1e-9)
    success: dict[str, list[float]] = {"step": [], "segment": []}
    for run in sorted((R7 / "runs").glob("uniform-flow-s*")):
        cfg, final = committed_run(run)
        if cfg["eval"]["seed"] != 2000:
            continue
        assert len(final) == 50 * 20 and cfg["seed"] in (0, 1)
        success[cfg["policy"]["time_sampling"]].append(100 * final["success"].mean())
    assert [len(v) for v in success.values()] == [2, 2]
    step, segment = (sum(v) / 2 for v in success.values())
    assert record["success"]["mean"] == pytest.approx({"step": step, "segment": segment}, abs=1e-9)
    # the rule by hand: (d) only within 1 point of step times; the highest; a tie within 0.02 to the first in order
    eligible = [k for k in "abcd" if k != "d" or segment >= step - 1]
    highest = max(weight_r[k] for k in eligible)
    chosen = next(k for k in eligible if weight_r[k] >= highest - 0.02)
    assert (record["candidate"], record["segment_eligible"]) == (chosen, segment >= step - 1)
    assert (record["signal"], record["time_sampling"], record["train_r7"]) == (*order[chosen][::-1], chosen != "a")
    # what the committed numbers give: step 78.2, segment 74.55, so (d) is out and (b) is highest at 0.466
    assert (chosen, round(step, 2), round(segment, 2)) == ("b", 78.2, 74.55)


def test_r7s_committed_uniform_runs_repeat_r5s_rollouts():
    """R7's uniform runs (``objective.signal=action_error``, which uniform does not read, at 511a8f1 on a format-4
    copy of R4's demonstrations) roll out exactly as R5's uniform runs of the same seed (at 2a4022e, on the format-3
    folder): every final rollout's task, variation, success, steps and rho equal, returns equal to 1e-9."""
    r5 = cli.RESULTS / "regimes" / "runs"
    compared = 0
    for run in sorted((R7 / "runs").glob("uniform-flow-s*")):
        cfg, a = committed_run(run)
        if cfg["eval"]["seed"] != 1000:  # the pilot's runs, on the tuning seed, have no R5 counterpart
            continue
        (twin,) = [p for p in r5.glob(f"uniform-flow-s{cfg['seed']}-*") if committed_run(p)[0]["data"]["n_demos"] == 50]
        b = committed_run(twin)[1]
        assert len(a) == len(b) == 1000, run.name
        for column in ("task", "variation_seed", "variation_index", "success", "steps", "rho"):
            assert a[column].equals(b[column]), (run.name, column)
        assert (a["return"] - b["return"]).abs().max() < 1e-9, run.name
        compared += 1
    assert compared >= 1


def test_the_committed_signal_alone_table_repeats_a_hand_pairing_of_r7s_and_r5s_tar_runs():
    """``signal_alone.csv`` (each R7 TAR arm minus R5's, seeds whose uniform runs roll out alike) against a pairing
    done here from the committed rollouts with yaml, pandas and scipy: arms told by the objective's settings, the
    seeds gated on equal final rollouts, the paired t CI and p from scipy."""
    from scipy import stats

    table = pd.read_csv(R7 / "signal_alone.csv")
    r5 = cli.RESULTS / "regimes" / "runs"

    def arm(cfg) -> str:
        o = cfg["objective"]
        return "tar_gentle" if o["name"] == "tar" and o["w_max"] != 3.0 else o["name"]

    def runs(folder, eval_seed=1000) -> dict:
        out = {}
        for path in sorted(folder.glob("*-flow-s*")):
            cfg, final = committed_run(path)
            if cfg["eval"]["seed"] == eval_seed and cfg["data"]["n_demos"] == 50 and len(final) == 1000:
                out[(arm(cfg), cfg["seed"])] = final
        return out

    new, old = runs(R7 / "runs"), runs(r5)
    alike = {
        s
        for (a, s), f in new.items()
        if a == "uniform"
        and ("uniform", s) in old
        and f[["task", "success", "steps"]].equals(old[("uniform", s)][["task", "success", "steps"]])
    }
    for name in ("tar", "tar_gentle"):
        seeds = sorted(s for (a, s) in new if a == name and (a, s) in old and s in alike)
        deltas = [100 * (new[(name, s)]["success"].mean() - old[(name, s)]["success"].mean()) for s in seeds]
        (row,) = table[table["comparison"] == f"R7 {name} - R5 {name}"].to_dict("records")
        assert row["pairs"] == len(seeds) >= 2
        test = stats.ttest_1samp(deltas, 0.0)
        half = stats.t.ppf(0.975, len(deltas) - 1) * stats.sem(deltas)
        mean = sum(deltas) / len(deltas)
        assert row["d_success"] == pytest.approx(mean, abs=1e-5)
        assert (row["d_success_ci_low"], row["d_success_ci_high"]) == pytest.approx(
            (mean - half, mean + half), abs=1e-5
        )
        assert row["p_success"] == pytest.approx(test.pvalue, abs=1e-5)
        assert row["higher"] == sum(d > 0 for d in deltas)


def test_a_seed_whose_uniform_runs_roll_out_differently_is_not_paired(tmp_path):
    """The gate of the exploratory pairing: one rollout's success flipped in R5's uniform run leaves that seed out
    and names it; the same rollouts pair it."""
    from types import SimpleNamespace

    def run(folder: Path, seed: int, success: list[int], objective: str = "uniform"):
        folder.mkdir(parents=True)
        rows = pd.DataFrame(
            {
                "step": 10,
                "task": ["reach", "push"],
                "variation_seed": [1, 2],
                "variation_index": [0, 1],
                "success": success,
                "steps": [30, 40],
            }
        )
        rows.to_csv(folder / "eval_rollouts.csv", index=False)
        return SimpleNamespace(path=folder, seed=seed, objective=objective)

    r7 = {"uniform": {0: run(tmp_path / "a", 0, [1, 0])}}
    same = {"uniform": {0: run(tmp_path / "b", 0, [1, 0])}}
    flipped = {"uniform": {0: run(tmp_path / "c", 0, [1, 1])}}
    assert flow_signal.signal_alone(r7, same) == ([], [])
    assert flow_signal.signal_alone(r7, flipped) == ([], [0])
