"""A small robomimic-layout HDF5 file, imported in milliseconds: data for tests of what reads a dataset."""

from __future__ import annotations

import json

import h5py
import numpy as np

LENGTHS = (6, 5)  # steps of its two demonstrations: the longest episode has 6


def robomimic_file(path, seed: int = 0):
    """Two demonstrations of the task ``Lift`` (``obs/state`` 3-d, actions 2-d in [-1, 1]) at ``path``."""
    rng = np.random.default_rng(seed)
    with h5py.File(path, "w") as f:
        f.create_group("data").attrs["env_args"] = json.dumps({"env_name": "Lift", "type": 1, "env_kwargs": {}})
        for i, n in enumerate(LENGTHS):
            f[f"data/demo_{i}/obs/state"] = rng.normal(size=(n, 3))
            f[f"data/demo_{i}/actions"] = rng.uniform(-1, 1, size=(n, 2))
            f[f"data/demo_{i}/dones"] = np.r_[np.zeros(n - 1), 1].astype(np.int64)
            f[f"data/demo_{i}/rewards"] = np.zeros(n)
    return path
