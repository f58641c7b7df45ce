"""Smoke test of the benchmark scripts: they run and write the tidy CSV they promise.

No timing is asserted here (speed is measured as ratios in benchmarks/, never in tests).
"""

from __future__ import annotations

import importlib
import math

import pandas as pd
import pytest
from paths import REPO


def _load_bench(name: str = "bench_objective"):
    return importlib.import_module(f"benchmarks.{name}")


@pytest.mark.slow
def test_bench_objective_quick_writes_csv(tmp_path):
    bench = _load_bench()
    out = tmp_path / "o.csv"
    bench.main(["--quick", "--step-reps", "5", "--weight-reps", "5", "--out", str(out)])  # the CSV's shape only

    assert out.exists()
    df = pd.read_csv(out)
    assert list(df.columns) == bench.COLUMNS
    assert set(df.section) == {"train_step", "train_step_paired", "weighting"}
    step = df[df.section == "train_step"]
    assert set(step.variant) == set(bench.STEP_VARIANTS)
    assert set(step.baseline) == set(bench.STEP_BASELINES)
    paired = df[df.section == "train_step_paired"]
    assert {"tar", "tar_exact"} <= set(paired[paired.baseline == "uniform"].variant)
    weighting = df[df.section == "weighting"]
    assert set(weighting.variant) == set(bench.WEIGHT_VARIANTS)

    # Every measured row has a positive finite median; compiled rows may only be missing
    # (NaN, unit "unavailable") where torch.compile failed, and then all of a variant's rows are.
    measured = df[df.unit != "unavailable"]
    assert all(math.isfinite(m) and m > 0 for m in measured["median"])
    assert all(math.isfinite(r) and r > 0 for r in measured["ratio_to_baseline"])
    assert (measured.n > 0).all()
    unavailable = df[df.unit == "unavailable"]
    assert set(unavailable.variant) <= set(bench.COMPILED)
    assert unavailable["median"].isna().all()
    weighted = (
        "masked_mean",
        "tar_paper",
        "tar_exact",
        "tilted",
        "truncate",
        "keyframe",
        "focal",
        "dro_time",
        "tar_arm",
    )
    for name in weighted:
        assert name in set(measured[measured.section == "weighting"].variant)
    # the baselines from the literature and the element variants are timed in a training step beside uniform
    baselines = {"tilted", "truncate", "keyframe", "focal", "dro_time", "tar_arm", "tar_dimnorm"}
    assert baselines <= set(paired[paired.baseline == "uniform"].variant)


@pytest.mark.slow
def test_bench_heads_quick_covers_every_registered_head(tmp_path):
    from tar_rl.policies import POLICIES

    bench = _load_bench("bench_heads")
    out = tmp_path / "h.csv"
    bench.main(["--quick", "--out", str(out), "--batch", "4", "--slice-len", "4", "--envs", "2", "--calls", "3"])

    df = pd.read_csv(out)
    assert list(df.columns) == bench.COLUMNS
    assert set(df.section) == {"train_step", "throughput", "tar_overhead", "inference"}
    for section, variants in (("train_step", {"uniform", "tar"}), ("throughput", {"uniform", "tar"})):
        rows = df[df.section == section]
        assert set(rows["head"]) == set(POLICIES)
        assert all(set(rows[rows["head"] == h].variant) == variants for h in POLICIES)
    assert set(df[df.section == "inference"]["head"]) == set(POLICIES)
    assert set(df[df.section == "tar_overhead"]["head"]) == set(POLICIES)
    assert all(math.isfinite(m) and m > 0 for m in df["median"])
    assert all(math.isfinite(r) and r > 0 for r in df["ratio_to_baseline"])
    # mlp is the baseline: its own ratios are 1
    mlp = df[(df["head"] == "mlp") & (df.baseline == "mlp")]
    assert len(mlp) == 5 and (mlp.ratio_to_baseline == 1).all()
    # throughput is the batch over the step time; with an odd number of rounds (3) the median of
    # B / t is exactly B over the median of t
    step = df[df.section == "train_step"].set_index(["head", "variant"])["median"]
    rate = df[df.section == "throughput"].set_index(["head", "variant"])["median"]
    assert ((rate * step / 1e3 - 4).abs() < 1e-9).all()


@pytest.mark.slow
def test_bench_heads_times_the_eager_weighting_beside_a_compiled_one(tmp_path):
    bench = _load_bench("bench_heads")
    out = tmp_path / "h.csv"
    args = ["--quick", "--heads", "mlp", "--batch", "4", "--slice-len", "4", "--envs", "2", "--calls", "3"]
    bench.main([*args, "--out", str(out), "--compile-weights", "always"])
    over = pd.read_csv(out).query("section == 'tar_overhead'")
    assert set(over.variant) == {"tar", "tar_eager"} and (over["median"] > 0).all()
    bench.main([*args, "--out", str(out)])  # auto on the CPU: nothing compiled, no eager twin
    assert set(pd.read_csv(out).query("section == 'tar_overhead'").variant) == {"tar"}


@pytest.mark.slow  # starts a Python process that imports torch and builds a head: ~10 s
def test_an_against_worker_times_steps_with_the_tar_rl_of_its_checkout():
    bench = _load_bench("bench_heads")
    args = bench.parse_args(["--quick", "--batch", "4", "--slice-len", "4"])
    worker = bench.Worker(REPO, args)  # this checkout, as `--against` starts one for each of its two
    try:
        seconds = [worker.time("mlp", False, 2), worker.time("mlp", False, 1)]
    finally:
        worker.close()
    assert worker.proc.returncode == 0
    assert all(math.isfinite(s) and s > 0 for s in seconds)
