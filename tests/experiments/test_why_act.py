"""R6, why TAR helps ``act`` (``benchmarks/studies/why_act.py``): the tuning rule by hand, the controls' weights on a
fixed batch against hand-computed values, the stages at the ci scale through the table command, and the refusals
(pairs of other commits, machines or devices; a changed plan; a missing run)."""

from __future__ import annotations

import json
import math
import shutil
import sys
from pathlib import Path

import pytest
import torch
from run_helpers import committed_run

from benchmarks.studies import cli, compare, why_act
from benchmarks.studies.stages import stage_arms
from benchmarks.studies.why_act import ladder_neighbour, select_rate


def main(study: str, argv: list[str]) -> int:
    return cli.main([study, *argv])


# -- The tuning rule -------------------------------------------------------------------------------------


def test_the_half_decade_ladder_steps_by_about_three():
    assert ladder_neighbour(1e-3, up=True) == 3e-3
    assert ladder_neighbour(3e-3, up=True) == 1e-2
    assert ladder_neighbour(3e-4, up=False) == 1e-4
    assert ladder_neighbour(1e-4, up=False) == 3e-5
    assert ladder_neighbour(0.3, up=True) == 1.0
    with pytest.raises(ValueError, match="not on the half-decade ladder"):
        ladder_neighbour(2e-3, up=True)


def test_the_best_rate_extends_the_grid_only_at_an_edge():
    assert select_rate({3e-4: 60.0, 1e-3: 70.0, 3e-3: 65.0}, 1e-3) == (1e-3, None)
    assert select_rate({3e-4: 60.0, 1e-3: 70.0, 3e-3: 75.0}, 1e-3) == (3e-3, 1e-2)
    assert select_rate({3e-4: 80.0, 1e-3: 70.0, 3e-3: 75.0}, 1e-3) == (3e-4, 1e-4)
    # a tie goes to the rate nearer the reference (log scale): 3e-3 beats 1e-2
    assert select_rate({1e-3: 70.0, 3e-3: 75.0, 1e-2: 75.0}, 1e-3) == (3e-3, None)
    assert select_rate({0.1: 50.0, 0.3: 60.0, 1.0: 70.0}, 1e-3) == (1.0, None)  # no rate above 1


# -- The controls' weights on a fixed batch ----------------------------------------------------------------


def _tar_by_hand(losses: list[float], gamma: float = 1.0) -> list[float]:
    """TAR's weights of one full segment without the cap binding: z-score (population std), softmax at 1 / gamma,
    times the segment length."""
    n = len(losses)
    mean = sum(losses) / n
    std = math.sqrt(sum((x - mean) ** 2 for x in losses) / n)
    e = [math.exp((x - mean) / (std + 1e-8) / gamma) for x in losses]
    return [n * v / sum(e) for v in e]


def test_the_controls_weights_on_a_fixed_segment_against_hand_values():
    from tar_rl.objectives import invert_weights, perturb_mask, shuffle_weights, tar_weights

    x = [0.1, 0.2, 0.3, 0.5]
    losses, valid = torch.tensor([x], dtype=torch.float64), torch.ones(1, 4, dtype=torch.bool)
    big = dict(gamma=1.0, w_max=100.0, cap="exact")  # a cap that never binds: the hand formula holds
    tar = tar_weights(losses, valid, **big)[0].tolist()
    assert tar == pytest.approx(_tar_by_hand(x), rel=1e-9)
    # invert: TAR's construction on the negated losses, so the order of TAR's weights reversed
    inverted = invert_weights(losses, valid, **big)[0].tolist()
    assert inverted == pytest.approx(_tar_by_hand([-v for v in x]), rel=1e-9)
    assert sorted(range(4), key=lambda i: inverted[i]) == sorted(range(4), key=lambda i: -tar[i])
    # shuffle: the segment's multiset of TAR's weights at other times
    shuffled = shuffle_weights(losses, valid, generator=torch.Generator().manual_seed(3), **big)[0].tolist()
    assert sorted(shuffled) == pytest.approx(sorted(tar), rel=1e-12)
    # perturb: a quarter of 4 valid steps is one step, the highest-loss one (index 3) or the lowest (index 0)
    high = perturb_mask(losses, valid, fraction=0.25, which="high")[0].tolist()
    low = perturb_mask(losses, valid, fraction=0.25, which="low")[0].tolist()
    assert high == [False, False, False, True] and low == [True, False, False, False]


