"""Executable specification of TAR's weightings (paper Sec. II-B/C, Eqs. 3-8; Sec. III-B).

Every expected value below comes from a hand computation (worked out in the comments) or from
``ref_tar_segment``, a plain-Python (lists + ``math``, no torch) re-implementation of Eqs. 3-8
written from the paper, one segment at a time. Nothing here derives an expected value from the
code under test, except where a test states a relation between two of its outputs (e.g. "the
same multiset as tar_weights").
"""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from tar_reference import ref_exact_cap, ref_precap, ref_tar, ref_tar_segment

import tar_rl
from tar_rl.objectives import MixSchedule, mix_at
from tar_rl.objectives.weighting import (
    WEIGHTINGS,
    TARParams,
    get_weighting,
    invert_weights,
    perturb_mask,
    random_weights,
    shuffle_weights,
    tar_weights,
    uniform_weights,
    window_weights,
)

SQRT2 = math.sqrt(2.0)
# E = exp(3 / sqrt 2): the ratio exp(s_big) / exp(s_small) in the [0, 0, 3] example below.
E3 = math.exp(3.0 / SQRT2)  # 8.342144716...


def t64(x) -> torch.Tensor:
    return torch.tensor(x, dtype=torch.float64)


def mask(x) -> torch.Tensor:
    return torch.tensor(x, dtype=torch.bool)


# Hand values are eps-free; the default eps = 1e-8 moves them by ~1e-8 relative, hence rtol=1e-7.
def close(actual: torch.Tensor, expected, *, rtol=1e-7, atol=1e-9) -> None:
    expected = torch.as_tensor(expected, dtype=torch.float64)
    torch.testing.assert_close(actual.double(), expected, rtol=rtol, atol=atol)


def segment_means(w: torch.Tensor, valid: torch.Tensor) -> list[float]:
    w2 = w.double().reshape(-1, w.shape[-1])
    v2 = valid.reshape(-1, valid.shape[-1])
    return [float(w2[i][v2[i]].mean()) for i in range(w2.shape[0]) if v2[i].any()]


def padded_batch(dtype=torch.float32):
    """Three segments of length 6: full, partly padded (NaN/inf in the padding), one valid step."""
    losses = torch.tensor(
        [
            [0.5, 2.0, 0.1, 3.0, 1.0, 0.7],
            [4.0, 0.2, 1.5, math.nan, math.inf, -math.inf],
            [2.5, 1e9, 1e9, 1e9, 1e9, 1e9],
        ],
        dtype=dtype,
    )
    valid = mask([[1, 1, 1, 1, 1, 1], [1, 1, 1, 0, 0, 0], [1, 0, 0, 0, 0, 0]])
    return losses, valid


# ---------------------------------------------------------------------------------------------
# The reference itself, on the hand-worked examples (so that it is trusted independently)
# ---------------------------------------------------------------------------------------------


def test_reference_reproduces_hand_examples():
    # [0, 0, 3]: mu = 1, sigma = sqrt(2), s = [-1/sqrt2, -1/sqrt2, sqrt2]; exp-ratio E3 = e^{3/sqrt2}
    # -> w~ = 3 * [1, 1, E3] / (2 + E3) = [0.2900752, 0.2900752, 2.4198495].
    w = ref_tar_segment([0, 0, 3], [1, 1, 1], w_max=math.inf, eps=0.0)
    assert w == pytest.approx([3 / (2 + E3), 3 / (2 + E3), 3 * E3 / (2 + E3)], rel=1e-12)
    assert w == pytest.approx([0.2900752292917, 0.2900752292917, 2.4198495414166], rel=1e-10)
    # exact cap at 2 on the same: top at 2, the other two share 1 -> [0.5, 0.5, 2].
    assert ref_exact_cap(w, 2.0) == pytest.approx([0.5, 0.5, 2.0], rel=1e-12)


# ---------------------------------------------------------------------------------------------
# The executable spec
# ---------------------------------------------------------------------------------------------


