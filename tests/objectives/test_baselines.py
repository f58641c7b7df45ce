"""The baselines from the literature (``tilted``, ``truncate``, ``keyframe``, ``focal``): specification and properties.

Every expected value is worked out by hand in the comments or computed here with plain Python
(lists and ``math``) from the rule as the issue states it; none comes from the code under test.
"""

from __future__ import annotations

import dataclasses
import math
from types import SimpleNamespace

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from numeric import close, mask, t64
from objective_helpers import tar_loss
from tensordict.nn import TensorDictModule
from torchrl.objectives import BCLoss

from tar_rl.objectives import (
    WEIGHTINGS,
    focal_weights,
    keyframe_count,
    keyframe_weights,
    tilted_weights,
    truncate_count,
    truncate_weights,
)

BASELINES = ("tilted", "truncate", "keyframe", "focal")


def full(n: int) -> torch.Tensor:
    return torch.ones(n, dtype=torch.bool)


# ---------------------------------------------------------------------------------------------
# Plain-Python readings of the four rules (one segment's valid losses at a time)
# ---------------------------------------------------------------------------------------------


def ref_tilted(x: list[float], t: float) -> list[float]:
    mean = math.fsum(x) / len(x)
    s = [t * v / mean if mean > 0 else 0.0 for v in x]
    top = max(s)
    e = [math.exp(v - top) for v in s]
    return [len(x) * v / math.fsum(e) for v in e]


def ref_selected(x: list[float], k: int) -> list[float]:
    """Share of each step in the k highest losses; a tie straddling the boundary shares equally."""
    out = []
    for v in x:
        above = sum(1 for u in x if u > v)
        equal = sum(1 for u in x if u == v)
        out.append(min(1.0, max(0.0, (k - above) / equal)))
    return out


def ref_truncate(x: list[float], q: float) -> list[float]:
    n = len(x)
    k = min(math.floor(q * n + 1e-9), n - 1)
    return [(1 - s) * n / (n - k) for s in ref_selected(x, k)]


def ref_keyframe(x: list[float], f: float, big_k: float) -> list[float]:
    n = len(x)
    k = min(max(math.floor(f * n + 0.5 + 1e-9), 1), n)
    return [(1 + (big_k - 1) * s) * n / (n + (big_k - 1) * k) for s in ref_selected(x, k)]


def ref_exact_cap(w: list[float], w_max: float) -> list[float]:
    """Clip-and-rescale until nothing new is clipped (the active-set method)."""
    n, clipped = len(w), set()
    while True:
        free = [i for i in range(n) if i not in clipped]
        mass = math.fsum(w[i] for i in free)
        if not free or mass <= 0:
            break
        c = (n - len(clipped) * w_max) / mass
        new = {i for i in free if c * w[i] > w_max}
        if not new:
            break
        clipped |= new
    return [w_max if i in clipped else c * w[i] for i in range(n)]


def ref_focal(x: list[float], beta: float, w_max: float, mix: float = 1.0) -> list[float]:
    n = len(x)
    if max(x) <= 0:
        return [1.0] * n
    mean = math.fsum(x) / n
    r = [(v / mean) ** beta for v in x]
    total = math.fsum(r)
    w = [(1 - mix) + mix * n * v / total for v in r]
    return ref_exact_cap(w, w_max) if math.isfinite(w_max) else w


# ---------------------------------------------------------------------------------------------
# tilted
# ---------------------------------------------------------------------------------------------


