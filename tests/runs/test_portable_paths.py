"""What a tracked copy of a run records for the machine's folders (``tar_rl.runs.portable_path`` and the config and
summary built on it): paths relative to the repository, the run's identity unchanged."""

from __future__ import annotations

import pytest

from tar_rl.runs import portable_config, portable_path, portable_summary, run_name


@pytest.fixture
def root(tmp_path):
    """A repository root holding a ``benchmarks`` folder and a ``README.md``."""
    repo = tmp_path / "checkout"
    (repo / "benchmarks").mkdir(parents=True)
    (repo / "README.md").write_text("x")
    return repo


@pytest.mark.parametrize(
    ("path", "expected"),
    [
        ("datasets", "datasets"),  # relative: kept
        ("benchmarks/results/x", "benchmarks/results/x"),
        ("{root}/benchmarks/results/paper-cpu", "benchmarks/results/paper-cpu"),  # inside the repository
        ("{root}/datasets", "datasets"),
        ("{root}", "."),
        ("/elsewhere/datasets", "datasets"),  # a checkout's folders (CHECKOUT_FOLDERS)
        ("/elsewhere/study/runs", "runs"),
        ("/elsewhere/study/runs/uniform-mlp-s0-b38746e7/checkpoint.pt", "runs/uniform-mlp-s0-b38746e7/checkpoint.pt"),
        ("/out/x/report/comparison.csv", "report/comparison.csv"),
        ("/other/checkout/benchmarks/results/paper-cpu", "benchmarks/results/paper-cpu"),  # an entry of the root
        ("/a/datasets/runs/b", "datasets/runs/b"),  # from the first such component
    ],
)
def test_paths_are_written_from_the_repository_root(root, path, expected):
    assert portable_path(path.format(root=root), root) == expected


@pytest.mark.parametrize("path", ["/elsewhere/cache", "/opt/me/metaworld", "/other/checkout/README.md.bak"])
def test_a_path_in_no_folder_of_a_checkout_is_refused_naming_it(root, path):
    with pytest.raises(ValueError, match=f"^{path} lies outside the repository"):
        portable_path(path, root)


def _config(**paths) -> dict:
    config = {"objective": {"name": "tar"}, "policy": {"name": "mlp"}, "seed": 0, "data": {"root": "datasets"}}
    config |= {"init": {"from": None}, "runs_root": "runs", "run_dir": ""}
    for key, value in paths.items():
        section, _, leaf = key.partition("__")
        if leaf:
            config[section][leaf] = value
        else:
            config[key] = value
    return config


def test_a_config_names_its_folders_relative_and_keeps_its_run_name(root):
    source = "/elsewhere/study/runs/uniform-mlp-s0-b38746e7"
    config = _config(data__root="/elsewhere/datasets", runs_root="/elsewhere/study/runs", init__from=source)
    config["init"]["source"] = "uniform-mlp-s0-b38746e7"  # what the recipe's validate fills in
    config["run_dir"] = f"{root}/benchmarks/results/r/runs/x"
    portable = portable_config(config, root)
    assert portable["data"]["root"] == "datasets" and portable["runs_root"] == "runs"
    assert portable["init"] == {"from": "runs/uniform-mlp-s0-b38746e7", "source": "uniform-mlp-s0-b38746e7"}
    assert portable["run_dir"] == "benchmarks/results/r/runs/x"
    assert config["data"]["root"] == "/elsewhere/datasets"  # the input is not changed
    assert {k: v for k, v in portable.items() if k not in ("data", "init", "runs_root", "run_dir")} == {
        k: v for k, v in config.items() if k not in ("data", "init", "runs_root", "run_dir")
    }
    defaults = _config()
    assert run_name(portable, defaults) == run_name(config, defaults)


def test_folders_in_no_folder_of_a_checkout_are_the_default_jobs_and_runs_lie_under_runs(root):
    config = _config(data__root="/elsewhere/cache", runs_root="/elsewhere/sweep", init__from="/elsewhere/sweep/s/c.pt")
    config["init"]["source"] = "src"
    config["run_dir"] = "/elsewhere/sweep/tar-mlp-s0-1"
    portable = portable_config(config, root)
    assert portable["data"]["root"] == "datasets" and portable["runs_root"] == "runs"
    assert portable["init"]["from"] == "runs/s/c.pt" and portable["run_dir"] == "runs/tar-mlp-s0-1"


def test_a_run_directory_that_cannot_be_placed_is_refused_naming_the_setting(root):
    config = _config(runs_root="/elsewhere/sweep", init__from="/elsewhere/other/src")
    with pytest.raises(ValueError, match=r"^init\.from: /elsewhere/other/src lies outside"):
        portable_config(config, root)


def test_a_summary_names_its_config_and_source_checkpoint_relative(root):
    config = _config(data__root="/elsewhere/datasets", runs_root="/elsewhere/study/runs")
    checkpoint = "/elsewhere/study/runs/uniform-mlp-s0-b38746e7/checkpoint.pt"
    summary = {"run_name": "n", "final": [{"success": 0.5}], "init": {"from": checkpoint, "source_step": 40000}}
    summary["config"] = config
    portable = portable_summary(summary, root)
    assert portable["init"] == {"from": "runs/uniform-mlp-s0-b38746e7/checkpoint.pt", "source_step": 40000}
    assert portable["config"] == portable_config(config, root)
    assert portable["final"] == [{"success": 0.5}] and portable["run_name"] == "n"
    assert portable_summary({"run_name": "n", "init": None}, root) == {"run_name": "n", "init": None}
    config = _config(runs_root="/elsewhere/sweep")
    summary = {"init": {"from": "/elsewhere/sweep/src/checkpoint.pt"}, "config": config}  # no checkout folder
    assert portable_summary(summary, root)["init"]["from"] == "runs/src/checkpoint.pt"


def test_a_summary_names_its_training_dataset_under_its_portable_data_root(root):
    # "data", the folder of the cache here, is no checkout folder
    config = _config(data__root="/elsewhere/exp/data", runs_root="/elsewhere/exp/r7/runs")
    summary = {"config": config, "data": {"path": "/elsewhere/exp/data/metaworld-demos-a0", "digest": "sha256:ab"}}
    portable = portable_summary(summary, root)
    assert portable["data"] == {"path": "datasets/metaworld-demos-a0", "digest": "sha256:ab"}
    assert summary["data"]["path"] == "/elsewhere/exp/data/metaworld-demos-a0"  # the summary given is not changed
    # a tracked copy whose config is portable already: the same folder under the same name
    assert portable_summary(portable, root) == portable
    # a dataset folder the config names itself is written by portable_path's rule
    config = _config(data__root="/elsewhere/datasets", data__path="/elsewhere/demos/lerobot-set")
    outside = {"config": config, "data": {"path": "/elsewhere/demos/lerobot-set"}}  # no checkout folder in it
    with pytest.raises(ValueError, match=r"^data\.path: /elsewhere/demos/lerobot-set lies outside"):
        portable_summary(outside, root)
    config = _config(data__root="/elsewhere/datasets", data__path="/elsewhere/x/datasets/other")
    inside = {"config": config, "data": {"path": "/elsewhere/x/datasets/other"}}
    assert portable_summary(inside, root)["data"]["path"] == "datasets/other"
    assert portable_summary({"config": config, "data": {"path": None}}, root)["data"] == {"path": None}
