"""The package as a user meets it: layout, docstring examples, the command line, the demo."""

from __future__ import annotations

import doctest
import importlib
import math
import subprocess
import sys

import pytest

MODULES = ["tar_rl.objectives.tar", "tar_rl.objectives.schedule", "tar_rl.objectives.tar_loss"]


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