class TestTilted:
    def test_hand_values_with_padding(self):
        # valid [0, 1, 2]: mean 1, scores 0, 1, 2; w = 3 e^s / (1 + e + e^2)
        z = 1 + math.e + math.e**2
        losses = t64([0.0, 1.0, 2.0, math.nan])
        w = tilted_weights(losses, mask([1, 1, 1, 0]))
        close(w, [3 / z, 3 * math.e / z, 3 * math.e**2 / z, 0.0])
        # tilt 2: w = 3 e^{2s} / (1 + e^2 + e^4)
        z2 = 1 + math.e**2 + math.e**4
        close(tilted_weights(losses, mask([1, 1, 1, 0]), tilt=2.0), [3 / z2, 3 * math.e**2 / z2, 3 * math.e**4 / z2, 0])

    def test_scale_free(self):
        # [0, 10, 20] has mean 10: the same scores as [0, 1, 2]
        z = 1 + math.e + math.e**2
        close(tilted_weights(t64([0.0, 10.0, 20.0]), full(3)), [3 / z, 3 * math.e / z, 3 * math.e**2 / z])

    def test_one_step_equal_losses_zero_losses_and_empty_segment(self):
        losses = t64([[5.0, 1.0, 2.0], [4.0, 4.0, 4.0], [0.0, 0.0, 0.0], [1.0, 2.0, 3.0]])
        valid = mask([[1, 0, 0], [1, 1, 1], [1, 1, 1], [0, 0, 0]])
        close(tilted_weights(losses, valid), [[1, 0, 0], [1, 1, 1], [1, 1, 1], [0, 0, 0]])

    def test_matches_plain_reference(self):
        x = [0.3, 0.01, 1.7, 0.9, 0.05]
        close(tilted_weights(t64(x), full(5), tilt=0.7), ref_tilted(x, 0.7))


# ---------------------------------------------------------------------------------------------
# truncate
# ---------------------------------------------------------------------------------------------


class TestTruncate:
    def test_default_drops_the_top_step_of_sixteen(self):
        # n = 16, q = 0.1: floor(1.6) = 1 step dropped; the others weigh 16/15
        x = [float(v) for v in (3, 1, 4, 1, 5, 9, 2, 6, 5, 3, 5, 8, 9.5, 7, 9.25, 3)]
        expected = [16 / 15] * 16
        expected[12] = 0.0  # 9.5 is the largest
        close(truncate_weights(t64(x), full(16)), expected)

    @pytest.mark.parametrize(
        ("n", "q", "dropped"),
        [
            (9, 0.1, 0),
            (10, 0.1, 1),
            (19, 0.1, 1),
            (20, 0.1, 2),
            (100, 0.29, 29),
            (3, 0.5, 1),
            (2, 0.5, 1),
            (1, 0.9, 0),
            (4, 0.0, 0),
            (16, 0.999, 15),
            (0, 0.5, 0),
        ],
    )
    def test_count_rounds_down(self, n, q, dropped):
        assert float(truncate_count(torch.tensor([n]), q)[0]) == dropped

    def test_short_segment_drops_nothing_and_padding(self):
        # 5 valid steps, q = 0.1: floor(0.5) = 0
        losses = t64([0.5, 9.0, 0.1, 2.0, 1.0, math.inf, -math.inf])
        close(truncate_weights(losses, mask([1, 1, 1, 1, 1, 0, 0])), [1, 1, 1, 1, 1, 0, 0])

    def test_a_tie_at_the_boundary_shares_the_dropped_step(self):
        # [1, 3, 3, 2], q = 0.25: k = 1; the two 3s each lose half: (1 - 1/2) * 4/3 = 2/3
        close(truncate_weights(t64([1.0, 3.0, 3.0, 2.0]), full(4), fraction=0.25), [4 / 3, 2 / 3, 2 / 3, 4 / 3])

    def test_equal_losses_one_step_and_empty_segment(self):
        losses = t64([[2.0] * 4, [7.0, 0.0, 0.0, 0.0], [1.0, 2.0, 3.0, 4.0]])
        valid = mask([[1, 1, 1, 1], [1, 0, 0, 0], [0, 0, 0, 0]])
        close(truncate_weights(losses, valid, fraction=0.5), [[1, 1, 1, 1], [1, 0, 0, 0], [0, 0, 0, 0]])

    def test_negative_losses_are_ranked_too(self):
        # q = 0.5 of 4: the two largest (-1, 0.5) weigh 0, the others 2
        close(truncate_weights(t64([-3.0, -1.0, 0.5, -2.0]), full(4), fraction=0.5), [2, 0, 0, 2])

    def test_matches_plain_reference(self):
        x = [0.2, 0.9, 0.9, 0.4, 0.9, 0.1, 0.3, 0.6, 0.9, 0.5, 0.05, 0.7]
        close(truncate_weights(t64(x), full(12), fraction=0.3), ref_truncate(x, 0.3))


# ---------------------------------------------------------------------------------------------
# keyframe
# ---------------------------------------------------------------------------------------------