class TestTarWeightsSpec:
    """Contract of ``tar_weights(losses, valid, *, gamma, w_max, eps, mix, cap)``.

    * Eq. 3: the losses are detached; the weights carry no gradient and act as constants.
    * Eq. 4: mean and POPULATION std over the valid steps of each segment only; whatever the
      padded steps hold (NaN and inf included) does not change the weights of the valid ones.
    * Eq. 5: z-score ``(l - mu) / (sigma + eps)``. Eq. 6: masked softmax of ``gamma * s``.
      Eq. 7: unit-mean scaling ``M * p``.
    * Sec. III-B: ``(1 - mix) * 1 + mix * w`` is formed BEFORE the cap; ``mix`` may be a float
      or a 0-d tensor; ``mix=0`` gives uniform weights.
    * Eq. 8, ``cap="paper"``: clip once at ``w_max``, renormalise to unit mean (the result may
      exceed ``w_max``). ``cap="exact"``: unit-mean ``min(c * w~, w_max)``, cap holds exactly.
    * Output: same shape and dtype as ``losses``; ``>= 0``; ``0`` on padding; mean ``1`` over
      the valid steps of each segment; all ``1`` for equal losses; ``1`` on a lone valid step;
      all ``0`` (no NaN) in a segment with no valid step; ``w_max=inf`` disables the cap.
      Half precision is computed in float32 and cast back; leading batch dims are free.
    * Bad input raises ``TypeError``/``ValueError`` with a clear message.
    """

    # -- Eq. 3: stop-gradient ----------------------------------------------------------------

    @pytest.mark.parametrize("cap", ["paper", "exact"])
    def test_weights_carry_no_gradient(self, cap):
        losses = torch.tensor([[0.3, 1.2, 0.1, 2.0]], requires_grad=True)
        valid = mask([[1, 1, 1, 0]])
        w = tar_weights(losses, valid, cap=cap, w_max=1.5)
        assert not w.requires_grad
        assert w.grad_fn is None

    def test_weights_act_as_constants_in_the_weighted_loss(self):
        theta = torch.tensor([0.5, -1.0, 2.0, 0.25, 3.0], dtype=torch.float64, requires_grad=True)
        losses = (theta**2).unsqueeze(0)  # a non-leaf loss with a graph behind it
        valid = mask([[1, 1, 1, 1, 0]])
        w = tar_weights(losses, valid)
        (g,) = torch.autograd.grad((w * losses).sum(), losses)
        # d/dl sum(w * l) = w exactly when w is a constant (no term through w(l)).
        torch.testing.assert_close(g, w, rtol=0, atol=0)

    # -- Eq. 4: masked mean and population std -------------------------------------------------

    def test_two_steps_use_population_std(self):
        # [0, 1]: mu = 0.5, POPULATION sigma = 0.5 -> s = [-1, 1]; softmax ratio e^2
        # -> w = 2 * [1, e^2] / (1 + e^2) = [0.2384058, 1.7615942].
        # (The sample std 1/sqrt2 would give s = [-0.707, 0.707] -> [0.3911, 1.6089].)
        w = tar_weights(t64([[0.0, 1.0]]), mask([[1, 1]]), w_max=math.inf)
        e2 = math.exp(2.0)
        close(w, [[2 / (1 + e2), 2 * e2 / (1 + e2)]])
        close(w, [[0.238405844044235, 1.761594155955765]])

    def test_statistics_ignore_padded_steps(self):
        # Same [0, 1] segment, with a padded step holding 100: the padded value must not enter
        # mu or sigma, so the valid weights are those of the example above, padding gets 0.
        w = tar_weights(t64([[0.0, 1.0, 100.0]]), mask([[1, 1, 0]]), w_max=math.inf)
        e2 = math.exp(2.0)
        close(w, [[2 / (1 + e2), 2 * e2 / (1 + e2), 0.0]])

    @pytest.mark.parametrize("junk", [math.nan, math.inf, -math.inf, 1e30, -7.0])
    @pytest.mark.parametrize("cap", ["paper", "exact"])
    def test_padding_content_never_changes_valid_weights(self, junk, cap):
        base = torch.tensor([[0.3, 2.0, 0.0, 0.0, 1.1], [5.0, 0.0, 0.2, 0.0, 0.0]])
        valid = mask([[1, 1, 0, 0, 1], [1, 0, 1, 0, 0]])
        dirty = base.masked_fill(~valid, junk)
        w_clean = tar_weights(base, valid, w_max=1.4, cap=cap)
        w_dirty = tar_weights(dirty, valid, w_max=1.4, cap=cap)
        assert torch.isfinite(w_dirty).all()
        torch.testing.assert_close(w_dirty, w_clean, rtol=0, atol=0)
        close(w_dirty, ref_tar(base, valid, w_max=1.4, cap=cap), rtol=1e-5, atol=1e-6)

    # -- Eq. 5: z-score with eps; Eq. 6: temperature; Eq. 7: M * p -----------------------------

    def test_eps_is_added_to_sigma(self):
        # [0, 1], eps = 1: s = +-0.5 / (0.5 + 1) = +-1/3; ratio e^{2/3}
        # -> w = [2 / (1 + e^{2/3}), 2 e^{2/3} / (1 + e^{2/3})] = [0.6784873, 1.3215127].
        w = tar_weights(t64([[0.0, 1.0]]), mask([[1, 1]]), eps=1.0, w_max=math.inf)
        e = math.exp(2 / 3)
        close(w, [[2 / (1 + e), 2 * e / (1 + e)]])
        close(w, [[0.678487262468366, 1.321512737531634]])

    def test_gamma_is_the_softmax_temperature(self):
        # [0, 1], gamma = 0.5: logits = 0.5 * [-1, 1]; ratio e -> w = [2/(1+e), 2e/(1+e)].
        w = tar_weights(t64([[0.0, 1.0]]), mask([[1, 1]]), gamma=0.5, w_max=math.inf)
        close(w, [[2 / (1 + math.e), 2 * math.e / (1 + math.e)]])
        close(w, [[0.537882842739990, 1.462117157260010]])

    def test_unit_mean_scaling_three_steps(self):
        # [0, 0, 3]: mu = 1, sigma = sqrt2, s = [-1/sqrt2, -1/sqrt2, sqrt2]; with gamma = 1,
        # p = [1, 1, E3] / (2 + E3) with E3 = e^{3/sqrt2} = 8.3421447; times M = 3:
        # w = [0.2900752, 0.2900752, 2.4198495] (sums to 3). Below the default cap 3.
        w = tar_weights(t64([[0.0, 0.0, 3.0]]), mask([[1, 1, 1]]))
        close(w, [[3 / (2 + E3), 3 / (2 + E3), 3 * E3 / (2 + E3)]])
        close(w, [[0.29007522929170, 0.29007522929170, 2.41984954141659]])
        assert float(w.sum()) == pytest.approx(3.0, rel=1e-12)

    def test_matches_reference_on_a_padded_batch(self):
        losses, valid = padded_batch(torch.float64)
        for kw in (
            {},
            {"gamma": 2.0, "w_max": 1.8},
            {"gamma": 0.3, "w_max": 1.2},
            {"gamma": 3.0, "w_max": 1.3, "cap": "exact"},
            {"gamma": 1.5, "w_max": 2.0, "mix": 0.4, "cap": "exact"},
            {"eps": 0.5, "mix": 0.25},
        ):
            close(tar_weights(losses, valid, **kw), ref_tar(losses, valid, **kw), rtol=2e-6, atol=1e-9)

    # -- Sec. III-B: mixing before the cap ----------------------------------------------------

    def test_mix_is_applied_before_the_cap(self):
        # [0, 0, 3] with mix = 0.5: pre-cap w~ = [0.2900752, 0.2900752, 2.4198495]
        # mixed = 0.5 + 0.5 w~ = [0.6450376, 0.6450376, 1.7099248]; clip at 1.5 -> [.., .., 1.5]
        # renormalise: top = 3 * 1.5 / (2 * 0.6450376 + 1.5) = 1.6128597, others 0.6935701.
        # (Capping first and mixing after would give [0.7091737, 0.7091737, 1.5816525].)
        w = tar_weights(t64([[0.0, 0.0, 3.0]]), mask([[1, 1, 1]]), mix=0.5, w_max=1.5)
        small = 0.5 + 0.5 * 3 / (2 + E3)
        top = 3 * 1.5 / (2 * small + 1.5)
        close(w, [[small * top / 1.5, small * top / 1.5, top]])
        close(w, [[0.6935701315942, 0.6935701315942, 1.6128597368116]])
        close(w, ref_tar(t64([[0.0, 0.0, 3.0]]), mask([[1, 1, 1]]), mix=0.5, w_max=1.5))

    @pytest.mark.parametrize("cap", ["paper", "exact"])
    def test_mix_before_cap_against_reference(self, cap):
        losses, valid = padded_batch(torch.float64)
        w = tar_weights(losses, valid, mix=0.6, w_max=1.2, gamma=2.0, cap=cap)
        close(w, ref_tar(losses, valid, mix=0.6, w_max=1.2, gamma=2.0, cap=cap), rtol=2e-6)

    @pytest.mark.parametrize("cap", ["paper", "exact"])
    def test_mix_zero_gives_uniform(self, cap):
        losses, valid = padded_batch()
        w = tar_weights(losses, valid, mix=0.0, cap=cap, gamma=5.0)
        torch.testing.assert_close(w, valid.float(), rtol=0, atol=1e-7)

    def test_mix_as_zero_dim_tensor(self):
        losses, valid = padded_batch()
        for alpha in (0.0, 0.35, 1.0):
            w_t = tar_weights(losses, valid, mix=torch.tensor(alpha), w_max=1.6)
            w_f = tar_weights(losses, valid, mix=alpha, w_max=1.6)
            assert w_t.dtype == torch.float32 and w_t.shape == losses.shape
            torch.testing.assert_close(w_t, w_f, rtol=1e-6, atol=1e-7)
        # also straight from the schedule (a float32 0-d tensor) with float64 losses
        alpha = MixSchedule(start=10, ramp=20)(torch.tensor(20))  # 0.5
        losses64, _ = padded_batch(torch.float64)
        w = tar_weights(losses64, valid, mix=alpha, w_max=1.6)
        assert w.dtype == torch.float64
        close(w, ref_tar(losses64, valid, mix=0.5, w_max=1.6), rtol=1e-6, atol=1e-7)

    # -- Eq. 8: the two cap modes ---------------------------------------------------------------

    def test_paper_cap_clips_once_and_may_end_above_w_max(self):
        # [0, 0, 3], w_max = 2: w~ = [a, a, b], a = 3/(2+E3) = 0.2900752, b = 2.4198495 > 2.
        # Clip: [a, a, 2]; renormalise by 3 / (2a + 2): top = 3 / (1 + a) = 3 (2+E3)/(5+E3)
        # = 2.3254458 > w_max (allowed in paper mode), others (3 - top)/2 = 0.3372771.
        w = tar_weights(t64([[0.0, 0.0, 3.0]]), mask([[1, 1, 1]]), w_max=2.0, cap="paper")
        top = 3 * (2 + E3) / (5 + E3)
        close(w, [[(3 - top) / 2, (3 - top) / 2, top]])
        close(w, [[0.3372771091624, 0.3372771091624, 2.3254457816752]])
        assert float(w.max()) > 2.0

    def test_paper_cap_four_steps(self):
        # [0, 0, 0, 4]: mu = 1, sigma = sqrt3, ratio R = e^{4/sqrt3} = 10.0683927;
        # w~ = [4/(3+R)] * 3 + [4R/(3+R)] = [0.3060820 x3, 3.0817539]; clip at 3 and renormalise
        # with 4 / (3 * 0.3060820 + 3): top = 3.0625948 (> 3), others 0.3124684.
        w = tar_weights(t64([[0.0, 0.0, 0.0, 4.0]]), mask([[1, 1, 1, 1]]), w_max=3.0)
        small = 4 / (3 + math.exp(4 / math.sqrt(3)))
        top = 12 / (3 * small + 3)
        close(w, [[small * 4 / (3 * small + 3)] * 3 + [top]])
        assert top == pytest.approx(3.062594801754563, rel=1e-12)

    def test_exact_cap_hand_examples(self):
        # [0, 0, 3], w_max = 2: the top step sits at 2, the other two share the rest equally.
        w = tar_weights(t64([[0.0, 0.0, 3.0]]), mask([[1, 1, 1]]), w_max=2.0, cap="exact")
        close(w, [[0.5, 0.5, 2.0]], rtol=1e-6)
        # [0, 0, 0, 4], w_max = 3: [1/3, 1/3, 1/3, 3].
        w = tar_weights(t64([[0.0, 0.0, 0.0, 4.0]]), mask([[1, 1, 1, 1]]), w_max=3.0, cap="exact")
        close(w, [[1 / 3, 1 / 3, 1 / 3, 3.0]], rtol=1e-6)
        # w_max = 1 forces all ones.
        w = tar_weights(t64([[0.0, 0.0, 0.0, 4.0]]), mask([[1, 1, 1, 1]]), w_max=1.0, cap="exact")
        close(w, [[1.0, 1.0, 1.0, 1.0]], rtol=1e-6)

    def test_exact_cap_needs_several_rounds(self):
        # One clip-and-renormalise pushes the second-largest step over the cap: paper mode ends
        # above w_max, exact mode clips both and matches the iterative reference.
        losses = t64([[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 8.0, 10.0]])
        valid = torch.ones(1, 8, dtype=torch.bool)
        kw = {"gamma": 1.0, "w_max": 2.5}
        paper = tar_weights(losses, valid, cap="paper", **kw)
        exact = tar_weights(losses, valid, cap="exact", **kw)
        assert float(paper.max()) > 2.5
        ref = ref_tar(losses, valid, cap="exact", **kw)
        assert int((ref >= 2.5 - 1e-12).sum()) == 2  # the example really needs two clipped steps
        close(exact, ref, rtol=2e-6)
        close(paper, ref_tar(losses, valid, cap="paper", **kw), rtol=1e-10)

    @pytest.mark.parametrize("mix", [1.0, 0.7])
    def test_exact_cap_holds_and_is_a_scaled_clip(self, mix):
        g = torch.Generator().manual_seed(3)
        losses = torch.rand(5, 12, generator=g, dtype=torch.float64) * 4
        losses[:, 0] += 6.0  # one large loss per segment so the cap binds
        valid = torch.rand(5, 12, generator=g) < 0.8
        valid[:, 0] = True
        valid[:, 1] = True
        w_max, gamma = 1.7, 2.0
        w = tar_weights(losses, valid, gamma=gamma, w_max=w_max, mix=mix, cap="exact")
        assert float(w.max()) <= w_max + 1e-6
        for mean in segment_means(w, valid):
            assert mean == pytest.approx(1.0, abs=1e-6)
        close(w, ref_tar(losses, valid, gamma=gamma, w_max=w_max, mix=mix, cap="exact"), rtol=2e-6)
        # form min(c * w~, w_max): the unclipped entries are proportional to the pre-cap weights
        for b in range(5):
            pre = ref_precap(losses[b].tolist(), valid[b].tolist(), gamma=gamma, mix=mix)
            got = w[b][valid[b]].tolist()
            free = [(g_, p) for g_, p in zip(got, pre) if g_ < w_max - 1e-6]
            clipped = [(g_, p) for g_, p in zip(got, pre) if g_ >= w_max - 1e-6]
            assert free and clipped
            ratios = [g_ / p for g_, p in free]
            c = ratios[0]
            assert ratios == pytest.approx([c] * len(ratios), rel=1e-6)
            assert all(c * p >= w_max * (1 - 1e-6) for _, p in clipped)

    # -- edge cases -------------------------------------------------------------------------------

    @pytest.mark.parametrize("cap", ["paper", "exact"])
    @pytest.mark.parametrize("value", [0.0, 0.1, 37.3, 1e6])
    def test_all_equal_losses_give_ones(self, cap, value):
        losses = torch.full((2, 7), value)
        valid = mask([[1] * 7, [1, 1, 1, 0, 1, 0, 1]])
        w = tar_weights(losses, valid, cap=cap, gamma=3.0)
        torch.testing.assert_close(w, valid.float(), rtol=0, atol=1e-6)

    @pytest.mark.parametrize("cap", ["paper", "exact"])
    def test_single_valid_step_gets_one(self, cap):
        losses = torch.tensor([[math.nan, 5.0, math.inf]])
        w = tar_weights(losses, mask([[0, 1, 0]]), cap=cap, w_max=1.0)
        assert w.tolist() == [[0.0, 1.0, 0.0]]

    @pytest.mark.parametrize("cap", ["paper", "exact"])
    @pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.float16])
    def test_segment_without_valid_steps_is_all_zero(self, cap, dtype):
        losses = torch.tensor([[1.0, 2.0, 3.0], [4.0, math.nan, 6.0]], dtype=dtype)
        valid = mask([[1, 1, 1], [0, 0, 0]])
        w = tar_weights(losses, valid, cap=cap, mix=torch.tensor(0.5))
        assert torch.isfinite(w).all()
        assert w[1].tolist() == [0.0, 0.0, 0.0]
        w = tar_weights(losses[1:], valid[1:], cap=cap)
        assert w.tolist() == [[0.0, 0.0, 0.0]]

    @pytest.mark.parametrize("cap", ["paper", "exact"])
    def test_padded_steps_are_exactly_zero(self, cap):
        losses, valid = padded_batch()
        for kw in ({}, {"gamma": 4.0, "w_max": 1.1}, {"mix": 0.3}):
            w = tar_weights(losses, valid, cap=cap, **kw)
            assert (w[~valid] == 0).all()
            assert (w >= 0).all()

    def test_infinite_w_max_disables_the_cap(self):
        # [0, 0, 0, 4]: uncapped top weight 4R/(3+R) = 3.0817539 > 3 is kept as is.
        losses = t64([[0.0, 0.0, 0.0, 4.0]])
        valid = mask([[1, 1, 1, 1]])
        r = math.exp(4 / math.sqrt(3))
        for cap in ("paper", "exact"):
            w = tar_weights(losses, valid, w_max=math.inf, cap=cap)
            close(w, [[4 / (3 + r)] * 3 + [4 * r / (3 + r)]])
        losses, valid = padded_batch(torch.float64)
        close(tar_weights(losses, valid, w_max=math.inf, gamma=3.0), ref_tar(losses, valid, w_max=math.inf, gamma=3.0))

    # -- dtypes and shapes ------------------------------------------------------------------------

    def test_float64_in_float64_out(self):
        losses, valid = padded_batch(torch.float64)
        w = tar_weights(losses, valid, gamma=2.0)
        assert w.dtype == torch.float64
        close(w, ref_tar(losses, valid, gamma=2.0), rtol=1e-12, atol=1e-12)

    @pytest.mark.parametrize(("dtype", "rtol"), [(torch.float16, 2e-3), (torch.bfloat16, 1.6e-2)])
    @pytest.mark.parametrize("cap", ["paper", "exact"])
    def test_half_precision_in_same_dtype_out(self, dtype, rtol, cap):
        losses, valid = padded_batch(torch.float32)
        losses = losses.masked_fill(~valid, 0.0).to(dtype)
        w = tar_weights(losses, valid, cap=cap, w_max=1.5)
        assert w.dtype == dtype
        w32 = tar_weights(losses.float(), valid, cap=cap, w_max=1.5)
        torch.testing.assert_close(w.float(), w32, rtol=rtol, atol=rtol)
        # "weighted in float32 and the weights cast back": equal to the float32 result rounded
        torch.testing.assert_close(w, w32.to(dtype), rtol=0, atol=0)
        close(w, ref_tar(losses, valid, cap=cap, w_max=1.5), rtol=rtol, atol=rtol)

    def test_leading_batch_dims(self):
        g = torch.Generator().manual_seed(0)
        losses = torch.rand(2, 3, 9, generator=g) * 10
        valid = torch.rand(2, 3, 9, generator=g) < 0.7
        for kw in ({}, {"cap": "exact", "w_max": 1.3}):
            w = tar_weights(losses, valid, **kw)
            assert w.shape == (2, 3, 9)
            flat = tar_weights(losses.reshape(6, 9), valid.reshape(6, 9), **kw)
            torch.testing.assert_close(w.reshape(6, 9), flat)
        one_d = tar_weights(losses[0, 0], valid[0, 0])
        torch.testing.assert_close(one_d, tar_weights(losses, valid)[0, 0])

    # -- bad input --------------------------------------------------------------------------------

    def test_rejects_mismatched_shapes(self):
        with pytest.raises(ValueError, match="same shape"):
            tar_weights(torch.zeros(2, 4), torch.ones(2, 5, dtype=torch.bool))

    @pytest.mark.parametrize("mdtype", [torch.uint8, torch.float32, torch.int64])
    def test_rejects_non_bool_mask(self, mdtype):
        with pytest.raises(TypeError, match=r"torch\.bool"):
            tar_weights(torch.zeros(2, 4), torch.ones(2, 4, dtype=mdtype))

    @pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
    def test_rejects_non_finite_loss_at_a_valid_step(self, bad):
        losses = torch.tensor([[0.1, 0.2, 0.3], [0.4, bad, 0.6]])
        with pytest.raises(ValueError, match="non-finite"):
            tar_weights(losses, torch.ones(2, 3, dtype=torch.bool))

    @pytest.mark.parametrize("gamma", [0.0, -1.0, math.nan, math.inf])
    def test_rejects_bad_gamma(self, gamma):
        with pytest.raises(ValueError, match="gamma"):
            tar_weights(torch.zeros(1, 3), torch.ones(1, 3, dtype=torch.bool), gamma=gamma)

    @pytest.mark.parametrize("w_max", [0.0, -2.0])
    def test_rejects_bad_w_max(self, w_max):
        with pytest.raises(ValueError, match="w_max"):
            tar_weights(torch.zeros(1, 3), torch.ones(1, 3, dtype=torch.bool), w_max=w_max)

    @pytest.mark.parametrize("eps", [0.0, -1e-8])
    def test_rejects_bad_eps(self, eps):
        with pytest.raises(ValueError, match="eps"):
            tar_weights(torch.zeros(1, 3), torch.ones(1, 3, dtype=torch.bool), eps=eps)

    @pytest.mark.parametrize("cap", ["paper", "exact"])
    @pytest.mark.parametrize("w_max", [0.9, 0.5, 1e-39, math.nan])
    def test_rejects_a_cap_below_one_with_either_cap(self, w_max, cap):
        with pytest.raises(ValueError, match="w_max >= 1 is needed"):
            tar_weights(torch.zeros(1, 3), torch.ones(1, 3, dtype=torch.bool), w_max=w_max, cap=cap)

    def test_paper_cap_below_one_could_not_hold(self):
        """Why the rule: by hand, clipping unit-mean weights (2.8, 0.4, 0.4, 0.4) at 0.5 gives (0.5, 0.4, 0.4, 0.4),
        which renormalise to (4 / 1.7) * (0.5, 0.4, 0.4, 0.4): the largest weight, 2 / 1.7 = 1.18, is above the cap,
        as the largest of any unit-mean weights (at least 1) is above every cap under 1."""
        clipped = [min(w, 0.5) for w in (2.8, 0.4, 0.4, 0.4)]
        largest = max(clipped) * 4 / sum(clipped)
        assert largest == pytest.approx(2 / 1.7) and largest > 1
        w = tar_weights(torch.tensor([[0.0, 0.0]]), torch.ones(1, 2, dtype=torch.bool), w_max=1.0, cap="paper")
        assert torch.equal(w, torch.ones(1, 2))  # w_max = 1, the smallest cap allowed, gives uniform weights

    def test_rejects_unknown_cap(self):
        with pytest.raises(ValueError, match="cap must be one of"):
            tar_weights(torch.zeros(1, 3), torch.ones(1, 3, dtype=torch.bool), cap="soft")

    def test_rejects_non_tensors(self):
        with pytest.raises(TypeError, match="must be tensors"):
            tar_weights([[0.1, 0.2]], torch.ones(1, 2, dtype=torch.bool))
        with pytest.raises(TypeError, match="must be tensors"):
            tar_weights(torch.zeros(1, 2), [[True, True]])

    def test_rejects_integer_losses_and_empty_time_axis(self):
        with pytest.raises(TypeError, match="floating-point"):
            tar_weights(torch.zeros(1, 3, dtype=torch.int64), torch.ones(1, 3, dtype=torch.bool))
        with pytest.raises(ValueError, match="L >= 1"):
            tar_weights(torch.zeros(2, 0), torch.ones(2, 0, dtype=torch.bool))

    def test_exported_at_package_top_level(self):
        assert tar_rl.tar_weights is tar_weights