# -- Pairs -------------------------------------------------------------------------------------------------


def _run(name, seed, commit="a", host="vm", device="cpu"):
    from types import SimpleNamespace

    machine = {"hostname": host, "device": device}
    return SimpleNamespace(name=name, seed=seed, summary={"git_commit": commit, "machine": machine})


def test_a_pair_from_another_device_on_the_same_host_is_refused_naming_the_runs():
    compare.check_pairs([_run("tar4", 4), _run("shuffle4", 4)])
    with pytest.raises(SystemExit, match=r"seed 4 \(tar4, shuffle4\) was trained at different devices"):
        compare.check_pairs([_run("tar4", 4, device="NVIDIA H200"), _run("shuffle4", 4)])


# -- The stages at the ci scale ----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def study(tmp_path_factory, data_root):
    """R4 at the ci scale (seed 0), then R6's placement (seeds 0 and 1: seed 0 reuses R4's uniform and tar, seed 1
    trains them), the tuning grid and its table, in ``<out>/r6``."""
    out = tmp_path_factory.mktemp("regimes")
    common = ["--scale", "ci", "--data-root", str(data_root)]
    assert main("regimes", ["run", "r4", "--out", str(out), "--seeds", "0", *common]) == 0
    r6 = out / "r6"
    for stage in ("placement", "tune"):
        assert main("why_act", ["run", stage, "--out", str(r6), "--seeds", "0,1", *common]) == 0
    assert main("why_act", ["table", "--out", str(r6), "--seeds", "0,1", *common]) == 0
    return out, r6, common


def _names(folder: Path) -> set[str]:
    return {p.name for p in (folder / "runs").iterdir() if (p / "summary.json").is_file()}


@pytest.mark.slow
def test_placement_reuses_r4s_pairs_where_they_match_and_trains_the_rest(study):
    out, r6, _ = study
    assert {n.split("-s")[0] for n in _names(out)} == {"uniform-act", "tar-act"}  # R4's three arms (and tar_gentle)
    for arm in ("uniform", "tar"):
        assert set(_arm_runs(out, arm)) == {0} and set(_arm_runs(r6, arm, eval_seed=1000)) == {1}
    for arm in ("shuffle", "random", "invert"):
        assert set(_arm_runs(r6, arm)) == {0, 1}
    assert set(_arm_runs(r6, "uniform", eval_seed=2000)) == {0}  # the tuning grid's runs
    assert set(json.loads((r6 / "started.json").read_text())) == {"placement", "tune"}


def _success(run_dir: Path) -> float:
    summary = json.loads((run_dir / "summary.json").read_text())
    return 100 * next(f["success"] for f in summary["final"] if f["level"] == "overall")


def _arm_runs(folder: Path, arm: str, eval_seed: int | None = None) -> dict[int, Path]:
    """The runs of ``arm`` in ``folder`` by seed (``tar`` at tar-rl's defaults: gamma 1, not the gentle preset;
    ``eval_seed``: only the runs evaluated on that seed)."""
    import yaml

    out = {}
    for name in _names(folder):
        config = yaml.safe_load((folder / "runs" / name / "config.yaml").read_text())
        objective = config["objective"]
        if eval_seed is not None and config["eval"]["seed"] != eval_seed:
            continue
        if objective["name"] == arm and not (arm == "tar" and objective.get("gamma") != 1.0):
            out[config["seed"]] = folder / "runs" / name
    return out