class TestKeyframe:
    def test_hand_values(self):
        # n = 5, f = 0.3: floor(1.5 + 0.5) = 2 keyframes (0.9 and 0.5); K = 5: 25/13 and 5/13
        got = keyframe_weights(t64([0.1, 0.5, 0.2, 0.9, 0.3, 4.0]), mask([1, 1, 1, 1, 1, 0]))
        close(got, [5 / 13, 25 / 13, 5 / 13, 25 / 13, 5 / 13, 0])

    @pytest.mark.parametrize(
        ("n", "f", "selected"),
        [
            (5, 0.3, 2),
            (16, 0.3, 5),
            (3, 0.1, 1),
            (1, 0.3, 1),
            (2, 0.25, 1),
            (6, 0.25, 2),
            (10, 0.25, 3),
            (4, 0.99, 4),
            (100, 0.285, 29),
            (10, 0.32, 3),
            (16, 0.2, 3),
            (4, 0.3, 1),
            (7, 0.35, 2),
            (0, 0.3, 0),
        ],
    )
    def test_count_rounds_half_up_and_selects_at_least_one(self, n, f, selected):
        assert float(keyframe_count(torch.tensor([n]), f)[0]) == selected

    def test_factor_and_fraction(self):
        # n = 4, f = 0.5: 2 keyframes (the 8 and the 6); K = 2: 2 * 4 / 6 = 4/3, others 2/3
        got = keyframe_weights(t64([8.0, 1.0, 6.0, 2.0]), full(4), fraction=0.5, factor=2.0)
        close(got, [4 / 3, 2 / 3, 4 / 3, 2 / 3])
        close(keyframe_weights(t64([8.0, 1.0, 6.0, 2.0]), full(4), factor=1.0), [1, 1, 1, 1])

    def test_a_tie_at_the_boundary_shares_the_keyframe(self):
        # n = 3, f = 0.3: 1 keyframe; the two 5s share it: (1 + 4 * 1/2) * 3 / 7 = 9/7; the 1: 3/7
        close(keyframe_weights(t64([5.0, 1.0, 5.0]), full(3)), [9 / 7, 3 / 7, 9 / 7])

    def test_one_step_equal_losses_and_empty_segment(self):
        losses = t64([[3.0, 0.0, 0.0], [2.0, 2.0, 2.0], [1.0, 2.0, 3.0]])
        valid = mask([[1, 0, 0], [1, 1, 1], [0, 0, 0]])
        close(keyframe_weights(losses, valid), [[1, 0, 0], [1, 1, 1], [0, 0, 0]])

    def test_matches_plain_reference(self):
        x = [0.2, 0.9, 0.9, 0.4, 0.9, 0.1, 0.3, 0.6, 0.9, 0.5, 0.05, 0.7, 0.0, 1.2]
        close(keyframe_weights(t64(x), full(14), fraction=0.2, factor=3.0), ref_keyframe(x, 0.2, 3.0))


# ---------------------------------------------------------------------------------------------
# focal
# ---------------------------------------------------------------------------------------------


