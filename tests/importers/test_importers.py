"""robomimic / LIBERO HDF5 import and ``tar-rl data info``.

Each test writes a small HDF5 file in robomimic's layout (three demos of different lengths, named so
that their natural order differs from the lexicographic one) and checks the imported dataset against
arrays built here by loops from the values written to the file.
"""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest
import torch

from tar_rl.cli import main
from tar_rl.data import VALID_KEY, load_dataset
from tar_rl.importers import DemoImportError, dataset_info, import_robomimic
from tar_rl.policies import DataInfo

LENGTHS = {"demo_0": 5, "demo_2": 3, "demo_10": 4}  # natural order: demo_0, demo_2, demo_10
ORDER = ["demo_0", "demo_2", "demo_10"]
KEYS = ["object", "eef_pos"]  # imported in this order: object (4) then eef_pos (3)
ENV_ARGS = {"env_name": "Lift", "type": 1, "env_kwargs": {"control_freq": 20, "robots": ["Panda"]}}
H, K = 3, 2


def _demos(seed: int = 0) -> dict:
    """Per demo the arrays to write: obs keys, actions in [-1, 1], dones, rewards."""
    rng = np.random.default_rng(seed)
    out = {}
    for name, n in LENGTHS.items():
        out[name] = {
            "obs/object": rng.normal(size=(n, 4)),
            "obs/eef_pos": rng.normal(size=(n, 3)).astype(np.float32),
            "obs/gripper": rng.normal(size=(n, 2)),
            "obs/agentview_image": rng.integers(0, 255, size=(n, 4, 4, 3), dtype=np.uint8),
            "actions": rng.uniform(-1, 1, size=(n, 7)),
            "dones": np.r_[np.zeros(n - 1), 0 if name == "demo_2" else 1].astype(np.int64),  # demo_2 never done
            "rewards": rng.uniform(size=n),
        }
    out["demo_0"]["next_obs/object"] = out["demo_0"]["obs/object"] + 100.0
    out["demo_0"]["next_obs/eef_pos"] = out["demo_0"]["obs/eef_pos"] - 100.0
    return out


def _write(path, demos, env_args=ENV_ARGS, problem_info=None, masks=None):
    masks = {"train": ["demo_10", "demo_0"], "valid": ["demo_2"], "empty": []} if masks is None else masks
    with h5py.File(path, "w") as f:
        data = f.create_group("data")
        if env_args is not None:
            data.attrs["env_args"] = json.dumps(env_args)
        if problem_info is not None:
            data.attrs["problem_info"] = json.dumps(problem_info)
        for name, arrays in demos.items():
            for key, value in arrays.items():
                data.create_dataset(f"{name}/{key}", data=value)
        for name, demo_names in masks.items():
            f.create_dataset(f"mask/{name}", data=np.array(demo_names, dtype="S16"))
    return path


@pytest.fixture
def h5file(tmp_path):
    demos = _demos()
    return _write(tmp_path / "lift.hdf5", demos), demos


def _expected(demos, order):
    """The dataset's steps built by loops from the written arrays."""
    rows = {k: [] for k in ("obs", "next", "act", "rew", "term", "trunc", "episode", "step", "chunk", "cvalid")}
    rows.update(hist=[], hvalid=[])
    for e, name in enumerate(order):
        d = demos[name]
        n = len(d["actions"])
        obs = np.concatenate([d[f"obs/{k}"].reshape(n, -1) for k in KEYS], 1).astype(np.float32)
        if "next_obs/object" in d:
            nxt = np.concatenate([d[f"next_obs/{k}"].reshape(n, -1) for k in KEYS], 1).astype(np.float32)
        else:
            nxt = np.stack([obs[min(t + 1, n - 1)] for t in range(n)])
        act = d["actions"].astype(np.float32)
        for t in range(n):
            rows["obs"].append(obs[t])
            rows["next"].append(nxt[t])
            rows["act"].append(act[t])
            rows["rew"].append(np.float32(d["rewards"][t]))
            rows["term"].append(bool(d["dones"][t]))
            rows["trunc"].append(t == n - 1 and not d["dones"][t])
            rows["episode"].append(e)
            rows["step"].append(t)
            rows["chunk"].append([act[min(t + h, n - 1)] for h in range(H)])
            rows["cvalid"].append([t + h < n for h in range(H)])
            rows["hist"].append([obs[max(t - K + 1 + j, 0)] for j in range(K)])
            rows["hvalid"].append([t - K + 1 + j >= 0 for j in range(K)])
    return {k: np.array(v) for k, v in rows.items()}


