"""MetaWorld demonstration collection and the on-disk dataset (real MetaWorld, small).

One module-scoped dataset (2 easy tasks x 3 demos, 2 worker processes, chunk horizon 4) is
collected once; expected values are recomputed here from the stored arrays, from MetaWorld
itself (replaying the stored actions) or by hand.
"""

from __future__ import annotations

import json
import shutil

import metaworld
import numpy as np
import pytest
import torch
from metaworld.env_dict import ALL_V3_ENVIRONMENTS
from objective_helpers import tar_loss
from tensordict.nn import TensorDictModule
from torchrl.objectives import BCLoss

from tar_rl.cli import main
from tar_rl.collectors.metaworld import demos, tasks
from tar_rl.collectors.metaworld.dataset import build_dataset, check_disjoint
from tar_rl.data import DatasetError, content_digest, load_dataset
from tar_rl.policies import DataInfo

TASKS = ["reach-v3", "button-press-topdown-v3"]
N_DEMOS = 3
H = 4
K = 3  # observation history window
SEED = 0


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    root = tmp_path_factory.mktemp("datasets")
    ds = build_dataset(root, TASKS, N_DEMOS, seed=SEED, chunk_horizon=H, history=K, workers=2, progress=False)
    return root, ds


@pytest.fixture(scope="module")
def arrays(built):
    """The stored steps as numpy arrays, read once."""
    _, ds = built
    td = ds.data
    return {key: td.get(key).numpy().copy() for key in td.keys(True, True)}


def _episodes(arrays):
    ep = arrays["episode"]
    return {int(e): np.flatnonzero(ep == e) for e in np.unique(ep)}


class _ZeroPolicy:
    def get_action(self, obs):
        return np.zeros(4, dtype=np.float32)


# -- Collection --------------------------------------------------------------------------


def test_episodes_contiguous_and_end_at_first_success(built, arrays):
    _, ds = built
    episodes = _episodes(arrays)
    assert len(episodes) == N_DEMOS * len(TASKS)
    assert sorted(episodes) == list(range(N_DEMOS * len(TASKS)))
    total = 0
    for rows in episodes.values():
        n = len(rows)
        total += n
        assert np.array_equal(rows, np.arange(rows[0], rows[0] + n)), "episode rows must be contiguous"
        assert np.array_equal(arrays["step"][rows], np.arange(n))
        term = arrays[("next", "terminated")][rows, 0]
        trunc = arrays[("next", "truncated")][rows, 0]
        assert term[-1] and not term[:-1].any()
        assert np.array_equal(arrays[("next", "done")][rows, 0], term | trunc)
        assert not trunc[: min(n, 499)].any()
        # next observation of step t is the observation of step t+1
        np.testing.assert_array_equal(arrays[("next", "observation")][rows[:-1]], arrays["observation"][rows[1:]])
        assert n <= 500
        assert len(np.unique(arrays["task_id"][rows])) == 1
    assert total == len(ds) == ds.metadata["total_steps"]


def test_replaying_stored_actions_succeeds_exactly_at_the_last_step(built, arrays):
    """Independent check with MetaWorld itself: the stored clipped actions on the recorded
    variation reproduce the observations, and success is first reached on the last step."""
    _, ds = built
    episodes = _episodes(arrays)
    first = 0
    for task in sorted(TASKS, key=sorted(ALL_V3_ENVIRONMENTS).index):
        info = ds.metadata["per_task"][task]
        bench = metaworld.MT1(task, seed=SEED)
        env = ALL_V3_ENVIRONMENTS[task]()
        for k, j in enumerate(info["episode_variation_index"]):
            rows = episodes[first + k]
            env.set_task(bench.train_tasks[j])
            obs, _ = env.reset()
            np.testing.assert_allclose(arrays["observation"][rows[0]], obs.astype(np.float32))
            successes = []
            for r in rows:
                obs, reward, _, _, step_info = env.step(arrays["action"][r])
                np.testing.assert_allclose(arrays[("next", "observation")][r], obs.astype(np.float32), atol=1e-6)
                assert arrays[("next", "reward")][r, 0] == pytest.approx(reward, rel=1e-6)
                successes.append(step_info["success"])
            assert successes[-1] == 1.0 and not any(successes[:-1])
        env.close()
        first += len(info["episode_variation_index"])


