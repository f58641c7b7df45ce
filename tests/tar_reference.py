"""An independent, plain-Python reading of the paper's Eqs. 3-8, one segment at a time.

Written from the paper's text with lists and ``math`` only, so that tests can compare the
vectorised torch code against something that shares none of its code.
"""

from __future__ import annotations

import math


def ref_segment_weights(losses, valid, *, gamma=1.0, w_max=3.0, eps=1e-8, mix=1.0, cap="paper"):
    """TAR weights of one segment (lists of floats and bools), as the paper defines them."""
    idx = [t for t, v in enumerate(valid) if v]
    out = [0.0] * len(losses)
    m = len(idx)
    if m == 0:
        return out
    x = [float(losses[t]) for t in idx]
    mu = sum(x) / m  # Eq. 4
    sigma = math.sqrt(sum((v - mu) ** 2 for v in x) / m)  # population std
    s = [(v - mu) / (sigma + eps) for v in x]  # Eq. 5
    top = max(gamma * v for v in s)
    e = [math.exp(gamma * v - top) for v in s]  # Eq. 6
    w = [m * v / sum(e) for v in e]  # Eq. 7
    w = [(1 - mix) + mix * v for v in w]  # Sec. III-B, before the cap
    if math.isfinite(w_max):
        if cap == "paper":  # Eq. 8
            clipped = [min(v, w_max) for v in w]
            w = [m * v / sum(clipped) for v in clipped]
        else:  # clip and rescale the unclipped ones until nothing moves
            fixed = [False] * m
            for _ in range(m + 1):
                free_mass = m - w_max * sum(fixed)
                free_sum = sum(v for v, f in zip(w, fixed) if not f)
                w = [w_max if f else v * free_mass / free_sum for v, f in zip(w, fixed)]
                over = [not f and v > w_max for v, f in zip(w, fixed)]
                if not any(over):
                    break
                fixed = [f or o for f, o in zip(fixed, over)]
    for t, v in zip(idx, w):
        out[t] = v
    return out


def ref_weights(losses, valid, **kwargs):
    """Row by row over nested lists ``[B][L]``."""
    return [ref_segment_weights(row, mask, **kwargs) for row, mask in zip(losses, valid)]


def ref_segment_loss(losses, weights, valid):
    """Eq. 2 averaged over the segments with a valid step."""
    per_segment = []
    for row, w, mask in zip(losses, weights, valid):
        m = sum(mask)
        if m:
            per_segment.append(sum(l * wt for l, wt, v in zip(row, w, mask) if v) / m)
    return sum(per_segment) / len(per_segment) if per_segment else 0.0