@pytest.mark.slow
def test_the_table_holds_every_placement_comparison_and_the_tuning_grid(study):
    import pandas as pd

    out, r6, _ = study
    md = (r6 / "decision.md").read_text()
    for label in ("R6 tar - shuffle", "R6 tar - random", "R6 tar - invert", "R6 shuffle - uniform"):
        assert f"| {label} | 2 |" in md
    assert "| R6 perturb_low - perturb_high |" not in md  # not run
    tuning = json.loads((r6 / "tuning.json").read_text())
    assert f"Best rate {tuning['best']:g}" in md
    assert "- perturb: 4 run(s)" in md  # the perturbation arms of seeds 0 and 1
    # the row's Δ is the mean over seeds of T - B, recomputed from the runs' summaries (seed 0's tar is R4's)
    tar = _arm_runs(out, "tar") | _arm_runs(r6, "tar", eval_seed=1000)
    shuffle = _arm_runs(r6, "shuffle")
    assert set(tar) == set(shuffle) == {0, 1}
    by_hand = sum(_success(tar[s]) - _success(shuffle[s]) for s in (0, 1)) / 2
    rows = {r["comparison"]: r for r in pd.read_csv(r6 / "decision.csv").to_dict("records")}
    assert rows["R6 tar - shuffle"]["d_success"] == pytest.approx(by_hand, abs=1e-6)
    assert rows["R6 tar - shuffle"]["pairs"] == 2
    # paired.csv (the regime study's paired figure reads it): each control minus the seed's uniform, per seed
    uniform = _arm_runs(out, "uniform") | _arm_runs(r6, "uniform", eval_seed=1000)
    paired = pd.read_csv(r6 / "paired.csv")
    mine = paired[paired["label"] == "R6 act: shuffle"].sort_values("seed")
    assert mine["seed"].tolist() == [0, 1]
    by_hand = [_success(shuffle[s]) - _success(uniform[s]) for s in (0, 1)]
    assert mine["delta"].tolist() == pytest.approx(by_hand, abs=1e-9)


@pytest.mark.slow
def test_a_changed_plan_a_missing_run_and_a_mixed_pair_are_refused(study, tmp_path):
    out, _, common = study
    copy = tmp_path / "regimes"
    shutil.copytree(out, copy, ignore=shutil.ignore_patterns("checkpoint.pt"))
    c6 = copy / "r6"
    args = ["--out", str(c6), "--seeds", "0,1", *common]
    with pytest.raises(SystemExit, match=r"perturb misses 4 run\(s\) of its plan: perturb_high-act-s0"):
        main("why_act", ["table", "--complete", *args])
    started = json.loads((c6 / "started.json").read_text())
    (c6 / "started.json").write_text(json.dumps({**started, "placement": "0123456789abcdef"}))
    for command in (["run", "placement"], ["table"]):
        with pytest.raises(SystemExit, match="placement's plan changed after its runs started"):
            main("why_act", [*command, *args])
    (c6 / "started.json").write_text(json.dumps(started))
    shuffle = next(n for n in _names(c6) if n.startswith("shuffle") and "-s1-" in n)
    summary_path = c6 / "runs" / shuffle / "summary.json"
    summary = json.loads(summary_path.read_text())
    summary["machine"]["device"] = "NVIDIA H200"
    summary_path.write_text(json.dumps(summary))
    with pytest.raises(SystemExit, match=rf"seed 1 \(tar-act-s1-\w+, {shuffle}\) was trained at different devices"):
        main("why_act", ["table", *args])


@pytest.mark.slow
def test_a_tree_trains_with_that_checkouts_python_in_its_folder(study, tmp_path):
    """``--tree``: the runs start as ``TREE/.venv/bin/python -m tar_rl train`` in TREE (here a wrapper that runs this
    repository's code and records where it started); the planned run folder is checked after training."""
    out, _, common = study
    repo = Path(__file__).resolve().parents[2]
    tree = tmp_path / "tree"
    (tree / ".venv" / "bin").mkdir(parents=True)
    (tree / "tar_rl").mkdir()
    started = tmp_path / "started_in"
    wrapper = tree / ".venv" / "bin" / "python"
    wrapper.write_text(f'#!/bin/sh\npwd > "{started}"\ncd "{repo}" && exec "{sys.executable}" "$@"\n')
    wrapper.chmod(0o755)
    copy = tmp_path / "regimes"
    shutil.copytree(out, copy, ignore=shutil.ignore_patterns("checkpoint.pt"))
    args = ["--out", str(copy / "r6"), "--seeds", "0", *common, "--tree", str(tree)]
    assert main("why_act", ["run", "perturb", *args]) == 0
    assert started.read_text().strip() == str(tree)
    assert {n.split("-act-")[0] for n in _names(copy / "r6") if "-s0-" in n} >= {"perturb_high", "perturb_low"}
    with pytest.raises(SystemExit, match=r"not a checkout of tar-rl with its own \.venv"):
        main("why_act", ["run", "perturb", "--out", str(copy / "r6"), *common, "--tree", str(tmp_path)])


