"""Shared test settings: quiet torchrl's INFO logging, one intra-op thread, GPU tests only with a GPU."""

from __future__ import annotations

import logging

import pytest
import torch

logging.getLogger("torchrl").setLevel(logging.WARNING)


def pytest_collection_modifyitems(config, items):
    if torch.cuda.is_available():
        return
    skip = pytest.mark.skip(reason="needs a CUDA device")
    for item in items:
        if "gpu" in item.keywords:
            item.add_marker(skip)


@pytest.fixture(scope="session")
def data_root(tmp_path_factory):
    """One dataset folder for the whole session: tiny datasets are collected once and reused."""
    return tmp_path_factory.mktemp("datasets")


@pytest.fixture(autouse=True, scope="module")
def _single_thread():
    """Run each test module on one intra-op thread, restored afterwards.

    On a 2-core runner torch's softmax wakes its OpenMP pool for a tiny tensor and pays
    ~10 ms per call when called from Python with pauses in between (as hypothesis does);
    single-threaded it takes microseconds. The results do not depend on the thread count.
    """
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)