class TestFocal:
    def test_hand_values(self):
        # [1, 2, 3, 10]: mean 4, ratios 1/4, 1/2, 3/4, 5/2 (unit mean); under the cap 3
        losses = t64([1.0, 2.0, 3.0, 10.0, math.nan])
        valid = mask([1, 1, 1, 1, 0])
        close(focal_weights(losses, valid), [0.25, 0.5, 0.75, 2.5, 0])
        # w_max = 2: 2.5 -> 2; the rest carry 2 with c = 2 / 1.5: 1/3, 2/3, 1
        close(focal_weights(losses, valid, w_max=2.0), [1 / 3, 2 / 3, 1.0, 2.0, 0])
        # beta = 2: 4 * [1, 4, 9, 100] / 114; w_max = 1.5 clips 100, then 9 (c = 2.5 / 14 gives 9c > 1.5),
        # and the rest carry 1 with c = 1 / 5: 0.2, 0.8
        close(focal_weights(losses, valid, beta=2.0, w_max=1.5), [0.2, 0.8, 1.5, 1.5, 0])
        close(focal_weights(losses, valid, beta=2.0, w_max=math.inf), [4 / 114, 16 / 114, 36 / 114, 400 / 114, 0])

    def test_zero_losses(self):
        # [0, 0, 0, 4]: w = [0, 0, 0, 4]; the cap 3 leaves 1 that the zeros share: 1/3 each
        close(focal_weights(t64([0.0, 0.0, 0.0, 4.0]), full(4)), [1 / 3, 1 / 3, 1 / 3, 3])
        # [0, 1, 3] under no binding cap: 0, 3/4, 9/4
        close(focal_weights(t64([0.0, 1.0, 3.0]), full(3)), [0, 0.75, 2.25])

    def test_beta_zero_one_step_equal_losses_zero_segment_and_empty_segment(self):
        losses = t64([[1.0, 2.0, 9.0], [5.0, 1.0, 1.0], [3.0, 3.0, 3.0], [0.0, 0.0, 0.0], [1.0, 2.0, 3.0]])
        valid = mask([[1, 1, 1], [1, 0, 0], [1, 1, 1], [1, 1, 1], [0, 0, 0]])
        expected = [[1, 1, 1], [1, 0, 0], [1, 1, 1], [1, 1, 1], [0, 0, 0]]
        close(focal_weights(losses, valid, beta=0.0), expected)
        close(focal_weights(losses[1:], valid[1:], beta=3.0), expected[1:])

    def test_mix_is_applied_before_the_cap(self):
        # mix 0.5 of [1/4, 1/2, 3/4, 5/2]: [0.625, 0.75, 0.875, 1.75]; cap 1.5: the rest carry 2.5 over 2.25
        c = 2.5 / 2.25
        got = focal_weights(t64([1.0, 2.0, 3.0, 10.0]), full(4), w_max=1.5, mix=0.5)
        close(got, [0.625 * c, 0.75 * c, 0.875 * c, 1.5])
        close(got, ref_focal([1.0, 2.0, 3.0, 10.0], 1.0, 1.5, mix=0.5))

    def test_matches_plain_reference(self):
        x = [0.2, 0.9, 0.01, 0.4, 2.9, 0.1, 0.3, 0.6]
        for beta, w_max in ((0.5, 3.0), (1.0, 1.2), (3.0, 2.0), (2.0, math.inf)):
            close(focal_weights(t64(x), full(8), beta=beta, w_max=w_max), ref_focal(x, beta, w_max), rtol=1e-8)


# ---------------------------------------------------------------------------------------------
# Shared behaviour
# ---------------------------------------------------------------------------------------------

FUNCTIONS = {
    "tilted": tilted_weights,
    "truncate": truncate_weights,
    "keyframe": keyframe_weights,
    "focal": focal_weights,
}


@pytest.mark.parametrize("name", BASELINES)
def test_mix_blends_with_uniform(name):
    # tilted, truncate and keyframe have no cap: (1 - a) + a * w on the valid steps
    losses, valid = t64([0.5, 2.0, 0.1, 3.0, 1.0, 0.7, 9.0]), mask([1, 1, 1, 1, 1, 1, 0])
    fn = FUNCTIONS[name]
    full_w = fn(losses, valid)
    close(fn(losses, valid, mix=0.0), valid.double())
    close(fn(losses, valid, mix=torch.tensor(0.0)), valid.double())
    if name != "focal":  # focal's cap is applied after the blend (tested above)
        close(fn(losses, valid, mix=0.25), (0.75 + 0.25 * full_w) * valid)


@pytest.mark.parametrize("name", BASELINES)
def test_leading_dims_half_precision_and_no_gradient(name):
    g = torch.Generator().manual_seed(0)
    losses = torch.rand(2, 3, 8, generator=g)
    valid = torch.rand(2, 3, 8, generator=g) > 0.3
    fn = FUNCTIONS[name]
    w = fn(losses, valid)
    flat = fn(losses.reshape(6, 8), valid.reshape(6, 8))
    torch.testing.assert_close(w.reshape(6, 8), flat)
    for dtype in (torch.bfloat16, torch.float16):
        half = fn(losses.to(dtype), valid)
        assert half.dtype == dtype
        # weighted in float32 (the rounded losses), then cast: equal up to the final rounding
        torch.testing.assert_close(half.float(), fn(losses.to(dtype).float(), valid), rtol=1e-2, atol=1e-2)
    grad_losses = losses.clone().requires_grad_(True)
    w = fn(grad_losses, valid)
    assert not w.requires_grad and w.grad_fn is None


