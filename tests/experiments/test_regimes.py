"""The regime study: fit diagnostics on hand-made numbers, Holm and the MDE against hand values, the
commands of ``python -m benchmarks.studies regimes`` at the ci scale, their refusals, and the committed tables."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
from paths import REPO

from benchmarks.studies import cli, compare, records, regimes
from tar_rl import diagnostics
from tar_rl.report import holm, min_detectable_effect

COMMITTED = REPO / "benchmarks" / "results" / "regimes"


def main(args: list[str]) -> int:
    """``python -m benchmarks.studies regimes ...``: a stage's name runs it, other commands as they are."""
    command, rest = args[0], args[1:]
    return cli.main(["regimes", *(["run", command] if command in regimes.STUDY.stages else [command]), *rest])


# -- Diagnostics -------------------------------------------------------------------------------------


def test_rank_correlation_is_one_minus_one_and_spearman_for_a_shuffle():
    x = np.arange(10.0)
    assert diagnostics.rank_correlation(x, x**2) == pytest.approx(1.0)
    assert diagnostics.rank_correlation(x, -3 * x) == pytest.approx(-1.0)
    # a fixed shuffle: rho = 1 - 6 sum d^2 / (n (n^2 - 1)) with the rank differences d by hand
    y = np.array([3, 8, 1, 10, 6, 2, 7, 4, 9, 5], dtype=float)  # ranks of y; x's ranks are 1..10
    d = np.array([3 - 1, 8 - 2, 1 - 3, 10 - 4, 6 - 5, 2 - 6, 7 - 7, 4 - 8, 9 - 9, 5 - 10])
    rho = 1 - 6 * float((d**2).sum()) / (10 * 99)  # sum d^2 = 4+36+4+36+1+16+0+16+0+25 = 138 -> 0.1636
    assert rho == pytest.approx(0.16363636, abs=1e-6)
    assert diagnostics.rank_correlation(x, y) == pytest.approx(rho)
    assert abs(rho) < 0.2
    assert math.isnan(diagnostics.rank_correlation([1, 2, 3], [5, 5, 5]))  # constant side
    assert math.isnan(diagnostics.rank_correlation([1, np.nan, 3], [1, 2, 3]))  # two pairs left


def test_rank_correlation_uses_average_ranks_for_ties():
    # x ranks 1, 2.5, 2.5, 4; y ranks 1..4: Pearson of the ranks by hand = 0.9486833
    got = diagnostics.rank_correlation([1, 2, 2, 3], [1, 2, 3, 4])
    rx, ry = np.array([-1.5, 0, 0, 1.5]), np.array([-1.5, -0.5, 0.5, 1.5])
    assert got == pytest.approx(float((rx * ry).sum() / math.sqrt((rx**2).sum() * (ry**2).sum())))
    assert got == pytest.approx(0.9486833, abs=1e-6)


def _steps(values_by_episode: dict[str, list[float]], gripper=None) -> pd.DataFrame:
    rows = []
    for episode, values in values_by_episode.items():
        T = len(values)
        for t, v in enumerate(values):
            g = -1.0 if gripper is None else gripper[t]
            rows.append({"episode": episode, "t": t, "length": T, "value": v, "gripper": g})
    return pd.DataFrame(rows)