def test_the_tuned_pair_waits_for_the_tuning_record(tmp_path):
    with pytest.raises(SystemExit, match="the tuned pair is planned once the tuning grid is complete"):
        main("why_act", ["run", "tuned", "--scale", "ci", "--out", str(tmp_path / "r6"), "--dry-run"])


@pytest.fixture(scope="module")
def cpu_placement():
    """R6's cpu plan of the placement stage for seeds 0 (R4's CPU seed) and 4 (R4's H200 seed), composed once."""
    ctx = cli.context(why_act.STUDY, ["plan", "--seeds", "0,4"])
    return ctx, stage_arms(ctx, why_act.STAGES["placement"], check=False)


def test_the_cpu_plan_reuses_r4s_cpu_seeds_and_trains_r4s_gpu_seeds_again(cpu_placement):
    """R6's cpu plan (PLAN.md): seeds 0-3 and 7 pair with R4's committed runs (trained on the CPU at R4's commit),
    seeds 4-6 (R4's ran on an H200) train uniform and tar again; every control is planned in ``regimes/r6``."""
    _, specs = cpu_placement
    r4 = cli.RESULTS / "regimes" / "runs"
    for arm in ("uniform", "tar"):
        homes = {s.config["seed"]: s.run_dir.parent for s in specs[arm]}
        assert homes == {0: r4, 4: cli.RESULTS / "regimes" / "r6" / "runs"}
        for s in specs[arm]:
            if s.run_dir.parent == r4:
                summary = json.loads((s.run_dir / "summary.json").read_text())
                assert summary["machine"]["device"] == "cpu" and summary["git_commit"].startswith("2a4022e")
    assert all(s.run_dir.parent.parent.name == "r6" for arm in why_act.CONTROLS for s in specs[arm])
    assert why_act.SIZES["cpu"].reused_seeds == (0, 1, 2, 3, 7)  # R4's CPU seeds (PLAN.md, "Deviations")


def test_the_committed_plans_are_the_ones_r6s_runs_started_with():
    """``regimes/r6/started.json`` (written by the harness when each stage's first run started) holds the digest of
    the stage's overrides, composed here by hand from R4's base: seeds 0-7, each seed's arms in order."""
    from types import SimpleNamespace

    from benchmarks.studies.core import Planner, plan_digest

    started = json.loads((cli.RESULTS / "regimes" / "r6" / "started.json").read_text())
    sizes = why_act.SIZES["cpu"]
    planner = Planner(sizes.scale, cli.RESULTS / "regimes" / "r6", "datasets")
    arms = {"placement": ("uniform", "tar", "shuffle", "random", "invert")}
    arms["perturb"] = ("uniform", "tar", "perturb_high", "perturb_low")
    # the tuning grid's first rates, uniform on the tuning evaluation seed, seeds 0 and 1
    tune = ("eval.seed=2000", "objective=uniform")
    for stage, digest in started.items():
        assert stage in (*arms, "tune", "tuned"), f"a test for the digest of {stage} is missing"
        if stage == "tuned":  # uniform and tar at the rate the tuning record selected (3e-3), seeds 0-7
            plan = {
                arm: [SimpleNamespace(overrides=planner.overrides(*sizes.base, "optim.lr=0.003", f"seed={seed}",
                                                                  f"objective={arm}"))
                      for seed in range(8)]
                for arm in ("uniform", "tar")
            }  # fmt: skip
        elif stage == "tune":
            plan = {
                f"lr={rate}": [SimpleNamespace(overrides=planner.overrides(*sizes.base, *tune, f"optim.lr={rate}",
                                                                            f"seed={seed}"))
                               for seed in (0, 1)]
                for rate in ("0.0003", "0.001", "0.003")
            }  # fmt: skip
        else:
            plan = {
                arm: [SimpleNamespace(overrides=planner.overrides(*sizes.base, f"seed={seed}", f"objective={arm}"))
                      for seed in range(8)]
                for arm in arms[stage]
            }  # fmt: skip
        assert plan_digest(plan) == digest, stage
    assert started["placement"] == "746c15c91d5ef103"  # recorded when its first run started, at 6dcbd3d
    tuning = json.loads((cli.RESULTS / "regimes" / "r6" / "tuning.json").read_text())
    assert tuning["best"] == 0.003 and tuning["train_pair"]  # 76.7 against 1e-3's 74.25 (the committed runs)