@pytest.mark.parametrize("name", ["tilted", "focal"])
def test_negative_losses_are_refused_by_the_mean_normalised_ones(name):
    with pytest.raises(ValueError, match=rf"{name} weighting .* needs per-step losses >= 0"):
        FUNCTIONS[name](t64([1.0, -0.5, 2.0]), full(3))
    FUNCTIONS[name](t64([1.0, 2.0, -7.0]), mask([1, 1, 0]))  # padding may hold anything


@pytest.mark.parametrize("name", BASELINES)
def test_nonfinite_valid_loss_is_refused(name):
    with pytest.raises(ValueError, match="non-finite"):
        FUNCTIONS[name](t64([1.0, math.nan, 2.0]), full(3))


@pytest.mark.parametrize(
    ("call", "named"),
    [
        (lambda x, v: tilted_weights(x, v, tilt=0.0), "tilt"),
        (lambda x, v: tilted_weights(x, v, tilt=-1.0), "tilt"),
        (lambda x, v: tilted_weights(x, v, tilt=math.inf), "tilt"),
        (lambda x, v: truncate_weights(x, v, fraction=1.0), "truncate_fraction"),
        (lambda x, v: truncate_weights(x, v, fraction=-0.1), "truncate_fraction"),
        (lambda x, v: truncate_weights(x, v, fraction=math.nan), "truncate_fraction"),
        (lambda x, v: keyframe_weights(x, v, fraction=0.0), "keyframe_fraction"),
        (lambda x, v: keyframe_weights(x, v, fraction=1.0), "keyframe_fraction"),
        (lambda x, v: keyframe_weights(x, v, factor=0.99), "keyframe_factor"),
        (lambda x, v: keyframe_weights(x, v, factor=math.inf), "keyframe_factor"),
        (lambda x, v: focal_weights(x, v, beta=-0.5), "focal_beta"),
        (lambda x, v: focal_weights(x, v, w_max=0.9), "w_max"),
    ],
)
def test_bad_parameters_are_refused_with_their_name(call, named):
    with pytest.raises(ValueError, match=rf"^{named} must"):
        call(t64([1.0, 2.0]), full(2))


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("tilt", 0.0),
        ("truncate_fraction", 1.0),
        ("truncate_fraction", -0.5),
        ("keyframe_fraction", 0.0),
        ("keyframe_fraction", 1.5),
        ("keyframe_factor", 0.5),
        ("focal_beta", -1.0),
        ("tilt", "1"),
        ("focal_beta", True),
    ],
)
def test_weighting_params_and_tarloss_refuse_bad_values(field, value):
    owner = {"tilt": "tilted", "truncate_fraction": "truncate", "focal_beta": "focal"}.get(field, "keyframe")
    with pytest.raises(ValueError, match=rf"^{field} must"):
        WEIGHTINGS[owner].params(**{field: value})
    inner = BCLoss(TensorDictModule(torch.nn.Linear(2, 2), ["observation"], ["action"]), reduction="none")
    with pytest.raises(ValueError, match=rf"^{field} must"):
        tar_loss(inner, owner, **{field: value})


def test_focal_needs_an_exact_cap_of_at_least_one():
    inner = BCLoss(TensorDictModule(torch.nn.Linear(2, 2), ["observation"], ["action"]), reduction="none")
    with pytest.raises(ValueError, match=r"^w_max must be >= 1 for the focal weighting"):
        tar_loss(inner, "focal", w_max=0.5)
    # TAR refuses it with either cap: one rule, w_max >= 1 (check_tar_params)
    with pytest.raises(ValueError, match=r"^w_max >= 1 is needed .*cap='paper' renormalises them above it"):
        tar_loss(inner, "tar", w_max=0.5)


