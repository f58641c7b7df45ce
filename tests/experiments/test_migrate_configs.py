"""``benchmarks/migrate_configs.py``: the committed runs' configs list their own weighting's parameters only, and a
config saved with every weighting's parameters is rewritten to the run it names."""

from __future__ import annotations

import importlib.util
import json
import sys

import pytest
import yaml
from paths import REPO
from recipe_helpers import compose_config

from benchmarks.studies import records
from tar_rl.recipes import run_name

BENCH = REPO / "benchmarks"


@pytest.fixture(scope="module")
def tool():
    spec = importlib.util.spec_from_file_location("migrate_configs", BENCH / "migrate_configs.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def _listed(config: dict) -> dict:
    """``config`` as a version before each weighting owned its parameters saved it."""
    listed = json.loads(json.dumps(config))
    listed["objective"] |= {"focal_beta": 1.0, "dro_bins": 10, "gripper_dims": [-1], "perturb_fraction": 0.25}
    return listed


def test_a_listed_config_and_summary_are_rewritten_once(tool):
    config = compose_config("objective=uniform", "seed=3")
    old = yaml.safe_dump(_listed(config), sort_keys=False)
    new = tool.migrate_text("config.yaml", old)
    assert new == yaml.safe_dump(config, sort_keys=False)
    assert tool.migrate_text("config.yaml", new) == new  # idempotent
    summary = {"run_name": "n", "final": [{"success": 0.5}], "config": _listed(config)}
    rewritten = json.loads(tool.migrate_text("summary.json", json.dumps(summary, indent=1)))
    assert rewritten == {**summary, "config": config}
    assert tool.migrate_text("table.md", old) == old


def test_a_migrated_config_must_name_its_folder(tool, tmp_path):
    config = compose_config("objective=uniform")
    folder = tmp_path / "runs" / run_name(config)
    folder.mkdir(parents=True)
    tool.check_run_name(folder / "config.yaml", yaml.safe_dump(config))
    with pytest.raises(ValueError, match="names the run"):
        tool.check_run_name(folder / "config.yaml", yaml.safe_dump({**config, "seed": 1}))


def test_no_committed_config_is_left_to_migrate(tool, capsys):
    assert tool.main(["--check"]) == 0
    assert capsys.readouterr().out.startswith("0 file(s) would change")


def test_collect_copies_a_run_of_an_older_version_as_this_version_writes_it(tmp_path):
    config = compose_config("objective=uniform", f"data.root={tmp_path / 'data'}", f"runs_root={tmp_path / 'src'}")
    run = tmp_path / "src" / "old-run"
    run.mkdir(parents=True)
    (run / "config.yaml").write_text(yaml.safe_dump(_listed(config), sort_keys=False))
    summary = {"finished": True, "seed": 0, "config": _listed(config)}
    (run / "summary.json").write_text(json.dumps(summary))
    assert records.collect(tmp_path / "src", tmp_path / "out") == [run_name(config)]
    copy = tmp_path / "out" / "runs" / run_name(config)
    for saved in (yaml.safe_load((copy / "config.yaml").read_text()), json.loads((copy / "summary.json").read_text())):
        objective = saved.get("config", saved)["objective"]
        assert objective == config["objective"] and "focal_beta" not in objective