def test_the_committed_tuning_record_recomputes_from_the_committed_tuning_runs():
    """``regimes/r6/tuning.json``'s success per rate is the mean over seeds 0 and 1 of the share of successful final
    rollouts (read here with pandas from each run's ``eval_rollouts.csv.gz``), and its outcome is the plan's rule
    applied by hand: the best rate, and the tuned pair trained when it beats 1e-3 by >= 2 points."""
    r6 = cli.RESULTS / "regimes" / "r6"
    record = json.loads((r6 / "tuning.json").read_text())
    per_rate: dict[float, list[float]] = {}
    for run in sorted((r6 / "runs").glob("uniform-act-s*")):
        cfg, final = committed_run(run)
        if cfg["eval"]["seed"] != 2000:
            continue
        assert len(final) == 50 * 20 and cfg["seed"] in (0, 1)
        per_rate.setdefault(cfg["optim"]["lr"], []).append(100 * final["success"].mean())
    assert sorted(per_rate) == record["rates"] == [0.0003, 0.001, 0.003, 0.01]
    for rate, values in per_rate.items():
        assert len(values) == 2
        assert record["success"][f"{rate:g}"] == pytest.approx(sum(values) / 2, abs=1e-9)
    best = max(per_rate, key=lambda r: sum(per_rate[r]))
    gain = (sum(per_rate[best]) - sum(per_rate[0.001])) / 2
    assert record["best"] == best == 0.003
    assert record["gain_over_reference"] == pytest.approx(gain) and record["train_pair"] == (gain >= 2)


def test_the_committed_paired_rows_of_the_perturbation_arms_and_the_tuned_pair_are_differences_to_their_uniform():
    """``r6/paired.csv``'s perturbation and tuned-pair rows against success computed here from the committed
    rollouts: each arm's run minus the uniform run of its seed and learning rate at evaluation seed 1000 (R6's own
    where R6 trained one, else R4's), found by config with yaml."""
    import pandas as pd

    r6, r4 = cli.RESULTS / "regimes" / "r6" / "runs", cli.RESULTS / "regimes" / "runs"

    def final_runs(folder):
        out = []
        for path in sorted(folder.glob("*-act-s*")):
            cfg, final = committed_run(path)
            if cfg["eval"]["seed"] == 1000 and cfg["data"]["n_demos"] == 50 and len(final) == 1000:
                out.append((cfg, 100 * final["success"].mean()))
        return out

    ours, r4s = final_runs(r6), final_runs(r4)

    def uniform(seed, lr):
        for runs in (ours, r4s):
            found = [
                v
                for c, v in runs
                if c["objective"]["name"] == "uniform" and c["seed"] == seed and c["optim"]["lr"] == lr
            ]
            if found:
                (value,) = found
                return value
        raise AssertionError(f"no uniform run of seed {seed} at lr {lr}")

    paired = pd.read_csv(cli.RESULTS / "regimes" / "r6" / "paired.csv")
    labels = {"R6 act: perturb_high": ("perturb_high", 1e-3), "R6 act: perturb_low": ("perturb_low", 1e-3)}
    labels["R6c act: tar (tuned lr)"] = ("tar", 3e-3)
    checked = 0
    for label, (arm, lr) in labels.items():
        rows = paired[paired["label"] == label]
        runs = {c["seed"]: v for c, v in ours if c["objective"]["name"] == arm and c["optim"]["lr"] == lr}
        assert sorted(rows["seed"]) == sorted(runs), label
        for seed, delta in zip(rows["seed"], rows["delta"], strict=True):
            assert delta == pytest.approx(runs[seed] - uniform(seed, lr), abs=1e-6), (label, seed)
            checked += 1
    assert checked >= 10  # the tuned pair's eight seeds and at least one of each perturbation arm
