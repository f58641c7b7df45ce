"""An independent, plain-Python reading of the paper's Eqs. 3-8, one segment at a time.

Written from the paper's text with lists and ``math`` only (no torch in the arithmetic), so that
tests can compare the vectorised code against something that shares none of its code. The
reference itself is checked against hand-worked values in ``test_weights_spec.py``.
"""

from __future__ import annotations

import math

import torch


def ref_exact_cap(w: list[float], w_max: float) -> list[float]:
    """Unit-mean ``min(c * w, w_max)`` by the iterative clip-and-rescale (active-set) method.

    Start with nothing clipped; rescale the free weights so that the total is ``M``; clip every
    free weight that now exceeds ``w_max``; repeat until nothing new is clipped. ``c`` only
    grows from round to round, so a weight clipped once stays clipped in the answer.
    """
    m = len(w)
    clipped: set[int] = set()
    c = 1.0
    while True:
        free = [i for i in range(m) if i not in clipped]
        mass = math.fsum(w[i] for i in free)
        if not free or mass <= 0:
            break
        c = (m - len(clipped) * w_max) / mass
        new = {i for i in free if c * w[i] > w_max}
        if not new:
            break
        clipped |= new
    return [w_max if i in clipped else c * w[i] for i in range(m)]


def ref_precap(losses, valid, *, gamma=1.0, eps=1e-8, mix=1.0) -> list[float]:
    """Eqs. 4-7 and the mixing of Sec. III-B on the valid steps of one segment (a list of M)."""
    x = [float(v) for v, ok in zip(losses, valid) if ok]
    m = len(x)
    if m == 0:
        return []
    mu = math.fsum(x) / m  # Eq. 4, mean over valid steps
    sigma = math.sqrt(math.fsum((v - mu) ** 2 for v in x) / m)  # Eq. 4, POPULATION std
    s = [(v - mu) / (sigma + eps) for v in x]  # Eq. 5
    logits = [gamma * v for v in s]  # Eq. 6
    top = max(logits)
    e = [math.exp(v - top) for v in logits]
    z = math.fsum(e)
    p = [v / z for v in e]
    w = [m * v for v in p]  # Eq. 7
    return [(1.0 - mix) * 1.0 + mix * v for v in w]  # Sec. III-B: mix before the cap


def ref_tar_segment(losses, valid, *, gamma=1.0, w_max=3.0, eps=1e-8, mix=1.0, cap="paper") -> list[float]:
    """TAR weights of one segment (list of length L), 0 on padding."""
    w = ref_precap(losses, valid, gamma=gamma, eps=eps, mix=mix)
    m = len(w)
    if m and math.isfinite(w_max):
        if cap == "paper":  # Eq. 8: clip once, renormalise to unit mean
            h = [min(v, w_max) for v in w]
            total = math.fsum(h)
            w = [m * v / total for v in h]
        else:
            w = ref_exact_cap(w, w_max)
    out = [0.0] * len(losses)
    it = iter(w)
    for t, ok in enumerate(valid):
        if ok:
            out[t] = next(it)
    return out


def ref_tar(losses: torch.Tensor, valid: torch.Tensor, **kw) -> torch.Tensor:
    """Apply ``ref_tar_segment`` to every row of a ``[..., L]`` pair; float64 result."""
    rows_l = losses.detach().double().reshape(-1, losses.shape[-1]).tolist()
    rows_v = valid.reshape(-1, valid.shape[-1]).tolist()
    out = [ref_tar_segment(lr, vr, **kw) for lr, vr in zip(rows_l, rows_v)]
    return torch.tensor(out, dtype=torch.float64).reshape(losses.shape)


def ref_weights(losses, valid, **kwargs) -> list[list[float]]:
    """``ref_tar_segment`` row by row over nested lists ``[B][L]``."""
    return [ref_tar_segment(row, mask, **kwargs) for row, mask in zip(losses, valid)]


def ref_segment_loss(losses, weights, valid) -> float:
    """Eq. 2 per segment, averaged over the segments that have a valid step."""
    per_segment = []
    for row, w, mask in zip(losses, weights, valid):
        m = sum(mask)
        if m:
            per_segment.append(math.fsum(loss * wt for loss, wt, ok in zip(row, w, mask) if ok) / m)
    return math.fsum(per_segment) / len(per_segment) if per_segment else 0.0