def test_actions_are_clipped_raw_actions(arrays):
    raw, act = arrays["action_raw"], arrays["action"]
    assert raw.dtype == act.dtype == np.float32 and act.shape[1:] == (4,)
    expected = np.minimum(np.maximum(raw, -1.0), 1.0)
    np.testing.assert_array_equal(act, expected)
    assert np.abs(act).max() <= 1.0
    assert np.abs(raw).max() > 1.0, "these experts emit actions beyond [-1, 1]: clipping must have mattered"
    assert arrays["observation"].dtype == np.float32 and arrays["observation"].shape[1:] == (39,)


def test_action_chunks_by_loop(arrays):
    act, chunk, valid, ep = arrays["action"], arrays["action_chunk"], arrays["action_chunk_valid"], arrays["episode"]
    n = len(act)
    assert chunk.shape == (n, H, 4) and valid.shape == (n, H) and valid.dtype == bool
    for t in range(n):
        last_real = t
        for k in range(H):
            u = t + k
            if u < n and ep[u] == ep[t]:
                assert valid[t, k]
                np.testing.assert_array_equal(chunk[t, k], act[u])
                last_real = u
            else:
                assert not valid[t, k]
                np.testing.assert_array_equal(chunk[t, k], act[last_real])


def test_observation_history_by_loop(arrays):
    obs, past, valid, ep = (
        arrays["observation"],
        arrays["observation_history"],
        arrays["observation_history_valid"],
        arrays["episode"],
    )
    n = len(obs)
    assert past.shape == (n, K, 39) and valid.shape == (n, K) and valid.dtype == bool
    for t in range(n):
        first = t
        while first > 0 and ep[first - 1] == ep[t]:
            first -= 1
        for j in range(K):  # entry j holds step t - (K - 1 - j): oldest first, the current step last
            u = t - (K - 1 - j)
            assert valid[t, j] == (u >= first)
            np.testing.assert_array_equal(past[t, j], obs[max(u, first)])


def test_task_ids(arrays, built):
    _, ds = built
    alphabetical = sorted(ALL_V3_ENVIRONMENTS)  # MetaWorld's own list, sorted
    expected = {alphabetical.index(t) for t in TASKS}
    assert set(np.unique(arrays["task_id"]).tolist()) == expected
    assert arrays["task_id"].dtype == np.int64 and arrays["episode"].dtype == np.int64
    # episodes are numbered in task-id order: the lower id comes first in storage
    assert np.all(np.diff(arrays["task_id"]) >= 0)
    assert ds.metadata["task_ids"] == {t: alphabetical.index(t) for t in TASKS}


