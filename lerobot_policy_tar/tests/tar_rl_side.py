"""tar-rl's side of the plugin's tests, run in tar-rl's own environment (``.venv/bin/python``), not the plugin's.

``python tar_rl_side.py DATASET OUT`` reads the tar-rl dataset folder ``DATASET`` with tar-rl's own loader and writes
into ``OUT``:

* ``arrays.npz``: the entries the export reads (``observation``, ``action``, ``episode``, ``step``, ``task_id``) as
  tar-rl's loader gives them, and ``metadata.json``'s task names and instructions in ``tasks.json``: the reference
  of the export's round trip;
* ``bad/<name>``: copies of ``DATASET`` that tar-rl refuses (unsealed, an older and a newer format version, a NaN
  sealed into an entry, a byte changed after sealing), made with tar-rl's own ``seal``, and ``messages.json``: for
  each, the path and the one-line message of tar-rl's ``load_dataset`` refusing it.
"""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np

from tar_rl.data import DatasetError, load_dataset
from tar_rl.data.checks import DIGEST_FILE, METADATA_FILE, seal


def _set_version(folder: Path, version: int) -> None:
    meta = json.loads((folder / METADATA_FILE).read_text())
    meta["format_version"] = version
    (folder / METADATA_FILE).write_text(json.dumps(meta))


def _write_nan(folder: Path, step: int) -> None:
    """A NaN at ``observation[step, 0]``, then a new content digest over the changed file (sealed as it is)."""
    dims = json.loads((folder / METADATA_FILE).read_text())["keys"]["observation"]["shape"][0]
    file = folder / "buffer" / "storage" / "observation.memmap"
    data = bytearray(file.read_bytes())
    data[step * dims * 4 : step * dims * 4 + 4] = np.array([np.nan], dtype="<f4").tobytes()
    file.write_bytes(bytes(data))
    (folder / DIGEST_FILE).unlink()
    seal(folder)


def _flip_byte(folder: Path) -> None:
    file = folder / "buffer" / "storage" / "action.memmap"
    data = bytearray(file.read_bytes())
    data[0] ^= 0x01
    file.write_bytes(bytes(data))


VARIANTS = {
    "unsealed": lambda folder: (folder / DIGEST_FILE).unlink(),
    "format_3": lambda folder: _set_version(folder, 3),
    "format_5": lambda folder: _set_version(folder, 5),
    "nan": lambda folder: _write_nan(folder, 5),
    "edited": _flip_byte,
}


def main(dataset: Path, out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    data = load_dataset(dataset)
    arrays = {name: data.data[name].numpy() for name in ("observation", "action", "episode", "step", "task_id")}
    np.savez(out / "arrays.npz", **arrays)
    meta = data.metadata
    (out / "tasks.json").write_text(
        json.dumps({"task_names": meta["task_names"], "instructions": meta["instructions"]})
    )
    messages = {}
    for name, spoil in VARIANTS.items():
        folder = (out / "bad" / name).resolve()
        shutil.copytree(dataset, folder)
        spoil(folder)
        try:
            load_dataset(folder)
        except DatasetError as error:
            messages[name] = {"path": str(folder), "message": str(error)}
        else:
            raise AssertionError(f"tar-rl loads the {name} variant")
    (out / "messages.json").write_text(json.dumps(messages, indent=1))


if __name__ == "__main__":
    main(Path(sys.argv[1]).resolve(), Path(sys.argv[2]))
