"""A dataset folder someone sends runs no code: a payload planted in each of its files that is not an array,
with the content digest recomputed (as the sender can), is never executed by the commands that read the folder,
and a file they need ends them with one line naming it.
"""

from __future__ import annotations

import json
import shutil

from data_helpers import robomimic_file
from payload_helpers import pickle_payload, run

from tar_rl.data import content_digest

# The files of the dataset format before version 4 (TorchRL's rb.dumps), which its loader read (prefetch.pkl
# unpickled): planted too, in case a reader still opened them.
OLD_FORMAT_FILES = (
    "buffer/prefetch.pkl",
    "buffer/buffer_metadata.json",
    "buffer/writer/metadata.json",
    "buffer/storage/meta.json",
    "buffer/storage/next/meta.json",
    "buffer/storage/storage_metadata.json",
)


def test_no_file_of_a_dataset_folder_runs_code(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    source = robomimic_file(tmp_path / "lift.hdf5")
    import_command = ["data", "import", "robomimic", str(source), "--obs-keys", "state", "--out"]
    assert run([*import_command, str(tmp_path / "made")]) is None
    (made,) = (tmp_path / "made").iterdir()
    arrays = {p.relative_to(made).as_posix() for p in made.rglob("*.memmap")}
    others = {p.relative_to(made).as_posix() for p in made.rglob("*") if p.is_file()} - arrays
    assert others, "a dataset folder has files that are not arrays"
    ended = {}  # planted file -> what each command ended with
    for i, rel in enumerate(sorted(others | set(OLD_FORMAT_FILES))):
        out = tmp_path / f"received-{i}"  # an --out folder holding the received dataset under its own name
        folder = out / made.name
        shutil.copytree(made, folder)
        (folder / rel).parent.mkdir(parents=True, exist_ok=True)
        (folder / rel).write_bytes(pickle_payload(tmp_path / f"code-ran-from-{i}"))
        if rel != "digest.json":
            (folder / "digest.json").write_text(json.dumps(content_digest(folder)))  # what a sender can do
        info = run(["data", "info", str(folder)])
        train = run(["train", f"data.path={folder}", "eval.rollouts=1", f"runs_root={tmp_path / 'runs'}"])
        again = run([*import_command, str(out)])  # the same import finds the folder under its name
        (folder / "digest.json").unlink(missing_ok=True)
        seal = run(["data", "seal", str(folder)])
        ended[rel] = (folder, info, train, again, seal)
    ran = [rel for i, rel in enumerate(ended) if (tmp_path / f"code-ran-from-{i}").exists()]
    assert ran == [], f"payloads planted in {ran} ran"
    for rel, (folder, info, train, again, seal) in ended.items():
        if rel in others:  # a file the format reads: refused, named
            assert info.startswith(f"tar-rl data info: {folder / rel}"), info
            assert train.startswith(f"tar-rl train: data.path={folder}: {folder / rel}"), train
        else:  # a file the format does not read: the dataset is read, then the rollouts are refused
            assert info is None
            assert train.startswith(f"tar-rl train: data.path={folder} holds robomimic demonstrations"), train
        assert again is None  # found, or replaced by a new import
        assert seal is None or seal.startswith("tar-rl data seal: "), seal
    assert not (tmp_path / "runs").exists()  # no command started a run