def test_metadata(built, arrays):
    root, ds = built
    m = json.loads((ds.path / "metadata.json").read_text())
    assert m == ds.metadata
    assert m["tasks"] == sorted(TASKS, key=sorted(ALL_V3_ENVIRONMENTS).index)
    # every task id is named, with its instruction: ids are global, so the policy reads all 50 from the data
    assert m["source"] == "metaworld" and m["task_names"] == sorted(ALL_V3_ENVIRONMENTS)
    assert m["instructions"] == {t: tasks.INSTRUCTIONS[t] for t in sorted(ALL_V3_ENVIRONMENTS)}
    assert all(m["per_task"][t]["instruction"] == tasks.INSTRUCTIONS[t] for t in TASKS)
    info = DataInfo.from_metadata(m)
    assert info.n_tasks == 50 and info.instructions == tuple(tasks.INSTRUCTIONS[t] for t in sorted(ALL_V3_ENVIRONMENTS))
    assert m["seed"] == SEED and m["chunk_horizon"] == H and m["n_demos"] == N_DEMOS
    assert m["max_attempts"] == 3 * N_DEMOS + 5
    assert m["variation_seeds"] == [SEED]
    episodes = _episodes(arrays)
    lengths = [len(episodes[e]) for e in sorted(episodes)]
    offset = 0
    for task in m["tasks"]:
        info = m["per_task"][task]
        assert info["kept"] == N_DEMOS
        assert info["attempts"] == info["kept"] + info["rejected"]
        assert len(info["rejected_variation_index"]) == info["rejected"]
        assert sorted(info["episode_variation_index"] + info["rejected_variation_index"]) == list(
            range(info["attempts"])
        )
        assert info["episode_lengths"] == lengths[offset : offset + N_DEMOS]
        assert info["steps"] == sum(info["episode_lengths"])
        offset += N_DEMOS
    assert m["total_episodes"] == N_DEMOS * len(TASKS)
    assert m["total_steps"] == len(arrays["step"])
    assert m["total_rejected"] == sum(m["per_task"][t]["rejected"] for t in TASKS)
    assert m["action_target"] == "expert action clipped to the action space [-1, 1]; the unclipped action is action_raw"
    assert set(m["versions"]) == {"tar_rl", "torch", "torchrl", "tensordict", "metaworld", "mujoco", "numpy"}
    assert m["versions"]["metaworld"] == "3.1.1"
    assert isinstance(m["format_version"], int)
    assert ds.path.parent == root and ds.path.name.endswith(m["cache_key"])
    for key, name in (("observation", "observation"), ("action", "action")):
        x = arrays[key].astype(np.float64)
        stats = m["stats"][name]
        np.testing.assert_allclose(stats["mean"], x.mean(0), rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(stats["std"], x.std(0), rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(stats["min"], x.min(0))
        np.testing.assert_allclose(stats["max"], x.max(0))
        assert len(stats["mean"]) == x.shape[1]


# -- Disk, cache and corruption -----------------------------------------------------------


def test_round_trip_load(built, arrays):
    _, ds = built
    again = load_dataset(ds.path)
    assert len(again) == len(ds)
    td = again.data
    assert set(td.keys(True, True)) == set(arrays)
    for key, value in arrays.items():
        np.testing.assert_array_equal(td.get(key).numpy(), value, err_msg=str(key))
    assert again.metadata == ds.metadata


def test_second_build_loads_without_collecting(built, monkeypatch):
    root, ds = built

    def boom(*args, **kwargs):
        raise AssertionError("collect() must not run for a cached dataset")

    monkeypatch.setattr(demos, "collect", boom)
    again = build_dataset(root, TASKS, N_DEMOS, seed=SEED, chunk_horizon=H, history=K, workers=2, progress=False)
    assert again.path == ds.path and len(again) == len(ds)
    # a different setting is a different folder (and would collect)
    with pytest.raises(AssertionError, match="must not run"):
        build_dataset(root, TASKS, N_DEMOS, seed=SEED, chunk_horizon=H + 1, workers=2, progress=False)


def _truncate_storage(path):
    f = path / "buffer" / "storage" / "action.memmap"
    f.write_bytes(f.read_bytes()[:10])


def _remove_storage(path):
    (path / "buffer" / "storage" / "next" / "observation.memmap").unlink()


def _remove_metadata(path):
    (path / "metadata.json").unlink()


def _garble_metadata(path):
    (path / "metadata.json").write_text('{"total_steps": ')


def _other_settings(path):
    meta = json.loads((path / "metadata.json").read_text())
    meta["settings"]["n_demos"] += 1
    (path / "metadata.json").write_text(json.dumps(meta))


def _wrong_length(path):
    meta = json.loads((path / "metadata.json").read_text())
    meta["total_steps"] += 1
    (path / "metadata.json").write_text(json.dumps(meta))


def _edit_metadata_number(path):
    # A number the policy uses (its observation normaliser's mean), edited by hand.
    meta = json.loads((path / "metadata.json").read_text())
    meta["stats"]["observation"]["mean"][1] = 5.0
    (path / "metadata.json").write_text(json.dumps(meta, indent=1))


def _edit_episode_lengths(path):
    meta = json.loads((path / "metadata.json").read_text())
    task = next(iter(meta["per_task"]))
    lengths = meta["per_task"][task]["episode_lengths"]
    lengths[0], lengths[1] = lengths[0] + 1, lengths[1] - 1  # the same total: the sizes still agree
    (path / "metadata.json").write_text(json.dumps(meta, indent=1))


def _flip_memmap_byte(path):
    f = path / "buffer" / "storage" / "observation.memmap"
    data = bytearray(f.read_bytes())
    data[len(data) // 2] ^= 0x01  # one bit of one float: the size and every structural check still agree
    f.write_bytes(bytes(data))


@pytest.mark.parametrize(
    "corrupt",
    [
        _remove_metadata,
        _garble_metadata,
        _truncate_storage,
        _remove_storage,
        _wrong_length,
        _other_settings,
        _edit_metadata_number,
        _edit_episode_lengths,
        _flip_memmap_byte,
    ],
)
def test_corrupt_dataset_is_detected_and_rebuilt(built, arrays, tmp_path, capsys, caplog, corrupt):
    _, ds = built
    copy = tmp_path / ds.path.name
    shutil.copytree(ds.path, copy)
    corrupt(copy)
    if corrupt is not _other_settings:  # readable, but not what its folder name promises
        with pytest.raises(DatasetError):
            load_dataset(copy)
    capsys.readouterr()
    rebuilt = build_dataset(tmp_path, TASKS, N_DEMOS, seed=SEED, chunk_horizon=H, history=K, workers=0, progress=False)
    printed = capsys.readouterr()
    assert (printed.out + printed.err + caplog.text).count("is incomplete or corrupt") == 1  # reported once
    assert rebuilt.path == copy
    assert rebuilt.metadata == ds.metadata | {"collection_seconds": rebuilt.metadata["collection_seconds"]} | {
        "created": rebuilt.metadata["created"]
    }
    td = load_dataset(copy).data
    for key, value in arrays.items():
        np.testing.assert_array_equal(td.get(key).numpy(), value, err_msg=str(key))


@pytest.mark.parametrize(
    ("corrupt", "named"),
    [(_edit_metadata_number, "metadata.json"), (_flip_memmap_byte, "observation.memmap")],
)
def test_changed_content_is_refused_naming_the_folder_and_file(built, tmp_path, corrupt, named):
    _, ds = built
    copy = tmp_path / "mine"
    shutil.copytree(ds.path, copy)
    load_dataset(copy)  # intact: loads
    corrupt(copy)
    with pytest.raises(DatasetError, match=rf"{copy}/.*{named} differs from its content digest"):
        load_dataset(copy)


def test_a_folder_without_a_digest_is_refused_until_sealed_by_command(built, tmp_path, capsys):
    # Without digest.json nothing says the files are as written: such a folder is refused, and sealed only on the
    # user's explicit command (never by a load), after the other checks pass.
    _, ds = built
    copy = tmp_path / "unsealed"
    shutil.copytree(ds.path, copy)
    (copy / "digest.json").unlink()
    with pytest.raises(DatasetError, match=rf"{copy} has no content digest .*`tar-rl data seal {copy}`"):
        load_dataset(copy)
    assert not (copy / "digest.json").exists()  # a load writes nothing
    _flip_memmap_byte(copy)  # damaged while unsealed: refused all the same
    with pytest.raises(DatasetError, match="has no content digest"):
        load_dataset(copy)
    _flip_memmap_byte(copy)  # the same bit again: the content as written
    capsys.readouterr()
    assert main(["data", "seal", str(copy)]) == 0
    assert "recorded its content digest" in capsys.readouterr().out
    recorded = json.loads((copy / "digest.json").read_text())
    assert recorded == json.loads((ds.path / "digest.json").read_text())  # the content is the same
    assert load_dataset(copy).digest == ds.digest
    with pytest.raises(SystemExit, match=rf"tar-rl data seal: {copy} already has a content digest"):
        main(["data", "seal", str(copy)])
    _flip_memmap_byte(copy)
    with pytest.raises(DatasetError, match="differs from its content digest"):
        load_dataset(copy)


def test_seal_refuses_a_folder_that_fails_the_other_checks(built, tmp_path):
    _, ds = built
    copy = tmp_path / "unsealed"
    shutil.copytree(ds.path, copy)
    (copy / "digest.json").unlink()
    _truncate_storage(copy)
    with pytest.raises(SystemExit, match=r"tar-rl data seal: storage file .*action\.memmap holds 10 bytes"):
        main(["data", "seal", str(copy)])
    assert not (copy / "digest.json").exists()


def _reseal(path):
    """Record the digest of the folder as it now is, as whoever sends a folder can."""
    (path / "digest.json").write_text(json.dumps(content_digest(path)))


def _set_value(path, name, step, column, raw: bytes, width: int, itemsize: int):
    """Overwrite the bytes of one value of a stored entry (``width`` values per step) and reseal the folder."""
    f = path / "buffer" / "storage" / (name.replace(".", "/") + ".memmap")
    data = bytearray(f.read_bytes())
    at = (step * width + column) * itemsize
    data[at : at + itemsize] = raw
    f.write_bytes(bytes(data))
    _reseal(path)


@pytest.mark.parametrize(
    ("name", "width", "itemsize", "raw", "rule"),
    [
        ("observation", 39, 4, np.float32(np.nan).tobytes(), "holds NaN or Inf"),
        ("next.reward", 1, 4, np.float32(np.inf).tobytes(), "holds NaN or Inf"),
        ("action_chunk", 4 * H, 4, np.float32(-np.inf).tobytes(), "holds NaN or Inf"),
        ("action_chunk_valid", H, 1, b"\x02", "holds a byte other than 0 or 1"),
    ],
)
def test_non_finite_values_are_refused_when_the_dataset_is_checked(built, tmp_path, name, width, itemsize, raw, rule):
    # A NaN in a received dataset is found by the load (naming the entry and the step), not as a NaN loss later;
    # the sender's digest agrees with the file.
    _, ds = built
    copy = tmp_path / "values"
    shutil.copytree(ds.path, copy)
    _set_value(copy, name, 7, min(1, width - 1), raw, width, itemsize)  # step 7, its second value if it has one
    with pytest.raises(DatasetError, match=rf"{copy}: entry '{name}' {rule}.*\(first at step 7\)"):
        load_dataset(copy)


def _edit_metadata(path, edit):
    meta = json.loads((path / "metadata.json").read_text())
    edit(meta)
    (path / "metadata.json").write_text(json.dumps(meta))
    _reseal(path)


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda m: m.update(format_version=3), r"format version 3, which this tar-rl no longer reads .*build it again"),
        (lambda m: m.update(format_version=5), r"format version 5, newer than this tar-rl reads \(4\)"),
        (lambda m: m["stats"]["observation"]["mean"].__setitem__(0, float("nan")), r"stats is .*finite numbers"),
        (lambda m: m["task_ids"].update({m["tasks"][0]: 50}), r"task_ids is .*index in task_names"),
        (lambda m: m.update(tasks="reach-v3"), r"tasks is 'reach-v3'; it must be a non-empty list"),
        (lambda m: m.update(chunk_horizon="4"), r"chunk_horizon is '4'; it must be an integer >= 1"),
        (lambda m: m["keys"].update({"../../outside": {"shape": [], "dtype": "float32"}}), r"name '../../outside'"),
        (lambda m: m["keys"]["observation"].update(dtype="object"), r"element type 'object', not one of"),
        (lambda m: m["keys"]["observation"].update(shape=[38]), r"observation\.memmap holds \d+ bytes, \d+ expected"),
    ],
)
def test_metadata_outside_the_format_is_refused_naming_the_entry(built, tmp_path, edit, message):
    _, ds = built
    copy = tmp_path / "meta"
    shutil.copytree(ds.path, copy)
    _edit_metadata(copy, edit)
    with pytest.raises(DatasetError, match=message):
        load_dataset(copy)