# ---------------------------------------------------------------------------------------------
# Hypothesis: tar_weights == the plain-Python reference, over random padded batches
# ---------------------------------------------------------------------------------------------

_POOL = st.one_of(st.floats(0.0, 100.0), st.sampled_from([0.0, 1.0, 2.5, 50.0]))


@st.composite
def _batches64(draw):
    b = draw(st.integers(1, 4))
    n = draw(st.integers(1, 16))
    vals = draw(st.lists(st.lists(_POOL, min_size=n, max_size=n), min_size=b, max_size=b))
    valid = draw(st.lists(st.lists(st.booleans(), min_size=n, max_size=n), min_size=b, max_size=b))
    return t64(vals), mask(valid)


@settings(max_examples=80, deadline=None)
@given(
    batch=_batches64(),
    gamma=st.sampled_from([0.3, 1.0, 2.5]),
    w_max=st.sampled_from([1.0, 1.7, 3.0, math.inf]),
    mix=st.sampled_from([0.0, 0.3, 1.0]),
    eps=st.sampled_from([1e-8, 0.1]),
    cap=st.sampled_from(["paper", "exact"]),
)
def test_tar_matches_reference(batch, gamma, w_max, mix, eps, cap):
    losses, valid = batch
    kw = {"gamma": gamma, "w_max": w_max, "mix": mix, "eps": eps, "cap": cap}
    got = tar_weights(losses, valid, **kw)
    want = ref_tar(losses, valid, **kw)
    tol = 2e-6 if cap == "exact" else 1e-9
    torch.testing.assert_close(got, want, rtol=tol, atol=tol)