def test_alignment_rises_together_opposite_and_shuffled():
    up = list(np.linspace(0.5, 2.0, 20))
    train = _steps({"a": up, "b": up[::2]})  # episodes of 20 and 10 steps
    rising = _steps({"h": list(np.linspace(0.01, 0.1, 30))})
    falling = _steps({"h": list(np.linspace(0.1, 0.01, 30))})
    assert diagnostics.alignment(train, rising, bins=10)["spearman"] == pytest.approx(1.0)
    assert diagnostics.alignment(train, falling, bins=10)["spearman"] == pytest.approx(-1.0)
    # held-out loss per bin in the shuffled order of the previous test: rho by hand 0.1636
    order = [3, 8, 1, 10, 6, 2, 7, 4, 9, 5]
    shuffled = _steps({"h": [float(order[t // 3]) for t in range(30)]})  # 3 steps per bin
    out = diagnostics.alignment(train, shuffled, bins=10)
    assert out["spearman"] == pytest.approx(0.16363636, abs=1e-6)
    assert out["heldout_loss_by_bin"] == [float(v) for v in order]


def test_binned_means_pool_episodes_and_leave_empty_bins_nan():
    steps = _steps({"a": [1.0, 3.0], "b": [5.0, 7.0, 9.0, 11.0]})
    # bins = 2: a -> t 0 in bin 0, t 1 in bin 1; b -> t 0, 1 in bin 0, t 2, 3 in bin 1
    np.testing.assert_allclose(diagnostics.binned_means(steps, 2), [(1 + 5 + 7) / 3, (3 + 9 + 11) / 3])
    got = diagnostics.binned_means(_steps({"a": [2.0, 4.0]}), 4)  # bins 0 and 2 hold a step
    np.testing.assert_allclose(got, [2.0, np.nan, 4.0, np.nan])


def test_tail_mean_passes_and_phases_by_hand():
    rows = [(s, "train", "uniform_loss", float(s)) for s in range(100, 1001, 100)]
    rows += [(1000, "train", "loss", 99.0), (1000, "eval", "uniform_loss", 99.0)]
    assert diagnostics.tail_mean(rows, "uniform_loss", 1000) == 1000.0  # last 5% = steps 951..1000
    assert diagnostics.tail_mean(rows, "uniform_loss", 1000, fraction=0.25) == pytest.approx((800 + 900 + 1000) / 3)
    assert diagnostics.tail_mean(rows, "nothing", 1000) is None
    assert diagnostics.passes(8000, 64, 16, 2048) == 4000.0
    with pytest.raises(ValueError, match="at least one step"):
        diagnostics.passes(1, 1, 1, 0)
    # 20 steps, gripper closes at t=8: onset window w=2 -> [6, 10); completion k=3 -> [17, 20)
    gripper = [-1.0] * 8 + [1.0] * 12
    values = [float(t) for t in range(20)]
    means = diagnostics.phase_means(_steps({"e": values}, gripper))
    assert means["approach"] == pytest.approx(np.mean(range(0, 6)))
    assert means["contact_onset"] == pytest.approx(np.mean(range(6, 10)))
    assert means["transport"] == pytest.approx(np.mean(range(10, 17)))
    assert means["completion"] == pytest.approx(np.mean(range(17, 20)))


# -- Statistics -------------------------------------------------------------------------------------


def test_holm_against_hand_values():
    # sorted 0.01, 0.03, 0.04 -> 3 x 0.01 = 0.03; 2 x 0.03 = 0.06; max(0.06, 1 x 0.04) = 0.06
    assert holm([0.01, 0.04, 0.03]) == pytest.approx([0.03, 0.06, 0.06])
    got = holm([math.nan, 0.02, 0.5])  # nan is not a test of the family: m = 2
    assert math.isnan(got[0]) and got[1:] == pytest.approx([0.04, 0.5])
    assert holm([0.6, 0.9]) == pytest.approx([1.0, 1.0])  # capped at 1 (2 x 0.6), then monotone


def test_min_detectable_effect_against_t_tables():
    # n = 8 pairs, sd 2: t_{0.975, 7} = 2.365 and t_{0.80, 7} = 0.896 (printed t tables)
    assert min_detectable_effect(2.0, 8) == pytest.approx((2.365 + 0.896) * 2 / math.sqrt(8), abs=2e-3)
    # n = 4, sd 3: t_{0.975, 3} = 3.182, t_{0.80, 3} = 0.978
    assert min_detectable_effect(3.0, 4) == pytest.approx((3.182 + 0.978) * 3 / 2, abs=3e-3)
    assert math.isnan(min_detectable_effect(1.0, 1))


# -- The commands --------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def study(tmp_path_factory, data_root):
    """Every command at the ci scale with one pair per comparison, in the plan's order."""
    out = tmp_path_factory.mktemp("regimes")
    for command in ("r1", "r2-screen", "r3", "r2", "table"):
        code = main([command, "--scale", "ci", "--out", str(out), "--data-root", str(data_root), "--seeds", "0"])
        assert code == 0, command
    return out, data_root


def _summaries(out: Path) -> dict[str, dict]:
    return {p.parent.name: json.loads(p.read_text()) for p in (out / "runs").glob("*/summary.json")}


@pytest.mark.slow
def test_every_regime_runs_at_the_ci_scale_in_pairs(study):
    out, _ = study
    runs = _summaries(out)
    # source + screening + pairs: R1 at two budgets, R2, R3 (one seed each)
    assert len(runs) == 2 + 2 * 4
    source = [s for s in runs.values() if s["config"]["data"]["seed"] == 3000]
    assert len(source) == 1 and source[0]["objective"] == "uniform"
    post = [s for s in runs.values() if s["init"] is not None]
    assert len(post) == 4 and {s["init"]["source"] for s in post} == {source[0]["run_name"]}
    for s in runs.values():
        fit = s["fit"]
        assert fit["passes"] > 0 and fit["heldout"]["episodes"] >= 1 and fit["alignment"]["bins"] == 10
    screened = json.loads((out / "screening.json").read_text())
    assert len(screened["tasks"]) == 2
    r2 = [s for s in runs.values() if s["config"]["data"]["tasks"] == screened["tasks"]]
    assert sorted(s["objective"] for s in r2) == ["tar", "uniform"]
    # pairs differ only in the objective (and so in the run name)
    by_key: dict[str, list[dict]] = {}
    for s in runs.values():
        c = {k: v for k, v in s["config"].items() if k not in ("objective", "run_dir")}
        by_key.setdefault(json.dumps(c, sort_keys=True), []).append(s)
    pairs = [v for v in by_key.values() if len(v) == 2]
    assert len(pairs) == 4 and all({s["objective"] for s in v} == {"uniform", "tar"} for v in pairs)
    md = (out / "decision.md").read_text()
    for regime in ("| R1 |", "| R1-10 |", "| R2 |", "| R3 |"):
        assert regime in md
    assert (out / "fig3_regimes.png").read_bytes()[:4] == b"\x89PNG"


@pytest.mark.slow
def test_second_call_trains_nothing_and_collect_keeps_only_the_source_checkpoint(study, tmp_path, capsys):
    out, data_root = study
    capsys.readouterr()
    assert main(["r3", "--scale", "ci", "--out", str(out), "--data-root", str(data_root), "--seeds", "0"]) == 0
    assert "0 to run" in capsys.readouterr().out
    repo = tmp_path / "repo"
    assert main(["collect", "--scale", "ci", "--out", str(repo), "--from", str(out / "runs")]) == 0
    copied = sorted((repo / "runs").iterdir())
    assert len(copied) == 10
    with_checkpoint = [p.name for p in copied if (p / "checkpoint.pt").exists()]
    source = [n for n, s in _summaries(out).items() if s["config"]["data"]["seed"] == 3000]
    assert with_checkpoint == source
    for p in copied:
        assert (p / "eval_rollouts.csv.gz").is_file() and not (p / "eval_rollouts.csv").exists()
    # the tables computed from the collected copy equal those of the original folder
    shutil.copy(out / "screening.json", repo / "screening.json")
    assert main(["table", "--scale", "ci", "--out", str(repo), "--data-root", str(data_root), "--seeds", "0"]) == 0
    assert (repo / "decision.md").read_text() == (out / "decision.md").read_text()
    assert (repo / "decision.csv").read_text() == (out / "decision.csv").read_text()


@pytest.mark.slow
def test_a_changed_screening_list_is_refused_once_comparisons_started(study, tmp_path):
    out, data_root = study
    copy = tmp_path / "copy"
    shutil.copytree(out, copy, ignore=shutil.ignore_patterns("checkpoint.pt"))
    screening = json.loads((copy / "screening.json").read_text())
    screening["tasks"] = list(reversed(screening["tasks"]))
    (copy / "screening.json").write_text(json.dumps(screening))
    with pytest.raises(SystemExit, match="may not change after comparison runs started"):
        main(["r2", "--scale", "ci", "--out", str(copy), "--data-root", str(data_root), "--seeds", "0"])
    started = json.loads((copy / "r2_started.json").read_text())
    (copy / "r2_started.json").write_text(json.dumps({**started, "tasks": ["reach-v3", "push-v3"]}))
    with pytest.raises(SystemExit, match="The list is fixed once comparison runs start"):
        regimes.write_screening(regimes.SIZES["ci"], SimpleNamespace(run_dir=_screen_dir(out)), copy)


# -- The chunked-heads regimes (R4, R5) ------------------------------------------------------------


@pytest.fixture(scope="module")
def chunked(tmp_path_factory, data_root):
    """R4 and R5 at the ci scale, seed 0 (three arms each), and their table."""
    out = tmp_path_factory.mktemp("chunked")
    for command in ("r4", "r5", "table"):
        args = [command, "--scale", "ci", "--out", str(out), "--data-root", str(data_root), "--seeds", "0"]
        assert main(args) == 0, command
    return out, data_root


@pytest.mark.slow
def test_chunked_regimes_run_at_the_ci_scale_three_arms_a_seed(chunked):
    out, _ = chunked
    runs = _summaries(out)
    assert len(runs) == 2 * 3
    for head in ("act", "flow"):
        mine = [s for s in runs.values() if s["policy"] == head]
        objectives = sorted(
            (
                (s["config"]["objective"].get("gamma"), s["config"]["objective"].get("cap"), s["objective"])
                for s in mine
            ),
            key=str,
        )
        # uniform (no parameters), tar at tar-rl's defaults, the gentle preset (tar at gamma 0.5, exact cap, w_max 1.5)
        assert objectives == [(0.5, "exact", "tar"), (1.0, "paper", "tar"), (None, None, "uniform")]
        configs = [{k: v for k, v in s["config"].items() if k not in ("objective", "run_dir")} for s in mine]
        assert all(c == configs[0] for c in configs)  # the arms of a seed differ only in the objective
    md = (out / "decision.md").read_text()
    for row in ("| R4 tar |", "| R4 tar_gentle |", "| R5 tar |", "| R5 tar_gentle |", "| R4 | act | tar_gentle |"):
        assert row in md
    assert (out / "fig3_chunked.png").read_bytes()[:4] == b"\x89PNG"
    assert (out / "fig_paired.png").read_bytes()[:4] == b"\x89PNG"  # R4 and R5, one seed each: no interval
    assert set(json.loads((out / "chunked_started.json").read_text())) == {"R4", "R5"}


@pytest.mark.slow
def test_a_changed_chunked_plan_is_refused_by_the_run_and_table_commands(chunked, tmp_path):
    out, data_root = chunked
    copy = tmp_path / "copy"
    shutil.copytree(out, copy, ignore=shutil.ignore_patterns("checkpoint.pt"))
    started = json.loads((copy / "chunked_started.json").read_text())
    (copy / "chunked_started.json").write_text(json.dumps({**started, "R4": "0123456789abcdef"}))
    common = ["--scale", "ci", "--out", str(copy), "--data-root", str(data_root), "--seeds", "0"]
    for command in ("r4", "table"):
        with pytest.raises(SystemExit, match="R4's plan changed after its runs started"):
            main([command, *common])
    main(["r5", *common, "--dry-run"])  # R5's plan is unchanged


@pytest.mark.slow
def test_an_arm_missing_a_seed_is_left_out_and_refused_by_the_complete_table(chunked, tmp_path):
    out, data_root = chunked
    copy = tmp_path / "copy"
    shutil.copytree(out, copy, ignore=shutil.ignore_patterns("checkpoint.pt"))
    gentle = next(
        n for n, s in _summaries(copy).items() if s["policy"] == "flow" and s["config"]["objective"]["cap"] == "exact"
    )
    shutil.rmtree(copy / "runs" / gentle)
    common = ["--scale", "ci", "--out", str(copy), "--data-root", str(data_root), "--seeds", "0"]
    with pytest.raises(SystemExit, match=f"R5 misses 1 run\\(s\\) of its plan: {gentle}"):
        main(["table", *common, "--complete"])
    assert main(["table", *common]) == 0
    md = (copy / "decision.md").read_text()
    assert "| R4 tar_gentle |" in md and "| R5 tar" not in md  # R5 has no seed with all three arms
    assert f"- R5: 1 run(s) ({gentle})" in md


def test_collect_keeps_the_weights_of_the_runs_an_analysis_reads_only(tmp_path):
    from tar_rl.recipes import run_name

    src = tmp_path / "src"
    read = []
    for seed in (0, 1):
        run = src / f"run{seed}"
        run.mkdir(parents=True)
        config = {"objective": {"name": "uniform"}, "policy": {"name": "mlp"}, "seed": seed}
        config |= {"data": {"root": str(tmp_path / "data")}, "runs_root": str(src)}  # this machine's folders
        (run / "config.yaml").write_text(json.dumps(config))
        (run / "summary.json").write_text(json.dumps({"finished": True, "seed": seed, "config": config}))
        for name in ("eval_rollouts.csv", "metrics.csv", "weights.csv"):
            (run / name).write_text("a\n1\n")
        read += [run_name(config)] if seed == 0 else []
    names = records.collect(src, tmp_path / "out", keep_weights=read)
    by_seed = {json.loads((tmp_path / "out" / "runs" / n / "summary.json").read_text())["seed"]: n for n in names}
    kept = {seed: sorted(p.name for p in (tmp_path / "out" / "runs" / n).iterdir()) for seed, n in by_seed.items()}
    assert "weights.csv.gz" in kept[0] and "weights.csv.gz" not in kept[1]
    assert "metrics.csv.gz" in kept[1] and "eval_rollouts.csv.gz" in kept[1]
    records.collect(src, tmp_path / "none")  # no run named: no weights, whatever the seed
    assert not list((tmp_path / "none").glob("runs/*/weights.csv.gz"))
    for name in names:  # the copies name the default job's relative folders, not this machine's
        folder = tmp_path / "out" / "runs" / name
        for text in ((folder / "config.yaml").read_text(), (folder / "summary.json").read_text()):
            assert str(tmp_path) not in text and "datasets" in text and "runs" in text


def test_the_weights_kept_are_r3s_and_seed_0_of_each_chunked_arm(tmp_path):
    from benchmarks.studies.core import Planner

    sizes = regimes.SIZES["ci"]
    names = regimes.weights_read(sizes, Planner(sizes.scale, tmp_path, str(tmp_path)))
    r3 = [f"{objective}-mlp-s{seed}" for objective in ("uniform", "tar") for seed in sizes.scale.seeds]
    chunked = [f"{arm}-{head}-s0" for head in ("act", "flow") for arm in ("uniform", "tar", "tar")]  # tar_gentle: tar
    assert sorted(n.rsplit("-", 1)[0] for n in names) == sorted(r3 + chunked)
    assert len(set(names)) == len(names)  # tar_gentle's runs differ from tar's by their settings


def _screen_dir(out: Path) -> Path:
    for name, s in _summaries(out).items():
        if s["config"]["eval"]["seed"] == 2000 and s["config"]["data"]["seed"] == 0:
            return out / "runs" / name
    raise AssertionError("no screening run")


def _run(name, seed, commit, host):
    return SimpleNamespace(name=name, seed=seed, summary={"git_commit": commit, "machine": {"hostname": host}})


def test_pairs_from_mixed_commits_or_machines_are_refused_naming_the_runs():
    compare.check_pairs([_run("u0", 0, "a", "m"), _run("t0", 0, "a", "m"), _run("u1", 1, "b", "n")])
    with pytest.raises(SystemExit, match=r"seed 0 \(u0, t0\) was trained at different commits"):
        compare.check_pairs([_run("u0", 0, "a", "m"), _run("t0", 0, "b", "m")])
    with pytest.raises(SystemExit, match=r"seed 3 \(u3, t3\) was trained at different machines"):
        compare.check_pairs([_run("u3", 3, "a", "m"), _run("t3", 3, "a", "other")])


def test_hardest_tasks_are_the_lowest_success_ties_by_name():
    rows = pd.DataFrame(
        {"task": ["c", "c", "a", "a", "b", "b", "d", "d"], "success": [1, 1, 0, 1, 0, 1, 0, 0]}
    )  # rates: c 1.0, a 0.5, b 0.5, d 0.0
    assert regimes.pick_hardest(rows, 3) == ["d", "a", "b"]


def test_every_committed_run_folder_is_named_by_its_identity():
    import yaml

    from tar_rl.recipes import run_name

    folders = sorted(p for p in (COMMITTED / "runs").iterdir() if p.is_dir())
    assert folders, "no committed run"
    for folder in folders:
        config = yaml.safe_load((folder / "config.yaml").read_text())
        assert folder.name == run_name(config) == json.loads((folder / "summary.json").read_text())["run_name"]


def test_committed_tables_equal_what_the_table_command_computes(tmp_path):
    """The tables under benchmarks/results/regimes are recomputed from its committed runs."""
    assert main(["table", "--tables", str(tmp_path)]) == 0
    for name in ("decision.md", "decision.csv", "groups.csv"):
        if (COMMITTED / name).is_file():
            assert (tmp_path / name).read_text() == (COMMITTED / name).read_text(), name


def _device_run(seed: int, success: float, device: str) -> SimpleNamespace:
    rows = [("overall", "overall", success), ("group", "easy", 0.0)]
    final = pd.DataFrame([{"level": lv, "name": n, "success": v, "fast20": 0.0, "neps": 0.0} for lv, n, v in rows])
    return SimpleNamespace(seed=seed, final=final, summary={"machine": {"device": device}})


def test_the_chunked_differences_per_device_are_the_means_over_each_devices_seeds():
    from benchmarks.studies.regimes_table import by_device, by_device_markdown

    kinds = ["cpu", "cpu", "NVIDIA H200"]
    loaded = {
        "uniform": [_device_run(s, u, k) for s, u, k in zip((0, 1, 4), (0.70, 0.80, 0.60), kinds)],
        "tar": [_device_run(s, t, k) for s, t, k in zip((0, 1, 4), (0.75, 0.78, 0.70), kinds)],
        "tar_gentle": [_device_run(s, t, k) for s, t, k in zip((0, 1, 4), (0.70, 0.90, 0.55), kinds)],
    }
    rows = {(r["regime"], r["device"]): r for r in by_device("R4", loaded)}
    # By hand: tar on the CPU seeds (+5 - 2) / 2 = +1.5, one of two higher; on the GPU seed +10.
    assert rows[("R4 tar", "cpu")]["delta"] == pytest.approx(1.5)
    assert rows[("R4 tar", "cpu")]["higher"] == 1 and rows[("R4 tar", "cpu")]["seeds"] == [0, 1]
    assert rows[("R4 tar", "cpu")]["uniform"] == pytest.approx(75.0)
    assert rows[("R4 tar", "NVIDIA H200")]["delta"] == pytest.approx(10.0)
    assert rows[("R4 tar_gentle", "cpu")]["delta"] == pytest.approx(5.0)
    assert rows[("R4 tar_gentle", "NVIDIA H200")]["delta"] == pytest.approx(-5.0)
    assert "| R4 tar | cpu | 0,1 | 75.0 | +1.50 | 1 of 2 |" in by_device_markdown(list(rows.values()))
    one_kind = {arm: [r for r in runs if r.summary["machine"]["device"] == "cpu"] for arm, runs in loaded.items()}
    assert by_device_markdown(by_device("R4", one_kind)) == ""  # one kind of device: no section


# -- The paired differences at a glance (fig_paired.png) --------------------------------------------------------


def test_the_chunked_paired_rows_are_each_arm_minus_uniform_per_seed():
    from benchmarks.studies.regimes_table import chunked_paired_rows

    loaded = {
        "uniform": [_device_run(0, 0.70, "cpu"), _device_run(1, 0.80, "cpu")],
        "tar": [_device_run(0, 0.75, "cpu"), _device_run(1, 0.78, "cpu")],
        "tar_gentle": [_device_run(0, 0.70, "cpu"), _device_run(1, 0.90, "cpu")],
    }
    rows = chunked_paired_rows({"R4": loaded}, {"R4": "act"})
    # by hand, in points: tar +5, -2; tar_gentle 0, +10
    assert [(r["label"], r["group"], r["seed"]) for r in rows] == [
        ("R4 act: tar", "R4", 0),
        ("R4 act: tar", "R4", 1),
        ("R4 act: tar_gentle", "R4", 0),
        ("R4 act: tar_gentle", "R4", 1),
    ]
    assert [r["delta"] for r in rows] == pytest.approx([5.0, -2.0, 0.0, 10.0])


def test_r6s_rows_are_read_from_its_tables_paired_file(tmp_path):
    from types import SimpleNamespace

    from benchmarks.studies.regimes_table import _r6_source

    ctx = SimpleNamespace(out=tmp_path)
    assert _r6_source(ctx, {}) == []
    (tmp_path / "r6").mkdir()
    (tmp_path / "r6" / "paired.csv").write_text("label,group,seed,delta\nR6 act: shuffle,R6,0,2.5\n")
    assert _r6_source(ctx, {}) == [{"label": "R6 act: shuffle", "group": "R6", "seed": 0, "delta": 2.5}]