def test_task_ids_outside_task_names_are_refused(built, tmp_path):
    _, ds = built
    copy = tmp_path / "ids"
    shutil.copytree(ds.path, copy)
    _set_value(copy, "task_id", 3, 0, np.int64(50).tobytes(), 1, 8)  # MetaWorld names ids 0..49
    with pytest.raises(DatasetError, match=r"entry 'task_id' is 50 at step 3; it must be 0\.\.49"):
        load_dataset(copy)


@pytest.mark.parametrize("linked", ["buffer/storage/observation.memmap", "metadata.json"])
def test_a_linked_file_is_refused(built, tmp_path, linked):
    # A symbolic link could point at any file of the disk; the digest would follow it.
    _, ds = built
    copy = tmp_path / "linked"
    shutil.copytree(ds.path, copy)
    f = copy / linked
    elsewhere = tmp_path / f.name
    f.rename(elsewhere)
    f.symlink_to(elsewhere)
    _reseal(copy)
    with pytest.raises(DatasetError, match=rf"{f} is a symbolic link"):
        load_dataset(copy)


def test_the_folder_holds_raw_arrays_and_two_json_files_and_its_files_are_never_written(built, tmp_path):
    _, ds = built
    files = sorted(p.relative_to(ds.path).as_posix() for p in ds.path.rglob("*") if p.is_file())
    assert [f for f in files if not f.endswith(".memmap")] == ["digest.json", "metadata.json"]
    assert sorted(f.removeprefix("buffer/storage/") for f in files if f.endswith(".memmap")) == sorted(
        k.replace(".", "/") + ".memmap" for k in ds.metadata["keys"]
    )
    copy = tmp_path / "mine"
    shutil.copytree(ds.path, copy)
    again = load_dataset(copy)
    again.data["observation"][0, 0] = 1e6  # a private map: this process's copy changes, the file does not
    assert float(again.data["observation"][0, 0]) == 1e6
    assert load_dataset(copy).digest == ds.digest


