"""The package as a user meets it: layout, docstring examples, the command line, the demo."""

from __future__ import annotations

import doctest
import importlib
import math
import subprocess
import sys

import pytest
from paths import REPO

MODULES = ["tar_rl.objectives.weighting", "tar_rl.objectives.schedule", "tar_rl.objectives.tar_loss"]


def test_root_folders_are_tar_rl_subpackages():
    import tar_rl.collectors
    import tar_rl.objectives
    import tar_rl.recipes

    assert tar_rl.objectives.__file__.replace("\\", "/").endswith("/objectives/__init__.py")
    assert tar_rl.collectors.__file__.replace("\\", "/").endswith("/collectors/__init__.py")
    assert tar_rl.recipes.__file__.replace("\\", "/").endswith("/recipes/__init__.py")
    assert tar_rl.tar_weights is tar_rl.objectives.tar_weights


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples(name):
    result = doctest.testmod(importlib.import_module(name), optionflags=doctest.NORMALIZE_WHITESPACE)
    assert result.attempted > 0 and result.failed == 0


def test_module_entry_point_help():
    done = subprocess.run([sys.executable, "-m", "tar_rl", "--help"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and "demo" in done.stdout


def test_cli_rejects_bad_arguments(capsys):
    from tar_rl.cli import main

    with pytest.raises(SystemExit):
        main(["demo", "--weightings", "nope"])
    assert "invalid choice" in capsys.readouterr().err
    with pytest.raises(SystemExit, match="at least 10"):
        main(["demo", "--steps", "3"])


@pytest.mark.slow
def test_demo_runs_end_to_end(capsys):
    from tar_rl.demo import DemoConfig, run

    report = run(DemoConfig(n_train=12, n_test=4, steps=40, batch_segments=8))
    printed = capsys.readouterr().out
    assert "TAR weights along a held-out demonstration" in printed
    assert set(report["weightings"]) == {"uniform", "tar"}
    for row in report["weightings"].values():
        assert all(math.isfinite(v) and v >= 0 for v in row.values())


def test_readme_training_example_runs(tmp_path, monkeypatch):
    """The README's training loop, run for a few steps instead of 1,000."""
    readme = (REPO / "README.md").read_text()
    block = readme.split("```python\n")[1].split("```")[0]
    assert "for step in range(1_000):" in block
    monkeypatch.chdir(tmp_path)
    scope: dict = {}
    exec(compile(block.replace("range(1_000)", "range(5)"), "README.md", "exec"), scope)
    assert int(scope["loss"].schedule_step) == 5
    assert math.isfinite(scope["out"]["loss_tar"].item())


@pytest.mark.slow
def test_readme_metaworld_example_runs(tmp_path, monkeypatch):
    """The README's MetaWorld block: a tiny dataset, a segment batch, an expert evaluation, the table."""
    readme = (REPO / "README.md").read_text()
    block = next(b.split("```")[0] for b in readme.split("```python\n")[1:] if "build_dataset" in b)
    monkeypatch.chdir(tmp_path)
    scope: dict = {}
    exec(compile(block, "README.md", "exec"), scope)
    assert tuple(scope["batch"].shape) == (8, 16)
    overall = scope["table"].set_index("level").loc["overall"]
    assert overall["success"] == 100.0  # the scripted expert solves reach