def _check_steps(td, expected):
    np.testing.assert_array_equal(td["observation"].numpy(), expected["obs"])
    np.testing.assert_array_equal(td["next", "observation"].numpy(), expected["next"])
    np.testing.assert_array_equal(td["action"].numpy(), expected["act"])
    np.testing.assert_array_equal(td["action_raw"].numpy(), expected["act"])
    np.testing.assert_array_equal(td["next", "reward"].numpy()[:, 0], expected["rew"])
    np.testing.assert_array_equal(td["next", "terminated"].numpy()[:, 0], expected["term"])
    np.testing.assert_array_equal(td["next", "truncated"].numpy()[:, 0], expected["trunc"])
    np.testing.assert_array_equal(td["next", "done"].numpy()[:, 0], expected["term"] | expected["trunc"])
    np.testing.assert_array_equal(td["episode"].numpy(), expected["episode"])
    np.testing.assert_array_equal(td["step"].numpy(), expected["step"])
    np.testing.assert_array_equal(td["action_chunk"].numpy(), expected["chunk"])
    np.testing.assert_array_equal(td["action_chunk_valid"].numpy(), expected["cvalid"])
    np.testing.assert_array_equal(td["observation_history"].numpy(), expected["hist"])
    np.testing.assert_array_equal(td["observation_history_valid"].numpy(), expected["hvalid"])


def test_import_matches_hand_built_arrays(h5file, tmp_path):
    path, demos = h5file
    ds = import_robomimic(path, "object,eef_pos", out=tmp_path / "out", chunk_horizon=H, history=K, verbose=False)
    td = ds.data
    assert td.shape == (12,)
    _check_steps(td, _expected(demos, ORDER))
    np.testing.assert_array_equal(td["task_id"].numpy(), np.zeros(12, dtype=np.int64))
    assert td["observation"].dtype == torch.float32 and td["action_chunk_valid"].dtype == torch.bool


def test_metadata(h5file, tmp_path):
    path, demos = h5file
    ds = import_robomimic(path, ["object", "eef_pos"], out=tmp_path / "out", chunk_horizon=H, history=K, verbose=False)
    m = ds.metadata
    assert m["source"] == "robomimic" and m["tasks"] == ["Lift"] and m["task_ids"] == {"Lift": 0}
    assert m["total_steps"] == 12 and m["total_episodes"] == 3
    assert m["per_task"]["Lift"]["episode_lengths"] == [5, 3, 4]
    (source,) = m["sources"]
    assert source["path"] == str(path.resolve()) and source["env_args"] == ENV_ARGS
    assert source["demos"] == ORDER and source["steps"] == 12 and source["filter"] is None
    assert m["obs_keys"] == [
        {"key": "object", "dim": 4, "slice": [0, 4]},
        {"key": "eef_pos", "dim": 3, "slice": [4, 7]},
    ]
    assert m["keys"]["observation"] == {"shape": [7], "dtype": "float32"}
    assert m["keys"]["action_chunk"] == {"shape": [H, 7], "dtype": "float32"}
    assert m["keys"]["observation_history"] == {"shape": [K, 7], "dtype": "float32"}
    info = DataInfo.from_metadata(m)
    assert (info.obs_dim, info.action_dim, info.chunk_horizon, info.history) == (7, 7, H, K)
    obs = _expected(demos, ORDER)["obs"].astype(np.float64)
    np.testing.assert_allclose(info.obs_mean, obs.mean(0), rtol=1e-6)
    np.testing.assert_allclose(info.obs_std, obs.std(0), rtol=1e-6)
    assert ds.path.name.startswith("robomimic-lift-") and not list(ds.path.parent.glob(".*tmp*"))


def test_filter_selects_demos_in_its_order(h5file, tmp_path):
    path, demos = h5file
    out = tmp_path / "out"
    ds = import_robomimic(path, KEYS, filter_key="train", out=out, chunk_horizon=H, history=K, verbose=False)
    _check_steps(ds.data, _expected(demos, ["demo_10", "demo_0"]))
    assert ds.metadata["sources"][0]["demos"] == ["demo_10", "demo_0"]
    assert ds.metadata["sources"][0]["filter"] == "train"