def test_leftover_temp_folder_is_removed(built, tmp_path, capsys):
    _, ds = built
    shutil.copytree(ds.path, tmp_path / ds.path.name)
    dead = tmp_path / f".{ds.path.name}.tmp-999999999-deadbeef"  # no such pid
    (dead / "buffer").mkdir(parents=True)
    (dead / "buffer" / "junk").write_text("partial")
    other = tmp_path / ".something-else.tmp-999999999-x"  # another dataset's: not ours to remove
    other.mkdir()
    again = build_dataset(tmp_path, TASKS, N_DEMOS, seed=SEED, chunk_horizon=H, history=K, workers=0, progress=False)
    assert again.path == tmp_path / ds.path.name
    assert not dead.exists()
    assert other.exists()
    assert "leftover" in capsys.readouterr().out


# -- Segments -----------------------------------------------------------------------------


@pytest.mark.parametrize("slice_len", [16, 64])
def test_segments(built, slice_len):
    _, ds = built
    torch.manual_seed(0)
    batch_segments = 48
    sampler = ds.segments(batch_segments, slice_len)
    # zero copy: the sampler reads the dataset's memory maps
    assert (
        sampler.buffer.storage._storage["observation"].data_ptr()
        == ds.buffer.storage._storage["observation"].data_ptr()
    )
    lengths = {}
    data = ds.data
    for e in data["episode"].unique().tolist():
        lengths[e] = int((data["episode"] == e).sum())
    saw_padding = False
    for _ in range(3):
        batch = sampler.sample()
        assert batch.batch_size == torch.Size([batch_segments, slice_len])
        mask = batch["collector", "mask"]
        assert mask.dtype == torch.bool and mask.shape == (batch_segments, slice_len)
        for i in range(batch_segments):
            m = mask[i]
            n_valid = int(m.sum())
            assert n_valid >= 1
            assert m[:n_valid].all() and not m[n_valid:].any(), "padding only at the end"
            ep = batch["episode"][i]
            step = batch["step"][i]
            assert (ep[:n_valid] == ep[0]).all()
            assert torch.equal(step[:n_valid], step[0] + torch.arange(n_valid))
            assert (batch["episode_length"][i] == lengths[int(ep[0])]).all()
            if n_valid < slice_len:
                saw_padding = True
                # cut at the episode's end: the last valid step is the episode's last
                assert int(step[n_valid - 1]) == lengths[int(ep[0])] - 1
                assert bool(batch["next", "terminated"][i, n_valid - 1])
    shortest = min(lengths.values())
    assert saw_padding == (shortest < slice_len)


