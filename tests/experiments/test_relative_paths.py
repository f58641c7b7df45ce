"""``benchmarks/relative_paths.py`` (the committed files' absolute paths written relative to the repository) and the
benchmarks' provenance, which records its command's paths the same way."""

from __future__ import annotations

import importlib.util
import json
import sys

import pytest
import yaml
from paths import REPO

BENCH = REPO / "benchmarks"


def _load(name: str):
    spec = importlib.util.spec_from_file_location(name, BENCH / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def tool():
    return _load("relative_paths")


CONFIG = """\
objective:
  name: tar
  w_max: 3.0
policy:
  name: mlp
data:
  root: /elsewhere/datasets
init:
  from: /elsewhere/study/runs/uniform-mlp-s0-b38746e7
seed: 0
runs_root: /elsewhere/study/runs
run_dir: ''
"""


def test_a_config_is_rewritten_line_for_line(tool, tmp_path):
    new, unplaced = tool.rewrite(CONFIG, tmp_path)
    expected = CONFIG.replace("/elsewhere/datasets", "datasets").replace("/elsewhere/study/runs", "runs")
    assert new == expected and unplaced == []
    assert "  from: runs/uniform-mlp-s0-b38746e7\n" in new
    tool.check_run_file("config.yaml", CONFIG, new, tmp_path)  # only the paths changed


def test_commands_and_reports_are_rewritten_and_other_slashes_kept(tool, tmp_path):
    (tmp_path / "benchmarks").mkdir()
    text = (
        '{"command": "python benchmarks/x.py --out /ck/benchmarks/results/p --data-root /ck/datasets"}\n'
        "wrote: /out/a/report/comparison.csv, /out/a/report/fig.png\n"
        "see https://github.com/o/r/blob/main/x.md, 3/4 of runs, success / NEPS, <folder>/buffer/storage\n"
    )
    new, unplaced = tool.rewrite(text, tmp_path)
    assert new == (
        '{"command": "python benchmarks/x.py --out benchmarks/results/p --data-root datasets"}\n'
        "wrote: report/comparison.csv, report/fig.png\n"
        "see https://github.com/o/r/blob/main/x.md, 3/4 of runs, success / NEPS, <folder>/buffer/storage\n"
    )
    assert unplaced == []
    again, _ = tool.rewrite(new, tmp_path)
    assert again == new  # idempotent


def test_a_path_it_cannot_place_is_kept_and_named(tool, tmp_path):
    text = "wrote: /out/rep-heads/comparison.csv and /elsewhere/runs/a\n"
    new, unplaced = tool.rewrite(text, tmp_path)
    assert new == "wrote: /out/rep-heads/comparison.csv and runs/a\n"
    assert unplaced == ["/out/rep-heads/comparison.csv"]


def test_a_run_files_folders_in_no_folder_of_a_checkout_are_the_default_jobs(tool, tmp_path):
    config = CONFIG.replace("/elsewhere/datasets", "/cache/mw").replace("/elsewhere/study/runs", "/sweep")
    new, unplaced = tool.rewrite(config, tmp_path, tool.run_file_paths("config.yaml", config, tmp_path))
    assert unplaced == [] and new == CONFIG.replace("/elsewhere/datasets", "datasets").replace(
        "/elsewhere/study/runs", "runs"
    )
    tool.check_run_file("config.yaml", config, new, tmp_path)
    assert tool.run_file_paths("table.md", config, tmp_path) == {}


def test_a_rewrite_that_changes_a_result_is_refused(tool, tmp_path):
    summary = {"run_name": "n", "final": [{"success": 0.5}], "config": yaml.safe_load(CONFIG)}
    old = json.dumps(summary, indent=1)
    new, _ = tool.rewrite(old, tmp_path)
    tool.check_run_file("summary.json", old, new, tmp_path)
    with pytest.raises(ValueError, match="would change more than the paths"):
        tool.check_run_file("summary.json", old, new.replace('"success": 0.5', '"success": 0.6'), tmp_path)
    with pytest.raises(ValueError, match="would change more than the paths"):
        tool.check_run_file("config.yaml", CONFIG, CONFIG.replace("w_max: 3.0", "w_max: 2.0"), tmp_path)


def test_no_committed_file_is_left_to_rewrite(tool, capsys):
    assert tool.main(["--check"]) == 0
    assert capsys.readouterr().out.startswith("0 file(s) would change")


def test_provenance_records_the_commands_paths_relative_to_the_repository():
    from benchmarks.studies import paper, records

    argv = ["run", "budget", "--out", str(REPO / "benchmarks" / "results" / "paper-cpu")]
    argv += ["--data-root", "/elsewhere/datasets"]
    argv += ["--set", f"data.path={REPO}/demos", "--set", "optim.steps=3", "--jobs", "/elsewhere/unplaced"]
    command = records.provenance(paper.SIZES["ci"].scale, "paper", argv)["command"]
    assert command == (
        "python -m benchmarks.studies paper run budget --out benchmarks/results/paper-cpu --data-root datasets "
        "--set data.path=demos --set optim.steps=3 --jobs /elsewhere/unplaced"
    )