def test_loads_and_samples_segments(h5file, tmp_path):
    path, _ = h5file
    ds = import_robomimic(path, KEYS, out=tmp_path / "out", chunk_horizon=H, history=K, verbose=False)
    again = load_dataset(ds.path)
    assert len(again) == 12
    batch = again.segments(6, 4, generator=torch.Generator().manual_seed(0)).sample()
    assert batch.shape == (6, 4) and batch["observation"].shape == (6, 4, 7)
    mask = batch[VALID_KEY]
    assert mask.dtype == torch.bool and mask.shape == (6, 4)
    for b in range(6):  # a segment lies within one episode; its valid steps are consecutive
        ep = batch["episode"][b][mask[b]]
        steps = batch["step"][b][mask[b]]
        assert (ep == ep[0]).all() and (steps.diff() == 1).all()


def test_second_import_loads_the_existing_folder(h5file, tmp_path, capsys):
    path, _ = h5file
    first = import_robomimic(path, KEYS, out=tmp_path / "out", verbose=False)
    second = import_robomimic(path, KEYS, out=tmp_path / "out")
    assert second.path == first.path and "already imported" in capsys.readouterr().out
    other = import_robomimic(path, KEYS, out=tmp_path / "out", history=3, verbose=False)
    assert other.path != first.path


def test_one_task_per_file_libero_problem_name(tmp_path):
    a = _write(tmp_path / "lift.hdf5", _demos(0))
    libero = {"problem_name": "libero_kitchen_tabletop_manipulation", "language_instruction": "open the drawer"}
    b = _write(tmp_path / "kitchen.hdf5", _demos(1), env_args={"env_name": "x"}, problem_info=libero)
    c = _write(tmp_path / "lift2.hdf5", _demos(2))
    ds = import_robomimic([a, b, c], KEYS, filter_key="valid", out=tmp_path / "out", verbose=False)
    m = ds.metadata
    assert m["tasks"] == ["Lift", "libero_kitchen_tabletop_manipulation"]
    assert m["instructions"]["libero_kitchen_tabletop_manipulation"] == "open the drawer"
    assert m["per_task"]["Lift"]["episodes"] == 2 and m["per_task"]["Lift"]["steps"] == 6
    # filter "valid" is demo_2 (3 steps) in each file: files a, b, c -> task ids 0, 1, 0
    np.testing.assert_array_equal(ds.data["task_id"].numpy(), np.repeat([0, 1, 0], 3))
    np.testing.assert_array_equal(ds.data["episode"].numpy(), np.repeat([0, 1, 2], 3))


def _mutate(demos, name, key, fn):
    demos[name][key] = fn(demos[name][key])


def _drop(demos, name, key):
    del demos[name][key]