@pytest.mark.parametrize(
    ("name", "kwargs", "fn_kwargs"),
    [
        ("tilted", {"tilt": 2.5}, {"tilt": 2.5}),
        ("truncate", {"truncate_fraction": 0.4}, {"fraction": 0.4}),
        ("keyframe", {"keyframe_fraction": 0.5, "keyframe_factor": 3.0}, {"fraction": 0.5, "factor": 3.0}),
        ("focal", {"focal_beta": 2.0, "w_max": 1.7}, {"beta": 2.0, "w_max": 1.7}),
    ],
)
def test_tarloss_passes_the_parameters(name, kwargs, fn_kwargs):
    from tensordict import TensorDict

    torch.manual_seed(0)
    actor = TensorDictModule(torch.nn.Linear(3, 2), ["observation"], ["action"])
    loss = tar_loss(BCLoss(actor, loss_function="mse", reduction="none"), name, return_weights=True, **kwargs)
    valid = torch.ones(4, 10, dtype=torch.bool)
    valid[1, 6:] = False
    data = TensorDict(
        {"observation": torch.randn(4, 10, 3), "action": torch.randn(4, 10, 2), ("collector", "mask"): valid}, [4, 10]
    )
    out = loss(data)
    with torch.no_grad():
        step_losses = loss.step_losses(data)
    torch.testing.assert_close(out["weights"], FUNCTIONS[name](step_losses, valid, **fn_kwargs))
    assert not torch.allclose(out["weights"], FUNCTIONS[name](step_losses, valid))  # not the defaults


def test_registered_and_reach_their_parameters():
    losses, valid = t64([[0.5, 2.0, 0.1, 3.0, 1.0], [4.0, 0.2, 1.5, 8.0, 0.0]]), mask([[1] * 5, [1, 1, 1, 0, 0]])
    params = SimpleNamespace(
        tilt=2.5, truncate_fraction=0.4, keyframe_fraction=0.5, keyframe_factor=3.0, focal_beta=1.5, w_max=1.8
    )
    expected = {
        "tilted": [ref_tilted([0.5, 2.0, 0.1, 3.0, 1.0], 2.5), [*ref_tilted([4.0, 0.2, 1.5], 2.5), 0, 0]],
        "truncate": [ref_truncate([0.5, 2.0, 0.1, 3.0, 1.0], 0.4), [*ref_truncate([4.0, 0.2, 1.5], 0.4), 0, 0]],
        "keyframe": [
            ref_keyframe([0.5, 2.0, 0.1, 3.0, 1.0], 0.5, 3.0),
            [*ref_keyframe([4.0, 0.2, 1.5], 0.5, 3.0), 0, 0],
        ],
        "focal": [ref_focal([0.5, 2.0, 0.1, 3.0, 1.0], 1.5, 1.8), [*ref_focal([4.0, 0.2, 1.5], 1.5, 1.8), 0, 0]],
    }
    for name in BASELINES:
        spec = WEIGHTINGS[name]
        assert spec.name == name and not spec.stochastic and spec.perturb is None and spec.summary
        close(spec.weights(losses, valid, _own(name, params), 1.0, None), expected[name], rtol=1e-8)


# ---------------------------------------------------------------------------------------------
# Hypothesis properties
# ---------------------------------------------------------------------------------------------

SETTINGS = settings(max_examples=40, deadline=None)
_VALUE = st.one_of(st.floats(0.0, 100.0, width=32, allow_subnormal=False), st.sampled_from([0.0, 0.5, 1.0, 7.25]))


@st.composite
def batches(draw):
    """A ``[B, L]`` float32 loss tensor with ties and zeros, and a random mask (empty segments included)."""
    b, n = draw(st.integers(1, 5)), draw(st.integers(1, 20))
    vals = draw(st.lists(st.lists(_VALUE, min_size=n, max_size=n), min_size=b, max_size=b))
    rows = draw(st.lists(st.lists(st.booleans(), min_size=n, max_size=n), min_size=b, max_size=b))
    return torch.tensor(vals, dtype=torch.float32), torch.tensor(rows, dtype=torch.bool)


@st.composite
def baseline_params(draw):
    return SimpleNamespace(
        tilt=draw(st.sampled_from([0.1, 1.0, 4.0, 30.0])),
        truncate_fraction=draw(st.sampled_from([0.0, 0.1, 0.25, 0.5, 0.9])),
        keyframe_fraction=draw(st.sampled_from([0.05, 0.3, 0.5, 0.95])),
        keyframe_factor=draw(st.sampled_from([1.0, 2.0, 5.0, 50.0])),
        focal_beta=draw(st.sampled_from([0.0, 0.5, 1.0, 3.0])),
        w_max=draw(st.sampled_from([1.0, 1.5, 3.0, math.inf])),
    )


def _own(name, values):
    """The weighting ``name``'s parameters, taken from ``values`` (a namespace holding every baseline's)."""
    params = WEIGHTINGS[name].params
    return params(**{f.name: getattr(values, f.name) for f in dataclasses.fields(params)})