def test_segments_feed_tar_loss(built):
    _, ds = built
    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Linear(39, 32), torch.nn.ReLU(), torch.nn.Linear(32, 4))
    actor = TensorDictModule(net, ["observation"], ["action"])
    loss = tar_loss(BCLoss(actor, loss_function="mse", reduction="none"))
    batch = ds.segments(8, 64).sample()
    out = loss(batch)
    assert torch.isfinite(out["loss_tar"]) and out["loss_tar"] > 0
    out["loss_tar"].backward()


def test_segments_key_subset(built):
    _, ds = built
    batch = ds.segments(4, 8, keys=["observation", ("next", "done")]).sample()
    assert set(batch.keys(True, True)) == {
        "observation",
        ("next", "done"),
        "episode",
        "index",
        ("collector", "mask"),
        "episode_length",  # always written, not stored
    }
    with pytest.raises(KeyError, match="not_there"):
        ds.segments(4, 8, keys=["not_there"])


def test_segments_generator_reproducible(built):
    _, ds = built
    a = ds.segments(8, 16, generator=torch.Generator().manual_seed(3)).sample()
    b = ds.segments(8, 16, generator=torch.Generator().manual_seed(3)).sample()
    assert torch.equal(a["step"], b["step"]) and torch.equal(a["episode"], b["episode"])