BAD = {
    "missing obs key": (lambda d: _drop(d, "demo_2", "obs/object"), {}, r"demo 'demo_2'.*'obs/object' is missing"),
    "missing actions": (lambda d: _drop(d, "demo_0", "actions"), {}, r"demo 'demo_0'.*'actions' is missing"),
    "ragged obs": (
        lambda d: _mutate(d, "demo_10", "obs/eef_pos", lambda x: x[:-1]),
        {},
        r"demo 'demo_10'.*'obs/eef_pos' has 3 steps, 'actions' has 4 \(ragged",
    ),
    "ragged dones": (
        lambda d: _mutate(d, "demo_2", "dones", lambda x: x[:-1]),
        {},
        r"demo 'demo_2'.*'dones' has 2 steps.*ragged",
    ),
    "nan obs": (
        lambda d: _mutate(d, "demo_0", "obs/object", lambda x: np.where(np.arange(5)[:, None] == 2, np.nan, x)),
        {},
        r"demo 'demo_0'.*'obs/object' holds NaN or Inf \(first at step 2\)",
    ),
    "inf action": (
        lambda d: _mutate(d, "demo_2", "actions", lambda x: np.where(np.arange(3)[:, None] == 1, np.inf, x)),
        {},
        r"demo 'demo_2'.*'actions' holds NaN or Inf \(first at step 1\)",
    ),
    "action out of range": (
        lambda d: _mutate(d, "demo_10", "actions", lambda x: np.where(np.arange(4)[:, None] == 3, 1.5, x)),
        {},
        r"demo 'demo_10'.*'actions' leaves the declared range \[-1, 1\].*step 3, dim 0: 1.5.*--clip",
    ),
    "image key": (lambda d: None, {"obs_keys": "object,agentview_image"}, r"'obs/agentview_image'.*low-dimensional"),
    "empty filter": (lambda d: None, {"filter_key": "empty"}, r"filter 'empty'.*lists no demos"),
    "empty demo": (  # every array of demo_2 with no steps: named as empty, before any reshape of its arrays
        lambda d: d["demo_2"].update({key: value[:0] for key, value in d["demo_2"].items()}),
        {},
        r"demo 'demo_2'.*'actions' has no steps \(empty episode\)",
    ),
    "unknown filter": (
        lambda d: None,
        {"filter_key": "nope"},
        r"filter 'nope' not found.*\['empty', 'train', 'valid'\]",
    ),
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_input_names_demo_and_key_and_writes_nothing(tmp_path, case):
    change, kwargs, match = BAD[case]
    demos = _demos()
    change(demos)
    path = _write(tmp_path / "bad.hdf5", demos)
    out = tmp_path / "out"
    kwargs = {"obs_keys": KEYS, **kwargs}
    with pytest.raises(DemoImportError, match=match):
        import_robomimic(path, out=out, verbose=False, **kwargs)
    assert not out.exists()


def test_clip(tmp_path):
    demos = _demos()
    demos["demo_10"]["actions"][3, 0] = 1.5
    demos["demo_0"]["actions"][1, 2] = -2.0
    path = _write(tmp_path / "clip.hdf5", demos)
    ds = import_robomimic(path, KEYS, out=tmp_path / "out", clip=True, verbose=False)
    raw = np.concatenate([demos[n]["actions"] for n in ORDER]).astype(np.float32)
    np.testing.assert_array_equal(ds.data["action_raw"].numpy(), raw)
    clipped = raw.copy()
    clipped[1, 2] = -1.0  # demo_0 step 1
    clipped[5 + 3 + 3, 0] = 1.0  # demo_10 step 3
    np.testing.assert_array_equal(ds.data["action"].numpy(), clipped)
    assert ds.metadata["sources"][0]["clipped_action_entries"] == 2


def test_cli_import_and_info(h5file, tmp_path, capsys):
    path, demos = h5file
    out = tmp_path / "out"
    args = ["data", "import", "robomimic", str(path), "--obs-keys", "object,eef_pos", "--out", str(out)]
    assert main([*args, "--chunk-horizon", "3", "--history", "2", "--filter", "train"]) == 0
    (folder,) = out.iterdir()
    capsys.readouterr()
    assert main(["data", "info", str(folder)]) == 0
    text = capsys.readouterr().out
    assert "source: robomimic" in text and "episodes: 2" in text and "steps: 9" in text
    assert "observation_history_valid  bool     [2]" in text
    assert "action_chunk               float32  [3, 7]" in text
    acts = np.concatenate([demos["demo_10"]["actions"], demos["demo_0"]["actions"]]).astype(np.float32)
    assert "action min: [" + ", ".join(f"{x:.4g}" for x in acts.min(0)) + "]" in text
    assert "action max: [" + ", ".join(f"{x:.4g}" for x in acts.max(0)) + "]" in text
    assert "        0         2      9  Lift" in text
    assert main(["data", "info", str(folder), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["per_task"] == {"Lift": {"task_id": 0, "episodes": 2, "steps": 9}}


def test_cli_errors(h5file, tmp_path):
    path, _ = h5file
    with pytest.raises(SystemExit, match=r"tar-rl data import robomimic: .*'obs/nope' is missing"):
        main(["data", "import", "robomimic", str(path), "--obs-keys", "nope", "--out", str(tmp_path / "o")])
    with pytest.raises(SystemExit, match=r"tar-rl data info: no dataset folder"):
        main(["data", "info", str(tmp_path / "missing")])


def test_info_on_a_metaworld_dataset(data_root):
    from tar_rl.collectors.metaworld.dataset import build_dataset

    ds = build_dataset(data_root, ["reach-v3"], 1, chunk_horizon=2, history=2, workers=0, progress=False, verbose=False)
    info = dataset_info(ds.path)
    n = len(ds)
    assert info["source"] == "metaworld" and info["episodes"] == 1 and info["steps"] == n
    assert info["per_task"] == {"reach-v3": {"task_id": ds.metadata["task_ids"]["reach-v3"], "episodes": 1, "steps": n}}
    assert info["keys"]["observation"] == {"shape": [39], "dtype": "float32"}
    np.testing.assert_array_equal(info["action_min"], ds.data["action"].numpy().min(0))


def test_failure_while_writing_leaves_no_dataset(h5file, tmp_path, monkeypatch):
    import tar_rl.data.format

    def fail(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(tar_rl.data.format, "write_json_atomic", fail)  # the metadata, written last
    path, _ = h5file
    out = tmp_path / "out"
    with pytest.raises(OSError, match="disk full"):
        import_robomimic(path, KEYS, out=out, verbose=False)
    assert list(out.iterdir()) == []  # neither the dataset folder nor its temporary sibling


# -- Training on an imported dataset (``data.path``) -------------------------------------------


def _two_task_dataset(tmp_path, instructions=False):
    """Two files, two tasks: robomimic's Lift (no instruction) and a LIBERO problem (with one)."""
    libero = {"problem_name": "open_the_drawer", "language_instruction": "open the top drawer"}
    lift_info = {"problem_name": "lift_the_cube", "language_instruction": "lift the cube"} if instructions else None
    a = _write(tmp_path / "lift.hdf5", _demos(0), problem_info=lift_info)
    b = _write(tmp_path / "drawer.hdf5", _demos(1), problem_info=libero)
    return import_robomimic([a, b], KEYS, out=tmp_path / "data", chunk_horizon=H, history=K, verbose=False)


def _train_config(tmp_path, ds, *overrides):
    from recipe_helpers import compose_config

    return compose_config(
        f"data.path={ds.path}",
        "data.batch_segments=4",
        "data.slice_len=3",
        "policy.hidden=[16]",
        "optim.steps=6",
        "optim.warmup=1",
        "logging.every=2",
        "logging.checkpoint_every=4",
        "logging.progress=false",
        "logging.record_weights_at=[-1]",
        "eval.rollouts=0",
        f"runs_root={tmp_path / 'runs'}",
        *overrides,
    )


def test_train_on_imported_dataset_without_evaluation(tmp_path):
    from tar_rl.recipes import train
    from tar_rl.runs import load_checkpoint

    ds = _two_task_dataset(tmp_path)
    assert ds.tasks == ["Lift", "open_the_drawer"]
    run = train(_train_config(tmp_path, ds))
    summary = json.loads((run / "summary.json").read_text())
    assert summary["finished"] and summary["final"] == [] and summary["steps"] == 6
    metrics = (run / "metrics.csv").read_text()
    assert "train,loss," in metrics and ",eval," not in metrics
    assert not (run / "eval_rollouts.csv").exists() or (run / "eval_rollouts.csv").read_text().count("\n") <= 1
    # the head was built on the dataset's own sizes and task ids: 7-d observations (object 4 +
    # eef_pos 3), 7-d actions, 2 task ids (an embedding of 2 rows, not MetaWorld's 50)
    state = load_checkpoint(run / "checkpoint.pt")
    info = DataInfo.from_dict(state["data_info"])
    assert (info.obs_dim, info.action_dim, info.n_tasks) == (7, 7, 2)
    assert info.instructions == ("", "open the top drawer")
    assert state["policy"]["module.task_embedding.embedding.weight"].shape == (2, 32)
    # Fig. 5's weights were recorded along demonstrations of both imported tasks
    weights = (run / "weights.csv").read_text()
    assert ",Lift," in weights and ",open_the_drawer," in weights


def test_imported_dataset_with_instructions_trains_instruction_conditioning(tmp_path):
    from tar_rl.recipes import train

    ds = _two_task_dataset(tmp_path, instructions=True)
    run = train(_train_config(tmp_path, ds, "policy.task_conditioning=instruction"))
    assert json.loads((run / "summary.json").read_text())["finished"]


def test_data_path_bad_settings_are_refused_before_work(tmp_path):
    from tar_rl.recipes import ConfigError, train

    ds = _two_task_dataset(tmp_path)
    refused = r"robomimic demonstrations of \['Lift', 'open_the_drawer'\].*eval\.rollouts=0"
    with pytest.raises(ConfigError, match=refused):
        train(_train_config(tmp_path, ds, "eval.rollouts=2"))
    with pytest.raises(ConfigError, match=r"task ids \[0\] have no instruction text"):
        train(_train_config(tmp_path, ds, "policy.task_conditioning=instruction"))
    with pytest.raises(ConfigError, match=r"data\.path=.*nowhere.*no dataset folder"):
        train(_train_config(tmp_path, ds, f"data.path={tmp_path / 'nowhere'}"))
    (ds.path / "metadata.json").unlink()  # an unfinished folder
    with pytest.raises(ConfigError, match=r"data\.path=.*metadata\.json is missing"):
        train(_train_config(tmp_path, ds))
    assert not (tmp_path / "runs").exists()  # nothing started
