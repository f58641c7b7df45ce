"""Hypothesis property tests of ``tar_weights`` (paper Eqs. 3-8) over random padded batches.

Losses are float32 values in [0, 100] with deliberate ties; masks are random (segments with
no valid step included). Each property holds for both cap modes and a few gamma / w_max.
"""

from __future__ import annotations

import math

import torch
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from tar_rl import tar_weights

SETTINGS = settings(max_examples=60, deadline=None)


# Floats in a sane range, mixed with a few repeated values so ties and equal segments occur.
_VALUE = st.one_of(
    st.floats(0.0, 100.0, width=32, allow_subnormal=False),
    st.sampled_from([0.0, 0.5, 1.0, 7.25, 100.0]),
)


@st.composite
def batches(draw, min_valid: int = 0):
    """A ``[B, L]`` float32 loss tensor and a bool mask; each row has >= ``min_valid`` valid steps."""
    b = draw(st.integers(1, 6))
    n = draw(st.integers(max(1, min_valid), 24))
    vals = draw(st.lists(st.lists(_VALUE, min_size=n, max_size=n), min_size=b, max_size=b))
    rows = []
    for _ in range(b):
        row = draw(st.lists(st.booleans(), min_size=n, max_size=n))
        for i in range(min_valid):  # force the first min_valid steps valid
            row[i] = True
        rows.append(row)
    return torch.tensor(vals, dtype=torch.float32), torch.tensor(rows, dtype=torch.bool)


@st.composite
def tar_params(draw):
    cap = draw(st.sampled_from(["paper", "exact"]))
    gamma = draw(st.sampled_from([0.25, 1.0, 2.0, 4.0]))
    w_max = draw(st.sampled_from([1.0, 1.5, 3.0, 10.0, math.inf]))
    return {"cap": cap, "gamma": gamma, "w_max": w_max}


def _valid_rows(valid: torch.Tensor):
    return [b for b in range(valid.shape[0]) if valid[b].any()]


@SETTINGS
@given(batch=batches(), params=tar_params())
def test_nonnegative_finite_and_zero_on_padding(batch, params):
    losses, valid = batch
    w = tar_weights(losses, valid, **params)
    assert w.shape == losses.shape and w.dtype == losses.dtype
    assert torch.isfinite(w).all()
    assert (w >= 0).all()
    assert (w[~valid] == 0).all()
    assert (w[~valid.any(-1)] == 0).all()  # segments without valid steps are all zero


@SETTINGS
@given(batch=batches(), params=tar_params(), mix=st.sampled_from([0.0, 0.4, 1.0]))
def test_unit_mean_over_valid_steps(batch, params, mix):
    losses, valid = batch
    w = tar_weights(losses, valid, mix=mix, **params).double()
    for b in _valid_rows(valid):
        mean = float(w[b][valid[b]].mean())
        assert abs(mean - 1.0) <= 1e-4, (b, mean)


@st.composite
def spread_batches(draw):
    """Batches where every segment with >= 2 valid steps has a std of at least 1e-3."""
    losses, valid = draw(batches())
    for b in range(losses.shape[0]):
        x = losses[b][valid[b]].double()
        if x.numel() >= 2:
            assume(float(x.std(unbiased=False)) >= 1e-3)
    return losses, valid


@SETTINGS
@given(
    batch=spread_batches(),
    params=tar_params(),
    a=st.floats(0.1, 10.0),
    shift=st.floats(-5.0, 5.0),
    dtype=st.sampled_from([torch.float64, torch.float32]),
)
def test_invariant_to_positive_affine_maps(batch, params, a, shift, dtype):
    # z-scores are invariant to l -> a l + b (a > 0) up to eps; use a small eps so that only
    # the rounding of a l + b matters. In float32 that rounding is ~1e-7 of |a l + b| <= 1005 a,
    # i.e. up to ~1e-4 / std in the z-scores: the tolerance scales with it.
    losses, valid = batch
    x = losses.to(dtype)
    kw = {**params, "eps": 1e-12}
    w1 = tar_weights(x, valid, **kw)
    w2 = tar_weights(a * x + shift, valid, **kw)
    tol = 1e-9 if dtype == torch.float64 else 2e-2
    if params["cap"] == "exact":
        tol = max(tol, 1e-5)
    torch.testing.assert_close(w2.double(), w1.double(), rtol=tol, atol=tol)


@SETTINGS
@given(batch=batches(), params=tar_params(), data=st.data())
def test_permutation_equivariance_within_a_segment(batch, params, data):
    losses, valid = batch
    n = losses.shape[-1]
    perms = [data.draw(st.permutations(range(n))) for _ in range(losses.shape[0])]
    idx = torch.tensor(perms, dtype=torch.long)
    w = tar_weights(losses, valid, **params)
    w_perm = tar_weights(losses.gather(-1, idx), valid.gather(-1, idx), **params)
    torch.testing.assert_close(w_perm, w.gather(-1, idx), rtol=1e-4, atol=1e-5)


@SETTINGS
@given(batch=batches(), gamma=st.sampled_from([0.25, 1.0, 2.0, 4.0, 8.0]), w_max=st.sampled_from([1.0, 1.2, 2.0, 3.0]))
def test_exact_cap_holds(batch, gamma, w_max):
    losses, valid = batch
    w = tar_weights(losses, valid, gamma=gamma, w_max=w_max, cap="exact")
    assert float(w.max()) <= w_max * (1 + 1e-5)
    for b in _valid_rows(valid):
        assert abs(float(w[b][valid[b]].double().mean()) - 1.0) <= 1e-4


@SETTINGS
@given(batch=batches(), params=tar_params())
def test_no_gradient_through_weights(batch, params):
    losses, valid = batch
    losses = losses.clone().requires_grad_(True)
    w = tar_weights(losses, valid, **params)
    assert not w.requires_grad and w.grad_fn is None
    (g,) = torch.autograd.grad((w * losses).sum(), losses)
    torch.testing.assert_close(g, w, rtol=0, atol=0)


@SETTINGS
@given(batch=batches(), params=tar_params())
def test_vanishing_temperature_gives_uniform(batch, params):
    losses, valid = batch
    params = {**params, "gamma": 1e-6}
    w = tar_weights(losses, valid, **params)
    torch.testing.assert_close(w, valid.float(), rtol=0, atol=1e-4)


@SETTINGS
@given(batch=batches(), params=tar_params(), mix=st.sampled_from([0.3, 1.0]))
def test_monotone_in_the_loss_within_a_segment(batch, params, mix):
    losses, valid = batch
    w = tar_weights(losses, valid, mix=mix, **params).double()
    for b in _valid_rows(valid):
        x = losses[b][valid[b]].tolist()
        y = w[b][valid[b]].tolist()
        for i in range(len(x)):
            for j in range(len(x)):
                tol = 1e-6 * max(1.0, y[i], y[j])
                if x[i] < x[j]:
                    assert y[i] <= y[j] + tol, (x[i], x[j], y[i], y[j])
                elif x[i] == x[j]:
                    assert abs(y[i] - y[j]) <= tol, (x[i], y[i], y[j])


@SETTINGS
@given(batch=batches(), params=tar_params())
def test_mix_zero_gives_ones(batch, params):
    losses, valid = batch
    w = tar_weights(losses, valid, mix=0.0, **params)
    torch.testing.assert_close(w, valid.float(), rtol=0, atol=1e-6)
    w_t = tar_weights(losses, valid, mix=torch.tensor(0.0), **params)
    torch.testing.assert_close(w_t, valid.float(), rtol=0, atol=1e-6)