def test_segments_equal_torchrls_slice_sampler(built):
    # The one-gather sampler must draw exactly what torchrl's own SliceSampler draws with the same
    # settings and generator state (it only skips a read of the storage that nothing uses).
    from torchrl.data import SliceSampler, TensorDictReplayBuffer

    _, ds = built
    ours = ds.segments(32, 16, generator=torch.Generator().manual_seed(5))
    reference = TensorDictReplayBuffer(
        storage=ours.buffer.storage,
        sampler=SliceSampler(
            slice_len=16, traj_key="episode", strict_length=False, pad_output=True, truncated_key=None
        ),
        batch_size=32 * 16,
        generator=torch.Generator().manual_seed(5),
    )
    for _ in range(3):
        got = ours.sample()
        expected = reference.sample().reshape(32, 16)
        if ("collector", "mask") not in expected.keys(True):  # torchrl writes it only when a slice is padded
            expected.set(("collector", "mask"), torch.ones(32, 16, dtype=torch.bool))
        assert set(got.keys(True, True)) == set(expected.keys(True, True)) | {"episode_length"}  # ours adds it
        for key in expected.keys(True, True):
            assert torch.equal(got.get(key), expected.get(key)), key


def test_segments_bad_arguments(built):
    _, ds = built
    with pytest.raises(ValueError, match="slice_len"):
        ds.segments(4, 0)
    with pytest.raises(ValueError, match="batch_segments"):
        ds.segments(0, 4)


# -- Seeds, names, failures ---------------------------------------------------------------


def test_check_disjoint(built):
    _, ds = built
    with pytest.raises(ValueError, match="also used for demonstrations"):
        check_disjoint(ds, SEED, 10)
    with pytest.raises(ValueError, match="also used for demonstrations"):
        check_disjoint(ds, SEED, 60)  # 60 rollouts use seeds {SEED, SEED + 1}
    check_disjoint(ds, SEED + 1, 50)  # seeds {SEED + 1}: disjoint
    check_disjoint(ds, 1000, 200)


def test_unknown_task_lists_names(tmp_path, monkeypatch):
    def boom(*args, **kwargs):
        raise AssertionError("no collection for bad input")

    monkeypatch.setattr(demos, "collect", boom)
    with pytest.raises(ValueError, match=r"not-a-task.*reach") as err:
        build_dataset(tmp_path, ["reach", "not-a-task"], 2)
    assert "button-press-topdown" in str(err.value)
    with pytest.raises(ValueError, match="not-a-task"):
        demos.collect_task("not-a-task", 1)
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"n_demos": 0}, "n_demos"),
        ({"chunk_horizon": 0}, "chunk_horizon"),
        ({"seed": -1}, "seed"),
        ({"max_attempts": 1, "n_demos": 2}, "max_attempts"),
    ],
)
def test_bad_arguments(tmp_path, monkeypatch, kwargs, match):
    monkeypatch.setattr(demos, "collect", lambda *a, **k: pytest.fail("no collection for bad input"))
    args = {"n_demos": 2, **kwargs}
    with pytest.raises(ValueError, match=match):
        build_dataset(tmp_path, TASKS, **args)