# ---------------------------------------------------------------------------------------------
# The control weightings
# ---------------------------------------------------------------------------------------------


class TestControls:
    """``uniform_weights``, ``invert_weights``, ``shuffle_weights``, ``random_weights`` and
    ``perturb_mask``: the paper's ablations, each against TAR or hand-computed values."""

    def test_uniform_is_the_mask_as_float(self):
        losses, valid = padded_batch(torch.float64)
        w = uniform_weights(losses, valid)
        assert w.dtype == torch.float64
        assert torch.equal(w, valid.double())
        with pytest.raises(ValueError, match="non-finite"):
            uniform_weights(t64([[math.nan]]), mask([[1]]))

    def test_invert_hand_example(self):
        # [0, 0, 3] negated -> [0, 0, -3]: s = [1/sqrt2, 1/sqrt2, -sqrt2]
        # -> w = 3 * [E3, E3, 1] / (2 E3 + 1) = [1.4151789, 1.4151789, 0.1696421].
        w = invert_weights(t64([[0.0, 0.0, 3.0]]), mask([[1, 1, 1]]))
        close(w, [[3 * E3 / (2 * E3 + 1), 3 * E3 / (2 * E3 + 1), 3 / (2 * E3 + 1)]])

    @pytest.mark.parametrize("kw", [{}, {"gamma": 2.0, "w_max": 1.4}, {"cap": "exact", "w_max": 1.2, "mix": 0.5}])
    def test_invert_is_tar_of_negated_losses(self, kw):
        losses, valid = padded_batch(torch.float64)
        w = invert_weights(losses, valid, **kw)
        close(w, ref_tar(-losses.masked_fill(~valid, 0.0), valid, **kw), rtol=2e-6)

    def test_invert_reverses_tar_order(self):
        losses = t64([[0.3, 2.0, 1.1, 5.0, 0.0, 9.0, 4.2], [1.0, 3.0, 2.0, 0.5, 8.0, 0.0, 0.0]])
        valid = mask([[1] * 7, [1, 1, 1, 1, 1, 0, 0]])
        tar = tar_weights(losses, valid, w_max=math.inf)
        inv = invert_weights(losses, valid, w_max=math.inf)
        for b in range(2):
            v = valid[b]
            order_tar = torch.argsort(tar[b][v]).tolist()
            order_inv = torch.argsort(inv[b][v]).tolist()
            assert order_inv == order_tar[::-1]
            assert order_tar == torch.argsort(losses[b][v]).tolist()

    @staticmethod
    def _batch():
        g = torch.Generator().manual_seed(11)
        losses = torch.rand(4, 9, generator=g) * 5
        valid = torch.rand(4, 9, generator=g) < 0.75
        valid[:, :2] = True
        valid[3] = False  # one empty segment
        losses = losses.masked_fill(~valid, math.nan)
        return losses, valid

    def test_shuffle_keeps_each_segments_multiset(self):
        losses, valid = self._batch()
        tar = tar_weights(losses, valid, gamma=2.0)
        for seed in range(5):
            sh = shuffle_weights(losses, valid, gamma=2.0, generator=torch.Generator().manual_seed(seed))
            assert (sh[~valid] == 0).all()
            for b in range(4):
                assert sorted(sh[b][valid[b]].tolist()) == sorted(tar[b][valid[b]].tolist())

    def test_shuffle_moves_weights_and_is_deterministic(self):
        losses, valid = self._batch()
        tar = tar_weights(losses, valid)
        runs = [shuffle_weights(losses, valid, generator=torch.Generator().manual_seed(s)) for s in range(6)]
        assert any(not torch.equal(r, tar) for r in runs)
        again = shuffle_weights(losses, valid, generator=torch.Generator().manual_seed(4))
        assert torch.equal(again, runs[4])

    def test_random_weights_unit_mean_zero_padding_and_loss_independent(self):
        losses, valid = self._batch()
        other = torch.where(valid, 100.0 - 3.0 * losses.nan_to_num(0.0) ** 2, 0.0)  # other values, same mask
        w1 = random_weights(losses, valid, generator=torch.Generator().manual_seed(5))
        w2 = random_weights(other, valid, generator=torch.Generator().manual_seed(5))
        assert torch.equal(w1, w2)
        assert (w1[~valid] == 0).all() and (w1 >= 0).all()
        for mean in segment_means(w1, valid):
            assert mean == pytest.approx(1.0, abs=1e-5)
        w3 = random_weights(losses, valid, generator=torch.Generator().manual_seed(6))
        assert not torch.equal(w1, w3)

    # -- perturb_mask ---------------------------------------------------------------------------

    @staticmethod
    def _distinct():
        # Distinct losses; padding holds NaN and huge values, which must never be selected.
        losses = torch.tensor(
            [
                [0.9, 0.1, 0.5, 0.3, 0.8, 0.2, 0.7, 0.4, 1.0, 0.6],
                [5.0, 1.0, 3.0, 1e6, 2.0, 4.0, 7.0, math.nan, 6.0, 0.0],
                [0.2, 1e6, 0.1, 1e6, 0.4, 0.3, math.nan, 1e6, 1e6, 1e6],
            ]
        )
        valid = mask([[1] * 10, [1, 1, 1, 0, 1, 1, 1, 0, 0, 1], [1, 0, 1, 0, 1, 1, 0, 0, 0, 0]])
        return losses, valid

    @pytest.mark.parametrize("which", ["high", "low"])
    def test_perturb_mask_selects_extreme_losses(self, which):
        losses, valid = self._distinct()
        # fraction 0.3: M = 10, 7, 4 -> round(3.0) = 3, round(2.1) = 2, round(1.2) = 1.
        sel = perturb_mask(losses, valid, fraction=0.3, which=which, generator=torch.Generator().manual_seed(0))
        assert sel.dtype == torch.bool and sel.shape == losses.shape
        assert not (sel & ~valid).any()
        # row 0 (all valid): top-3 = 1.0 @8, 0.9 @0, 0.8 @4; bottom-3 = 0.1 @1, 0.2 @5, 0.3 @3.
        # row 1 valid: 0:5, 1:1, 2:3, 4:2, 5:4, 6:7, 9:0 -> top-2 = @6, @0; bottom-2 = @9, @1.
        # row 2 valid: 0:0.2, 2:0.1, 4:0.4, 5:0.3 -> top-1 = @4; bottom-1 = @2.
        expected_idx = {
            "high": [{0, 4, 8}, {0, 6}, {4}],
            "low": [{1, 3, 5}, {1, 9}, {2}],
        }[which]
        for b in range(3):
            assert set(torch.nonzero(sel[b]).flatten().tolist()) == expected_idx[b]

    def test_perturb_mask_counts_and_bounds(self):
        losses, valid = self._distinct()
        gen = torch.Generator().manual_seed(1)
        assert not perturb_mask(losses, valid, fraction=0.0, which="high", generator=gen).any()
        assert torch.equal(perturb_mask(losses, valid, fraction=1.0, which="low", generator=gen), valid)
        # fraction 0.6: 10 -> 6, 7 -> round(4.2) = 4, 4 -> round(2.4) = 2
        sel = perturb_mask(losses, valid, fraction=0.6, which="high", generator=gen)
        assert sel.sum(-1).tolist() == [6, 4, 2]
        # ties: all-equal losses still select exactly round(fraction * M) valid steps
        sel = perturb_mask(torch.zeros(3, 10), valid, fraction=0.3, which="low", generator=gen)
        assert sel.sum(-1).tolist() == [3, 2, 1] and not (sel & ~valid).any()

    def test_perturb_mask_float64_ranking(self):
        # float64 losses that differ below float32 resolution: 1 + k * 1e-12. The highest-loss
        # five steps are k = 15..19; they are not tied in the input dtype, so the docstring's
        # "highest-loss ones; ties are broken at random" leaves no room for chance here.
        # (Fails at the time of writing: perturb_mask ranks `losses.detach().float()`, which
        # rounds all 20 values to 1.0f and turns the ranking into a random tie-break.)
        losses = torch.tensor([[1.0 + k * 1e-12 for k in range(20)]], dtype=torch.float64)
        valid = torch.ones(1, 20, dtype=torch.bool)
        sel = perturb_mask(losses, valid, fraction=0.25, which="high", generator=torch.Generator().manual_seed(0))
        assert torch.nonzero(sel[0]).flatten().tolist() == [15, 16, 17, 18, 19]

    def test_perturb_mask_rejects_bad_arguments(self):
        losses, valid = self._distinct()
        with pytest.raises(ValueError, match="which"):
            perturb_mask(losses, valid, fraction=0.3, which="middle")
        for fraction in (-0.1, 1.5):
            with pytest.raises(ValueError, match="fraction"):
                perturb_mask(losses, valid, fraction=fraction, which="high")


