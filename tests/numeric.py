"""Small tensor helpers the weighting tests share: float64 tensors, bool masks, and a tight comparison."""

from __future__ import annotations

import torch


def t64(x) -> torch.Tensor:
    return torch.tensor(x, dtype=torch.float64)


def mask(x) -> torch.Tensor:
    return torch.tensor(x, dtype=torch.bool)


def close(actual: torch.Tensor, expected, *, rtol=1e-9, atol=1e-12) -> None:
    torch.testing.assert_close(actual.double(), torch.as_tensor(expected, dtype=torch.float64), rtol=rtol, atol=atol)
