"""LeRobot datasets on local disk: a v3.0 folder written here with pandas, and TorchRL's converted copy.

Expected arrays are built by loops from the frames written (not by the importer's code).
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pandas as pd
import pytest
import torch

from tar_rl.cli import main
from tar_rl.importers import DemoImportError, import_lerobot
from tar_rl.policies import DataInfo

LENGTHS = [4, 3, 5]  # episodes 0, 1, 2
TASK_OF = [0, 1, 0]  # task_index of each episode
TASK_TEXT = ["push the T to the goal", "pick up the cube"]
DONE = [True, True, False]  # episode 2 ends without next.done: truncated there
H, K = 3, 2


def _frames(seed: int = 0) -> pd.DataFrame:
    rng = np.random.default_rng(seed)
    rows, index = [], 0
    for e, n in enumerate(LENGTHS):
        for t in range(n):
            rows.append(
                {
                    "observation.state": rng.normal(size=3).tolist(),
                    "observation.environment_state": rng.normal(size=2).tolist(),
                    "action": rng.uniform(-1, 1, size=2).tolist(),
                    "episode_index": e,
                    "frame_index": t,
                    "timestamp": t / 10,
                    "index": index,
                    "task_index": TASK_OF[e],
                    "next.reward": float(rng.uniform()),
                    "next.done": bool(DONE[e] and t == n - 1),
                }
            )
            index += 1
    return pd.DataFrame(rows)


def _write_v3(root, frames: pd.DataFrame, tasks=TASK_TEXT):
    """A LeRobot v3.0 folder: the frames over two parquet files (the second holding the first rows)."""
    (root / "meta").mkdir(parents=True)
    features = {
        "observation.state": {"dtype": "float32", "shape": [3]},
        "observation.environment_state": {"dtype": "float32", "shape": [2]},
        "action": {"dtype": "float32", "shape": [2]},
    }
    (root / "meta" / "info.json").write_text(json.dumps({"codebase_version": "v3.0", "fps": 10, "features": features}))
    pd.DataFrame({"task_index": list(range(len(tasks)))}, index=pd.Index(tasks, name="task")).to_parquet(
        root / "meta" / "tasks.parquet"
    )
    data = root / "data" / "chunk-000"
    data.mkdir(parents=True)
    frames.iloc[6:].to_parquet(data / "file-000.parquet")  # storage order is restored from `index`
    frames.iloc[:6].to_parquet(data / "file-001.parquet")
    return root


def _expected(frames: pd.DataFrame, keys=("observation.state", "observation.environment_state")):
    rows = {k: [] for k in ("obs", "next", "act", "rew", "term", "trunc", "episode", "step", "task", "chunk", "cvalid")}
    for e, n in enumerate(LENGTHS):
        ep = frames[frames["episode_index"] == e]
        obs = np.array([np.concatenate([ep[k].iloc[t] for k in keys]) for t in range(n)], np.float32)
        act = np.array([ep["action"].iloc[t] for t in range(n)], np.float32)
        for t in range(n):
            rows["obs"].append(obs[t])
            rows["next"].append(obs[min(t + 1, n - 1)])
            rows["act"].append(act[t])
            rows["rew"].append(np.float32(ep["next.reward"].iloc[t]))
            rows["term"].append(bool(ep["next.done"].iloc[t]))
            rows["trunc"].append(t == n - 1 and not DONE[e])
            rows["episode"].append(e)
            rows["step"].append(t)
            rows["task"].append(TASK_OF[e])  # tasks numbered in order of appearance: the same here
            rows["chunk"].append([act[min(t + h, n - 1)] for h in range(H)])
            rows["cvalid"].append([t + h < n for h in range(H)])
    return {k: np.array(v) for k, v in rows.items()}


KEYS = "observation.state,observation.environment_state"


@pytest.fixture
def folder(tmp_path):
    frames = _frames()
    return _write_v3(tmp_path / "pusht_like", frames), frames


def _check(ds, expected):
    td = ds.data
    np.testing.assert_array_equal(td["observation"].numpy(), expected["obs"])
    np.testing.assert_array_equal(td["next", "observation"].numpy(), expected["next"])
    np.testing.assert_array_equal(td["action"].numpy(), expected["act"])
    np.testing.assert_array_equal(td["next", "reward"].numpy()[:, 0], expected["rew"])
    np.testing.assert_array_equal(td["next", "terminated"].numpy()[:, 0], expected["term"])
    np.testing.assert_array_equal(td["next", "truncated"].numpy()[:, 0], expected["trunc"])
    np.testing.assert_array_equal(td["episode"].numpy(), expected["episode"])
    np.testing.assert_array_equal(td["step"].numpy(), expected["step"])
    np.testing.assert_array_equal(td["task_id"].numpy(), expected["task"])
    np.testing.assert_array_equal(td["action_chunk"].numpy(), expected["chunk"])
    np.testing.assert_array_equal(td["action_chunk_valid"].numpy(), expected["cvalid"])


def test_v3_folder_matches_hand_built_arrays(folder, tmp_path):
    path, frames = folder
    ds = import_lerobot(path, KEYS, out=tmp_path / "out", chunk_horizon=H, history=K, verbose=False)
    _check(ds, _expected(frames))
    m = ds.metadata
    assert m["source"] == "lerobot" and m["tasks"] == TASK_TEXT
    assert m["instructions"] == {t: t for t in TASK_TEXT}
    assert m["per_task"][TASK_TEXT[0]]["episode_lengths"] == [4, 5]
    assert m["obs_keys"] == [
        {"key": "observation.state", "dim": 3, "slice": [0, 3]},
        {"key": "observation.environment_state", "dim": 2, "slice": [3, 5]},
    ]
    assert m["lerobot"]["format"] == "v3.0"
    info = DataInfo.from_metadata(m)
    assert (info.obs_dim, info.action_dim, info.n_tasks, info.instructions) == (5, 2, 2, tuple(TASK_TEXT))
    assert ds.path.name.startswith("lerobot-pusht_like-")
    # the same import again loads the folder
    again = import_lerobot(path, KEYS, out=tmp_path / "out", chunk_horizon=H, history=K, verbose=False)
    assert again.path == ds.path and len(list((tmp_path / "out").iterdir())) == 1


def _torchrl_copy(frames: pd.DataFrame, copy):
    """What LeRobotExperienceReplay(repo_id, root=ROOT, download=True) leaves in ROOT/<repo_id>, which it reads back
    with download=False: TorchRL's canonical keys, memory-mapped (tensordict's memmap layout)."""
    from torchrl.data.datasets.lerobot import lerobot_columns_to_tensordict

    columns = {
        "observation.state": torch.tensor(np.stack(frames["observation.state"])),
        "observation.environment_state": torch.tensor(np.stack(frames["observation.environment_state"])),
        "action": torch.tensor(np.stack(frames["action"])),
        "episode_index": torch.tensor(frames["episode_index"].to_numpy()),
        "frame_index": torch.tensor(frames["frame_index"].to_numpy()),
        "next.reward": torch.tensor(frames["next.reward"].to_numpy()),
        "next.done": torch.tensor(frames["next.done"].to_numpy()),
        "task": [TASK_TEXT[i] for i in frames["task_index"]],
    }
    lerobot_columns_to_tensordict(columns).memmap_(copy)
    return copy


def test_torchrl_converted_copy_gives_the_same_dataset(folder, tmp_path):
    _, frames = folder
    copy = _torchrl_copy(frames, tmp_path / "torchrl" / "user_pusht")
    ds = import_lerobot(copy, KEYS, out=tmp_path / "out", chunk_horizon=H, history=K, verbose=False)
    _check(ds, _expected(frames))
    assert ds.metadata["lerobot"]["format"] == "torchrl-lerobot-memmap" and ds.metadata["tasks"] == TASK_TEXT


def test_no_file_of_a_torchrl_copy_runs_code(tmp_path):
    # A payload in each file of the copy that is not an array, and the instructions stored as tensordict stores
    # text it cannot write as JSON (a pickle.pkl its load_memmap unpickles): no code runs, one line names the file.
    from payload_helpers import pickle_payload, run

    copy = _torchrl_copy(_frames(), tmp_path / "torchrl" / "user_pusht")
    metas = sorted(p.relative_to(copy).as_posix() for p in copy.rglob("*") if p.suffix != ".memmap" and p.is_file())
    assert metas == [
        "language_instruction/meta.json",
        "meta.json",
        "next/meta.json",
        "observation/meta.json",
    ]
    cases = {rel: {rel: pickle_payload(tmp_path / f"code-ran-{i}")} for i, rel in enumerate(metas)}
    text = json.loads((copy / "language_instruction" / "meta.json").read_text())
    cases["language_instruction/pickle.pkl"] = {
        "language_instruction/meta.json": json.dumps({**text, "data": "pickle.pkl"}).encode(),
        "language_instruction/pickle.pkl": pickle_payload(tmp_path / "code-ran-pickle"),
    }
    ended = {}
    for i, (name, planted) in enumerate(cases.items()):
        received = tmp_path / f"received-{i}" / "user_pusht"
        shutil.copytree(copy, received)
        for rel, content in planted.items():
            (received / rel).write_bytes(content)
        command = ["data", "import", "lerobot", str(received), "--obs-keys", KEYS, "--out", str(tmp_path / "out")]
        ended[name] = (received, run(command))
    assert sorted(p.name for p in tmp_path.glob("code-ran-*")) == []
    for name, (received, message) in ended.items():
        named = received / ("language_instruction/meta.json" if name.endswith("pickle.pkl") else name)
        assert message.startswith(f"tar-rl data import lerobot: {named}"), message
    assert not any((tmp_path / "out").iterdir())  # nothing imported


def _bad(frames, case):
    if case == "missing":
        return frames.drop(
            columns=["observation.environment_state"]
        ), "column 'observation.environment_state' is missing"
    if case == "ragged":
        frames.at[5, "observation.state"] = [0.0, 1.0]
        return frames, r"episode 1: column 'observation.state' has rows of 2 and 3 values \(ragged"
    if case == "nan":
        frames.at[6, "action"] = [0.0, float("nan")]  # episode 1, its frame 2
        return frames, r"episode 1: column 'action' holds NaN or Inf \(first at frame 2\)"
    if case == "range":
        frames.at[8, "action"] = [0.0, 1.5]  # episode 2, frame 1
        return frames, r"episode 2: key 'action' leaves the declared range \[-1, 1\].*step 1, dim 1: 1.5"
    if case == "gap":
        return frames.drop(index=2).reset_index(drop=True), r"episode 0: column 'frame_index' is 3 at its frame 2"
    if case == "task":
        frames.at[3, "task_index"] = 1
        return frames, r"episode 0: column 'task' changes within the episode"
    raise AssertionError(case)


@pytest.mark.parametrize("case", ["missing", "ragged", "nan", "range", "gap", "task"])
def test_bad_input_names_episode_and_column_and_writes_nothing(tmp_path, case):
    frames, message = _bad(_frames(), case)
    path = _write_v3(tmp_path / "bad", frames)
    with pytest.raises(DemoImportError, match=message):
        import_lerobot(path, KEYS, out=tmp_path / "out", verbose=False)
    assert not any((tmp_path / "out").iterdir())


def test_clip_and_refused_inputs(folder, tmp_path):
    frames = _frames()
    frames.at[8, "action"] = [0.0, 1.5]
    path = _write_v3(tmp_path / "wide", frames)
    ds = import_lerobot(path, KEYS, out=tmp_path / "out", clip=True, verbose=False)
    assert float(ds.data["action"][8, 1]) == 1.0 and float(ds.data["action_raw"][8, 1]) == 1.5
    assert ds.metadata["clipped_action_entries"] == 1
    with pytest.raises(DemoImportError, match="images or videos"):
        import_lerobot(folder[0], "observation.images.top", out=tmp_path / "out", verbose=False)
    with pytest.raises(DemoImportError, match="not a TorchRL LeRobot copy"):
        import_lerobot(tmp_path, out=tmp_path / "out2", verbose=False)  # neither layout
    with pytest.raises(DemoImportError, match="no such folder"):
        import_lerobot(tmp_path / "nowhere", verbose=False)


def test_cli_import_then_train_without_evaluation(folder, tmp_path, capsys):
    from recipe_helpers import compose_config

    from tar_rl.recipes import train

    path, _ = folder
    assert main(["data", "import", "lerobot", str(path), "--obs-keys", KEYS, "--out", str(tmp_path / "out")]) == 0
    assert "imported 3 episodes, 12 steps, 2 task(s)" in capsys.readouterr().out
    (dataset,) = (tmp_path / "out").iterdir()
    cfg = compose_config(
        f"data.path={dataset}",
        "data.batch_segments=4",
        "data.slice_len=3",
        "policy.hidden=[16]",
        "policy.task_conditioning=instruction",
        "optim.steps=4",
        "optim.warmup=1",
        "logging.every=2",
        "logging.progress=false",
        "logging.record_weights_at=[]",
        "eval.rollouts=0",
        f"runs_root={tmp_path / 'runs'}",
    )
    run = train(cfg)
    assert json.loads((run / "summary.json").read_text())["finished"]
    with pytest.raises(SystemExit, match=r"tar-rl data import lerobot: .*no such folder"):
        main(["data", "import", "lerobot", str(tmp_path / "nowhere")])


def test_v2_folder_gives_the_same_dataset(tmp_path):
    # LeRobot v2.x: one parquet file per episode, the task table in meta/tasks.jsonl.
    frames = _frames()
    root = tmp_path / "v21"
    (root / "meta").mkdir(parents=True)
    (root / "meta" / "info.json").write_text(json.dumps({"codebase_version": "v2.1", "fps": 10}))
    (root / "meta" / "tasks.jsonl").write_text(
        "\n".join(json.dumps({"task_index": i, "task": t}) for i, t in enumerate(TASK_TEXT)) + "\n"
    )
    data = root / "data" / "chunk-000"
    data.mkdir(parents=True)
    for e in range(len(LENGTHS)):
        frames[frames["episode_index"] == e].to_parquet(data / f"episode_{e:06d}.parquet")
    ds = import_lerobot(root, KEYS, out=tmp_path / "out", chunk_horizon=H, history=K, verbose=False)
    _check(ds, _expected(frames))
    assert ds.metadata["tasks"] == TASK_TEXT and ds.metadata["lerobot"]["format"] == "v2.1"
    (root / "meta" / "info.json").write_text(json.dumps({"codebase_version": "v1.6"}))
    with pytest.raises(DemoImportError, match=r"LeRobot format 'v1.6' is not supported \(v2.x and v3.x are\)"):
        import_lerobot(root, KEYS, out=tmp_path / "out2", verbose=False)


@pytest.mark.parametrize(
    ("keys", "message"),
    [("", "obs_keys is empty: name at least one state column"), (["action", "action"], r"\['action'\] more than once")],
)
def test_obs_keys_refused_by_both_importers(folder, tmp_path, keys, message):
    from tar_rl.importers import import_robomimic

    with pytest.raises(DemoImportError, match=message.replace("state column", ".*")):
        import_robomimic(tmp_path / "none.hdf5", keys, out=tmp_path / "out", verbose=False)
    with pytest.raises(DemoImportError, match=message):
        import_lerobot(folder[0], keys, out=tmp_path / "out", verbose=False)
