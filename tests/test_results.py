"""The committed runs keep to the per-run budget of docs/contributing.md ("Committed results"): each is named by its
identity, holds the files the budget allows within their sizes, keeps its weight statistics, and keeps a
``weights.csv`` only where an analysis reads it (or where it was committed before the budget, listed by name)."""

from __future__ import annotations

import gzip
import io
import json
import subprocess
from pathlib import Path

import pandas as pd
import pytest
import yaml
from paths import REPO

from tar_rl.recipes import run_name

RESULTS = REPO / "benchmarks" / "results"
#: What every committed run keeps, and the most bytes they may take together.
KEPT = ("config.yaml", "summary.json", "eval_rollouts.csv.gz", "metrics.csv.gz")
KEPT_BUDGET = 64 * 1024
#: A weights recording, where kept, and its most bytes.
WEIGHTS = "weights.csv.gz"
WEIGHTS_BUDGET = 2 * 1024 * 1024
#: The runs that keep their checkpoint, with the reason.
CHECKPOINTS = {"regimes/runs/uniform-mlp-s0-b38746e7": "R1's source: the R1 runs start from it"}
#: The runs committed with a weights recording before the budget (the list only shrinks from its 175 runs).
BEFORE_BUDGET = RESULTS / "weights_before_budget.txt"
BEFORE_BUDGET_RUNS = 175


def reads_weights(rel: str, config: dict) -> bool:
    """Whether an analysis reads the committed run ``rel``'s weights (the budget's list, stated by hand):
    the R3 diagnosis (``python -m benchmarks.analysis diagnosis``) reads every R3 run (the MLP on MT50, 50
    demonstrations, 3,743 steps: uniform and tar, every seed); R4 and R5 (the ``act`` and ``flow`` heads) keep
    seed 0 of each arm, whose weights ``tar-rl report`` draws; R6 (``regimes/r6``) keeps seed 0 of each control
    (its uniform and tar of seed 0 are R4's); R7 (``regimes/r7``) keeps seed 0 of each arm of its comparison (on
    evaluation seed 1000; its pilot's uniform runs, on the tuning seed 2000, keep none)."""
    if rel.startswith("regimes/r6/runs/"):
        return config["seed"] == 0 and config["objective"]["name"] not in ("uniform", "tar")
    if rel.startswith("regimes/r7/runs/"):
        return config["seed"] == 0 and config["eval"]["seed"] == 1000
    if not rel.startswith("regimes/runs/"):
        return False
    head = config["policy"]["name"]
    data, steps = config["data"], config["optim"]["steps"]
    r3 = head == "mlp" and data["tasks"] == ["mt50"] and data["n_demos"] == 50 and steps == 3743
    return r3 or (head in ("act", "flow") and config["seed"] == 0)


def committed_runs() -> dict[str, Path]:
    """Every committed run folder (a folder of a ``runs`` folder under benchmarks/results, holding tracked files),
    by its path there; local runs that git ignores are left out."""
    listed = subprocess.run(["git", "ls-files", "-z", "benchmarks/results"], cwd=REPO, capture_output=True, timeout=60)
    if listed.returncode != 0:
        pytest.skip("not a git checkout")
    files = [Path(name).relative_to("benchmarks/results") for name in listed.stdout.decode().split("\0") if name]
    folders = {f.parent.as_posix() for f in files if len(f.parts) >= 3 and f.parts[-3] == "runs"}
    return {rel: RESULTS / rel for rel in sorted(folders)}


def before_budget() -> list[str]:
    return [line for line in BEFORE_BUDGET.read_text().splitlines() if line and not line.startswith("#")]


@pytest.fixture(scope="module")
def runs() -> dict[str, tuple[Path, dict]]:
    found = {rel: (path, yaml.safe_load((path / "config.yaml").read_text())) for rel, path in committed_runs().items()}
    assert len(found) >= 201, "the committed runs are not found"
    return found


def test_every_committed_run_folder_is_named_by_its_identity(runs):
    for rel, (path, config) in runs.items():
        summary = json.loads((path / "summary.json").read_text())
        assert path.name == run_name(config) == summary["run_name"], rel


def test_a_committed_run_holds_the_files_of_the_budget_within_their_sizes(runs):
    wrong = []
    for rel, (path, _) in runs.items():
        files = {p.name: p.stat().st_size for p in path.iterdir()}
        allowed = {*KEPT, WEIGHTS, *(["checkpoint.pt"] if rel in CHECKPOINTS else [])}
        if set(KEPT) - set(files) or set(files) - allowed:
            wrong.append(f"{rel}: lacks {sorted(set(KEPT) - set(files))}, holds {sorted(set(files) - allowed)}")
        elif sum(files[name] for name in KEPT) > KEPT_BUDGET or files.get(WEIGHTS, 0) > WEIGHTS_BUDGET:
            wrong.append(f"{rel}: {files} over the budget ({KEPT_BUDGET} bytes kept, {WEIGHTS_BUDGET} of weights)")
    assert not wrong, "\n".join(wrong)


def test_weights_are_committed_where_an_analysis_reads_them_and_before_the_budget_only(runs):
    listed = before_budget()
    assert len(listed) == len(set(listed)) <= BEFORE_BUDGET_RUNS
    with_weights = {rel for rel, (path, _) in runs.items() if (path / WEIGHTS).is_file()}
    read = {rel for rel, (_, config) in runs.items() if reads_weights(rel, config)}
    stale = sorted(set(listed) - (with_weights - read))
    assert not stale, f"{BEFORE_BUDGET.name} lists runs without unread weights: {stale}"
    unread = sorted(with_weights - read - set(listed))
    assert not unread, f"weights.csv committed where no analysis reads it: {unread}"
    lacking = sorted(read - with_weights)
    assert not lacking, f"runs an analysis reads without their weights.csv: {lacking}"


def test_every_committed_run_keeps_its_weight_statistics(runs):
    for rel, (path, _) in runs.items():
        summary = json.loads((path / "summary.json").read_text())
        assert len(summary["fit"]["alignment"]["weight_by_bin"]) == summary["fit"]["alignment"]["bins"], rel
        metrics = pd.read_csv(io.BytesIO(gzip.decompress((path / "metrics.csv.gz").read_bytes())))
        assert {"weight_max", "weight_ess"} <= set(metrics["name"]), rel


def test_the_reading_rule_matches_a_hand_count():
    """R3's 8 pairs, R4's seed 0 and R5's seed 0 (three arms each), R6's seed-0 controls and R7's seed-0 arms
    committed so far: the runs whose weights an analysis reads."""
    configs = {rel: yaml.safe_load((p / "config.yaml").read_text()) for rel, p in committed_runs().items()}
    read = sorted(rel.rsplit("/", 1)[1].rsplit("-", 1)[0] for rel, c in configs.items() if reads_weights(rel, c))
    r3 = sorted(f"{objective}-mlp-s{seed}" for objective in ("tar", "uniform") for seed in range(8))
    r4_r5 = ["tar-act-s0", "tar-act-s0", "uniform-act-s0", "tar-flow-s0", "tar-flow-s0", "uniform-flow-s0"]
    # R6's seed-0 controls: placement and perturbation
    r6 = ["invert-act-s0", "perturb_high-act-s0", "perturb_low-act-s0", "random-act-s0", "shuffle-act-s0"]
    r7 = ["tar-flow-s0", "tar-flow-s0", "uniform-flow-s0"]  # R7's seed-0 arms: tar, tar_gentle, uniform
    assert read == sorted([*r3, *r4_r5, *r6, *r7])