# ---------------------------------------------------------------------------------------------
# The registry
# ---------------------------------------------------------------------------------------------

NAMES = [
    "uniform",
    "tar",
    "shuffle",
    "random",
    "invert",
    "perturb_high",
    "perturb_low",
    "tilted",
    "truncate",
    "keyframe",
    "focal",
    "dro_time",
    "tar_arm",
    "tar_dimnorm",
]


def test_registry_names():
    assert set(WEIGHTINGS) == set(NAMES)
    assert len(WEIGHTINGS) == len(NAMES)
    for name in NAMES:
        assert get_weighting(name).name == name
    assert get_weighting("perturb_high").perturb == "high"
    assert get_weighting("perturb_low").perturb == "low"
    assert get_weighting("tar").perturb is None


def test_unknown_weighting_lists_names():
    with pytest.raises(ValueError, match="unknown weighting 'nope'") as info:
        get_weighting("nope")
    for name in NAMES:
        assert name in str(info.value)


@pytest.mark.parametrize("name", NAMES)
def test_every_weighting_is_a_unit_mean_weighting(name):
    losses, valid = padded_batch()
    spec = WEIGHTINGS[name]
    params = spec.params()
    if spec.elementwise:  # per-element losses [B, L, 2] (the second dim doubled), reduced to step weights
        elements = torch.stack([losses, 2 * losses], -1)
        element_valid = valid[..., None].expand_as(elements)
        w = spec.weights(elements, element_valid, params, 1.0, None)
        assert w.shape == elements.shape and (w[~element_valid] == 0).all()
        w = w.mean(-1)
    else:
        inputs = {}
        if spec.reads_time:  # the segments are steps 0..5, 10..15 and 20..25 of episodes of 30 steps
            inputs["step"] = torch.arange(6) + torch.tensor([[0], [10], [20]])
            inputs["episode_length"] = torch.full((3, 6), 30)
        if spec.initial_state is not None:
            inputs["state"] = spec.initial_state(params)
        w = spec.weights(losses, valid, params, 1.0, torch.Generator().manual_seed(0), **inputs)
        if spec.initial_state is not None:
            w, state = w
            assert state.shape == inputs["state"].shape and float(state.exp().sum()) == pytest.approx(1.0)
    assert w.shape == losses.shape and w.dtype == losses.dtype
    assert torch.isfinite(w).all()
    assert (w >= 0).all()
    assert (w[~valid] == 0).all()
    for mean in segment_means(w, valid):
        assert mean == pytest.approx(1.0, abs=1e-5)