def _weights(name, losses, valid, params, mix=1.0):
    return WEIGHTINGS[name].weights(losses, valid, _own(name, params), mix, None)


@SETTINGS
@given(batch=batches(), params=baseline_params(), name=st.sampled_from(BASELINES), mix=st.sampled_from([0.3, 1.0]))
def test_nonnegative_unit_mean_zero_on_padding(batch, params, name, mix):
    losses, valid = batch
    w = _weights(name, losses, valid, params, mix)
    assert w.shape == losses.shape and w.dtype == losses.dtype
    assert torch.isfinite(w).all() and (w >= 0).all()
    assert (w[~valid] == 0).all()
    for b in range(losses.shape[0]):
        if valid[b].any():
            assert float(w[b][valid[b]].double().mean()) == pytest.approx(1.0, abs=1e-5)
    if name == "focal":
        assert float(w.max()) <= params.w_max * (1 + 1e-5)


@SETTINGS
@given(batch=batches(), params=baseline_params(), name=st.sampled_from(BASELINES))
def test_no_gradient(batch, params, name):
    losses, valid = batch
    losses = losses.clone().requires_grad_(True)
    w = _weights(name, losses, valid, params)
    assert not w.requires_grad
    (g,) = torch.autograd.grad((w * losses).sum(), losses)
    torch.testing.assert_close(g, w, rtol=0, atol=0)


@SETTINGS
@given(batch=batches(), params=baseline_params(), name=st.sampled_from(BASELINES), data=st.data())
def test_permutation_equivariance_ties_included(batch, params, name, data):
    losses, valid = batch
    n = losses.shape[-1]
    idx = torch.tensor([data.draw(st.permutations(range(n))) for _ in range(losses.shape[0])])
    w = _weights(name, losses, valid, params)
    w_perm = _weights(name, losses.gather(-1, idx), valid.gather(-1, idx), params)
    torch.testing.assert_close(w_perm, w.gather(-1, idx), rtol=1e-5, atol=1e-5)


@SETTINGS
@given(batch=batches(), params=baseline_params(), name=st.sampled_from(BASELINES), value=_VALUE)
def test_equal_losses_give_uniform_weights(batch, params, name, value):
    _, valid = batch
    w = _weights(name, torch.full(valid.shape, value), valid, params)
    torch.testing.assert_close(w, valid.float(), rtol=0, atol=1e-5)


@SETTINGS
@given(batch=batches(), params=baseline_params(), name=st.sampled_from(BASELINES), scale=st.floats(0.01, 100.0))
def test_scale_free(batch, params, name, scale):
    losses, valid = batch
    x = losses.double()
    torch.testing.assert_close(
        _weights(name, scale * x, valid, params), _weights(name, x, valid, params), rtol=1e-6, atol=1e-6
    )


@SETTINGS
@given(batch=batches(), params=baseline_params(), name=st.sampled_from(BASELINES))
def test_monotone_in_the_loss(batch, params, name):
    # tilted, keyframe, focal: a larger loss never weighs less; truncate: never more. Equal losses weigh the same.
    losses, valid = batch
    w = _weights(name, losses.double(), valid, params)
    sign = -1.0 if name == "truncate" else 1.0
    for b in range(losses.shape[0]):
        x, y = losses[b][valid[b]].tolist(), w[b][valid[b]].tolist()
        for i in range(len(x)):
            for j in range(len(x)):
                if x[i] < x[j]:
                    assert sign * (y[j] - y[i]) >= -1e-9 * max(1.0, y[i], y[j])
                elif x[i] == x[j]:
                    assert y[i] == pytest.approx(y[j], rel=1e-9, abs=1e-12)


@SETTINGS
@given(batch=batches(), params=baseline_params(), name=st.sampled_from(["truncate", "keyframe"]))
def test_ranking_baselines_match_the_plain_reference(batch, params, name):
    losses, valid = batch
    w = _weights(name, losses.double(), valid, params)
    for b in range(losses.shape[0]):
        x = losses[b][valid[b]].double().tolist()
        if not x:
            continue
        if name == "truncate":
            expected = ref_truncate(x, params.truncate_fraction)
        else:
            expected = ref_keyframe(x, params.keyframe_fraction, params.keyframe_factor)
        close(w[b][valid[b]], expected, rtol=1e-9, atol=1e-9)