def test_expert_that_never_succeeds_raises_naming_task(monkeypatch, tmp_path):
    monkeypatch.setattr(tasks, "expert", lambda task: _ZeroPolicy())
    with pytest.raises(RuntimeError, match=r"reach-v3.*only 0 of 2 episodes"):
        demos.collect_task("reach", 1, seed=SEED, max_attempts=2)
    with pytest.raises(RuntimeError, match="reach-v3"):
        build_dataset(tmp_path, ["reach"], 1, max_attempts=2, workers=0, progress=False)
    assert not any(p.name.startswith("metaworld-demos-") for p in tmp_path.iterdir()), "nothing half-built left"
    assert not any(p.name.startswith(".") for p in tmp_path.iterdir())


def test_collect_in_process_summary(capsys):
    out = demos.collect(["reach"], 1, seed=SEED, workers=0, progress=False)
    assert list(out) == ["reach-v3"]
    r = out["reach-v3"]
    assert r.kept == 1 and r.steps == len(r.step) == int(r.lengths.sum())
    assert r.env_steps == r.steps + 500 * r.rejected
    assert r.terminated[-1] and r.terminated.sum() == 1
    text = capsys.readouterr().out
    assert "1 demonstrations kept" in text and f"{r.steps} steps" in text


def test_workers_argument_is_checked():
    with pytest.raises(ValueError, match="workers"):
        demos.collect(["reach"], 1, workers=-1)


@pytest.mark.slow
def test_bench_data_quick_writes_csv(tmp_path):
    import pandas as pd

    from benchmarks import bench_data as bench  # its spawned pool workers import it by that name

    out = tmp_path / "data.csv"
    bench.main(["--quick", "--workers", "2", "--out", str(out)])
    df = pd.read_csv(out)
    assert list(df.columns) == bench.COLUMNS
    assert set(df.section) == {"collect_per_step", "collect_end_to_end", "segments"}
    assert (df["median"] > 0).all() and (df["ratio_to_baseline"] > 0).all()
    assert not list(tmp_path.glob(".*")), "no temporary file left beside the CSV"


@pytest.mark.slow  # collects a tiny dataset in this process and starts a `tar-rl train` process: ~5 s
def test_bench_data_startup_quick_writes_csv(tmp_path):
    import pandas as pd

    from benchmarks import bench_data as bench

    out = tmp_path / "startup.csv"
    root = str(tmp_path / "data")
    bench.main(["--quick", "--sections", "startup", "--workers", "1", "--root", root, "--out", str(out)])
    df = pd.read_csv(out)
    assert list(df.columns) == bench.COLUMNS
    assert list(df.variant) == ["job_startup", "load_dataset", "check_content"]
    assert (df["median"] > 0).all() and (df.baseline == "job_startup").all()


def test_worker_init_sets_one_torch_thread():
    import multiprocessing

    with multiprocessing.get_context("spawn").Pool(1, initializer=demos._worker_init) as pool:
        assert pool.apply(torch.get_num_threads) == 1


@pytest.mark.parametrize("workers", [1, 2])  # collected in this process, or in spawned workers
def test_collection_keeps_the_experts_clipping_warning_off_the_terminal(workers, capfd):
    """MetaWorld's scripted experts warn on every action outside [-1, 1] (``Constant(s) may be too high``); the
    actions are clipped, so collection shows no such warning, with every warning filter of this process open."""
    import warnings

    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        results = demos.collect(["push", "reach"], 1, workers=workers, progress=False, verbose=False)
    assert any((np.abs(r.action_raw) > 1).any() for r in results.values())  # the experts did act outside [-1, 1]
    assert [str(w.message) for w in seen if "may be too high" in str(w.message)] == []
    assert "may be too high" not in capfd.readouterr().err  # nor from the workers, on the terminal