def test_registered_tar_matches_reference_with_params():
    losses, valid = padded_batch(torch.float64)
    params = TARParams(gamma=2.0, w_max=1.5, cap="exact")
    w = WEIGHTINGS["tar"].weights(losses, valid, params, 0.8, None)
    close(w, ref_tar(losses, valid, gamma=2.0, w_max=1.5, cap="exact", mix=0.8), rtol=2e-6)


# ---------------------------------------------------------------------------------------------
# The schedule (Sec. III-B)
# ---------------------------------------------------------------------------------------------


class TestMixSchedule:
    """alpha = 0 before ``start``, rises over ``ramp`` steps (linear or (1 - cos(pi x))/2),
    1 from ``start + ramp`` on; ``ramp=0`` is a switch; int and tensor steps agree."""

    # paper: start 20K, ramp 30K. x = (step - 20000) / 30000.
    LINEAR = [(0, 0.0), (19_999, 0.0), (20_000, 0.0), (27_500, 0.25), (35_000, 0.5), (50_000, 1.0), (10**9, 1.0)]
    # cosine: x = 1/4 -> (1 - cos(pi/4))/2 = (1 - sqrt2/2)/2 = 0.1464466; x = 3/4 -> 0.8535534.
    COSINE = [
        (0, 0.0),
        (20_000, 0.0),
        (27_500, (1 - SQRT2 / 2) / 2),
        (35_000, 0.5),
        (42_500, (1 + SQRT2 / 2) / 2),
        (50_000, 1.0),
        (10**9, 1.0),
    ]

    @pytest.mark.parametrize(("shape", "table"), [("linear", LINEAR), ("cosine", COSINE)])
    def test_values_by_hand(self, shape, table):
        s = MixSchedule(start=20_000, ramp=30_000, shape=shape)
        for step, alpha in table:
            assert s(step) == pytest.approx(alpha, abs=1e-12), step
            assert mix_at(step, start=20_000, ramp=30_000, shape=shape) == pytest.approx(alpha, abs=1e-12)
            t = s(torch.tensor(step))
            assert isinstance(t, torch.Tensor) and t.dtype == torch.float32
            assert float(t) == pytest.approx(alpha, abs=1e-6), step

    def test_ramp_zero_is_a_switch(self):
        s = MixSchedule(start=100, ramp=0)
        assert [s(0), s(99), s(100), s(101)] == [0.0, 0.0, 1.0, 1.0]
        assert [float(s(torch.tensor(k))) for k in (0, 99, 100, 101)] == [0.0, 0.0, 1.0, 1.0]

    def test_default_is_full_tar(self):
        assert MixSchedule()(0) == 1.0
        assert float(MixSchedule()(torch.tensor(0))) == 1.0

    def test_int_and_tensor_steps_agree(self):
        for shape in ("linear", "cosine"):
            s = MixSchedule(start=7, ramp=13, shape=shape)
            steps = list(range(0, 30))
            as_int = [s(k) for k in steps]
            as_tensor = s(torch.tensor(steps)).tolist()
            assert as_tensor == pytest.approx(as_int, abs=1e-6)

    @pytest.mark.parametrize(
        "kw",
        [
            {"start": -1},
            {"ramp": -5},
            {"start": 1.5},
            {"ramp": 30.0},
            {"start": True},
            {"ramp": False},
        ],
    )
    def test_rejects_bad_counts(self, kw):
        with pytest.raises(ValueError, match=r"must be an int >= 0"):
            MixSchedule(**kw)

    def test_rejects_unknown_shape(self):
        with pytest.raises(ValueError, match="shape must be one of"):
            MixSchedule(start=0, ramp=10, shape="sigmoid")

    def test_mix_at_checks_its_arguments_too(self):
        with pytest.raises(ValueError, match="shape must be one of"):
            mix_at(5, start=0, ramp=10, shape="Linear")
        with pytest.raises(ValueError, match=r"ramp must be an int >= 0"):
            mix_at(5, start=0, ramp=-10)


