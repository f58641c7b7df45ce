"""Shared test settings: quiet torchrl's INFO logging, skip GPU tests where there is no GPU."""

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
