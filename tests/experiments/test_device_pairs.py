"""``benchmarks/device/chunked_pairs.py``, the driver that trains whole seeds of a chunked-heads regime from the
study commit's own code: the plan digest it computes from that code equals the one the study recorded when R4's
first run started, and a changed plan, a seed outside the plan and a folder that is not the study's are refused
before anything is trained."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from paths import REPO

DRIVER = REPO / "benchmarks" / "device" / "chunked_pairs.py"
RECORD = REPO / "benchmarks" / "results" / "regimes" / "chunked_started.json"
STUDY_COMMIT = "2a4022e"  # PLAN.md: the commit R4 and R5 are trained at


@pytest.fixture(scope="module")
def study_tree(tmp_path_factory) -> Path:
    """The study commit's files (results left out); they import unbuilt (tar_rl's sub-packages are links)."""
    tree = tmp_path_factory.mktemp("study")
    archive = subprocess.run(
        ["git", "-C", str(REPO), "archive", STUDY_COMMIT, "--", ".", ":(exclude)benchmarks/results"],
        capture_output=True,
        check=True,
    ).stdout
    subprocess.run(["tar", "-x", "-C", str(tree)], input=archive, check=True)
    return tree


def drive(tree: Path, tmp_path: Path, *args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(tree)}
    cmd = [sys.executable, "-P", str(DRIVER), "--tree", str(tree), "--out", str(tmp_path / "out")]
    cmd += ["--data-root", str(tmp_path / "data"), *args]
    return subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)


def test_the_digest_from_the_study_code_equals_the_one_recorded_when_r4_started(study_tree, tmp_path):
    done = drive(study_tree, tmp_path, "--regime", "r4", "--seeds", "7", "--digest")
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == json.loads(RECORD.read_text())["R4"]


def test_a_plan_that_differs_from_its_record_is_refused_naming_both_digests(study_tree, tmp_path):
    record = tmp_path / "started.json"
    record.write_text(json.dumps({"R4": "0123456789abcdef"}))
    done = drive(study_tree, tmp_path, "--regime", "r4", "--seeds", "7", "--started", str(record))
    assert done.returncode != 0
    assert "0123456789abcdef" in done.stderr and json.loads(RECORD.read_text())["R4"] in done.stderr
    assert not (tmp_path / "out").exists() and not (tmp_path / "data").exists()


def test_a_seed_outside_the_plan_is_refused(study_tree, tmp_path):
    done = drive(study_tree, tmp_path, "--regime", "r4", "--seeds", "3,8")
    assert done.returncode != 0
    assert "--seeds 3,8" in done.stderr and "[0, 1, 2, 3, 4, 5, 6, 7]" in done.stderr


def test_a_folder_that_is_not_the_study_is_refused(tmp_path):
    done = drive(tmp_path, tmp_path, "--regime", "r4", "--seeds", "7")
    assert done.returncode != 0
    assert "holds no benchmarks/regimes.py" in done.stderr