class TestWindowWeights:
    """``window_weights``: TAR's weight per step of a whole trajectory, averaged over its L-step windows."""

    def test_a_trajectory_shorter_than_the_window_is_one_segment(self):
        losses = [0.3, 0.1, 0.7]
        got = window_weights(torch.tensor(losses, dtype=torch.float64), slice_len=8)
        assert got.tolist() == pytest.approx(ref_tar_segment(losses, [True] * 3), rel=1e-9)

    def test_window_of_one_step_gives_ones(self):
        got = window_weights(torch.tensor([0.3, 0.1, 0.7]), slice_len=1)
        assert got.tolist() == [1.0, 1.0, 1.0]

    def test_two_windows_by_hand(self):
        losses = [0.0, 1.0, 0.0]
        # Windows [0, 1] and [1, 0]: each gives the high step e^1/(e^1+e^-1)*2 before the cap.
        first = ref_tar_segment(losses[:2], [True, True], w_max=10.0)
        second = ref_tar_segment(losses[1:], [True, True], w_max=10.0)
        got = window_weights(torch.tensor(losses, dtype=torch.float64), slice_len=2, w_max=10.0)
        assert got.tolist() == pytest.approx([first[0], (first[1] + second[0]) / 2, second[1]], rel=1e-9)
        assert got[1] == pytest.approx(2 * math.e / (math.e + 1 / math.e), rel=1e-6)

    @pytest.mark.parametrize(
        ("losses", "slice_len"), [(torch.zeros(0), 4), (torch.zeros(2, 3), 4), (torch.zeros(3), 0)]
    )
    def test_bad_input(self, losses, slice_len):
        with pytest.raises(ValueError):
            window_weights(losses, slice_len)
