"""The ``dro_time`` baseline (group DRO over bins of normalised episode time): specification, properties, state.

Expected values are worked out by hand in the comments, or computed by the plain-Python reading
of the rule below (lists and ``math`` only), never by the code under test.
"""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from numeric import close, mask, t64
from objective_helpers import tar_loss
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torchrl.objectives import BCLoss

from tar_rl.objectives import (
    WEIGHTINGS,
    DROTimeParams,
    MixSchedule,
    TARLoss,
    dro_time_weights,
    time_bins,
)


def uniform_log_q(bins: int) -> torch.Tensor:
    return torch.full((bins,), -math.log(bins), dtype=torch.float64)


# ---------------------------------------------------------------------------------------------
# A plain-Python reading of the rule (lists of rows; one call = one update, then the weights)
# ---------------------------------------------------------------------------------------------


def ref_bin(step: int, length: int, bins: int) -> int:
    return (bins * step) // length


def ref_dro_time(losses, valid, bins_of, q, eta, mix=1.0):
    """``(weights, new_q)`` from rows of losses, validity and bins, and the group weights ``q`` (a list)."""
    g = len(q)
    sums, counts = [0.0] * g, [0] * g
    for row, ok_row, bin_row in zip(losses, valid, bins_of):
        for x, ok, b in zip(row, ok_row, bin_row):
            if ok:
                sums[b] += x
                counts[b] += 1
    total = math.fsum(sums)
    n = sum(counts)
    mean = total / n if n else 0.0
    moved = []
    for b in range(g):
        if counts[b] and mean > 0:
            moved.append(q[b] * math.exp(eta * (sums[b] / counts[b]) / mean))
        else:
            moved.append(q[b])  # not seen (or all losses 0): not multiplied
    z = math.fsum(moved)
    new_q = [v / z for v in moved]
    weights = []
    for ok_row, bin_row in zip(valid, bins_of):
        m = sum(ok_row)
        mass = math.fsum(new_q[b] for ok, b in zip(ok_row, bin_row) if ok)
        w = [((1 - mix) + mix * m * new_q[b] / mass) if ok else 0.0 for ok, b in zip(ok_row, bin_row)]
        weights.append(w)
    return weights, new_q


# ---------------------------------------------------------------------------------------------
# Hand-worked values
# ---------------------------------------------------------------------------------------------


class TestHandValues:
    # G = 4, eta = 1/2, q uniform. Three segments of 4 steps:
    #   A: steps 2..5 of an episode of 8 steps: bins floor(4 t / 8) = 1, 1, 2, 2; losses 1, 3, 4, 6
    #   B: steps 6, 7 of an episode of 8 (bins 3, 3), then padding (NaN): losses 4, 4; all in one bin
    #   C: the last step of an episode of 10 (step 9: bin floor(36 / 10) = 3), then padding: loss 4
    # Bin means: bin 0 no valid step; bin 1 (1 + 3) / 2 = 2; bin 2 (4 + 6) / 2 = 5; bin 3 4.
    # Batch mean: (1 + 3 + 4 + 6 + 4 + 4 + 4) / 7 = 26 / 7.
    # Exponents eta * bin mean / batch mean: bin 0 none; bin 1 7/26; bin 2 35/52; bin 3 7/13.
    # q ∝ [1, e^(7/26), e^(35/52), e^(7/13)].
    # A's weights: 4 q_b / (2 q_1 + 2 q_2) = 2 q_b / (q_1 + q_2); B and C: uniform over their valid steps.
    LOSSES = [[1.0, 3.0, 4.0, 6.0], [4.0, 4.0, math.nan, math.nan], [4.0, math.nan, math.nan, math.nan]]
    VALID = [[1, 1, 1, 1], [1, 1, 0, 0], [1, 0, 0, 0]]
    STEP = [[2, 3, 4, 5], [6, 7, 7, 7], [9, 9, 9, 9]]
    LENGTH = [[8] * 4, [8] * 4, [10] * 4]

    def expected(self, mix=1.0):
        a, b, c = math.exp(7 / 26), math.exp(35 / 52), math.exp(7 / 13)
        z = 1 + a + b + c
        q = [1 / z, a / z, b / z, c / z]
        w1, w2 = 2 * a / (a + b), 2 * b / (a + b)
        blend = [(1 - mix) + mix * w for w in (w1, w1, w2, w2)]
        return [blend, [1, 1, 0, 0], [1, 0, 0, 0]], q

    def inputs(self):
        bins = time_bins(torch.tensor(self.STEP), torch.tensor(self.LENGTH), 4, mask(self.VALID))
        return t64(self.LOSSES), mask(self.VALID), bins

    def test_time_bins(self):
        _, _, bins = self.inputs()
        assert bins.tolist() == [[1, 1, 2, 2], [3, 3, 3, 3], [3, 3, 3, 3]]
        assert bins.dtype == torch.int64

    @pytest.mark.parametrize("mix", [1.0, 0.5])
    def test_update_then_weights(self, mix):
        losses, valid, bins = self.inputs()
        w, log_q = dro_time_weights(losses, valid, bins, uniform_log_q(4), eta=0.5, mix=mix)
        expected_w, expected_q = self.expected(mix)
        close(w, expected_w)
        close(log_q.exp(), expected_q)
        assert w.dtype == torch.float64 and log_q.dtype == torch.float64
        # the plain reference agrees, and a second step continues from the new q
        ref_w, ref_q = ref_dro_time(self.LOSSES, self.VALID, bins.tolist(), [0.25] * 4, 0.5, mix)
        close(w, ref_w)
        close(log_q.exp(), ref_q)
        w2, log_q2 = dro_time_weights(losses, valid, bins, log_q, eta=0.5, mix=mix)
        ref_w2, ref_q2 = ref_dro_time(self.LOSSES, self.VALID, bins.tolist(), ref_q, 0.5, mix)
        close(w2, ref_w2)
        close(log_q2.exp(), ref_q2)

    def test_the_registered_weighting_bins_the_steps_itself(self):
        losses, valid, _ = self.inputs()
        spec = WEIGHTINGS["dro_time"]
        params = DROTimeParams(dro_eta=0.5, dro_bins=4)
        state = spec.initial_state(params)
        close(state.exp(), [0.25] * 4)
        w, log_q = spec.weights(
            losses,
            valid,
            params,
            1.0,
            None,
            step=torch.tensor(self.STEP),
            episode_length=torch.tensor(self.LENGTH),
            state=state,
        )
        expected_w, expected_q = self.expected()
        close(w, expected_w)
        close(log_q.exp(), expected_q)
        close(state.exp(), [0.25] * 4)  # the given state is not modified

    def test_equal_losses(self):
        # every bin seen, equal losses: every exponent is eta, q stays uniform, the weights are uniform
        losses, valid = t64([[3.0] * 4, [3.0] * 4]), mask([[1, 1, 1, 1], [1, 1, 1, 0]])
        bins = torch.tensor([[0, 1, 2, 3], [0, 1, 2, 3]])
        w, log_q = dro_time_weights(losses, valid, bins, uniform_log_q(4), eta=0.7)
        close(w, [[1, 1, 1, 1], [1, 1, 1, 0]])
        close(log_q.exp(), [0.25] * 4)
        # bin 3 unseen: the three seen bins are multiplied by e^eta, bin 3 is not: q ∝ [e, e, e, 1] (eta = 1)
        valid = mask([[1, 1, 1, 0], [1, 1, 1, 0]])
        w, log_q = dro_time_weights(losses, valid, bins, uniform_log_q(4), eta=1.0)
        z = 3 * math.e + 1
        close(log_q.exp(), [math.e / z] * 3 + [1 / z])
        close(w, [[1, 1, 1, 0], [1, 1, 1, 0]])  # the valid steps' bins share one q

    def test_zero_losses_and_an_empty_batch_leave_q(self):
        log_q = torch.log(t64([0.1, 0.2, 0.3, 0.4]))
        bins = torch.tensor([[0, 1, 2, 3]])
        w, new = dro_time_weights(t64([[0.0] * 4]), mask([[1] * 4]), bins, log_q, eta=5.0)
        close(new.exp(), [0.1, 0.2, 0.3, 0.4])
        close(w, [[0.4, 0.8, 1.2, 1.6]])  # 4 q_b / sum q
        w, new = dro_time_weights(t64([[1.0] * 4]), mask([[0] * 4]), bins, log_q, eta=5.0)
        close(new.exp(), [0.1, 0.2, 0.3, 0.4])
        close(w, [[0, 0, 0, 0]])

    def test_scale_free(self):
        # losses times 1000: the same exponents, the same q and weights
        losses, valid, bins = self.inputs()
        w, log_q = dro_time_weights(losses, valid, bins, uniform_log_q(4), eta=0.5)
        w2, log_q2 = dro_time_weights(1000 * losses, valid, bins, uniform_log_q(4), eta=0.5)
        close(w2, w)
        close(log_q2, log_q)

    def test_time_bins_on_boundaries_and_one_bin(self):
        step = torch.arange(10)[None, :]
        length = torch.full((1, 10), 10)
        assert time_bins(step, length, 10).tolist() == [list(range(10))]
        assert time_bins(step, length, 3).tolist() == [[0, 0, 0, 0, 1, 1, 1, 2, 2, 2]]  # floor(3 t / 10)
        assert time_bins(step, length, 1).tolist() == [[0] * 10]
        # padding may hold anything: it is put in range and not checked
        bins = time_bins(torch.tensor([[4, 99, -3]]), torch.tensor([[5, 5, 0]]), 5, mask([[1, 0, 0]]))
        assert bins.tolist() == [[4, 4, 0]]

    def test_the_state_dtype_is_kept_and_half_losses_are_weighted_in_float32(self):
        losses, valid, bins = self.inputs()
        w, log_q = dro_time_weights(losses.to(torch.bfloat16), valid, bins, uniform_log_q(4).float(), eta=0.5)
        assert w.dtype == torch.bfloat16 and log_q.dtype == torch.float32
        close(w.double(), self.expected()[0], rtol=1e-2, atol=1e-2)


# ---------------------------------------------------------------------------------------------
# Bad input and parameters
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("dro_eta", 0.0),
        ("dro_eta", -0.1),
        ("dro_eta", math.nan),
        ("dro_eta", math.inf),
        ("dro_bins", 0),
        ("dro_bins", 1.5),
        ("dro_bins", True),
        ("dro_bins", "10"),
    ],
)
def test_bad_parameters_are_refused_with_their_name(field, value):
    with pytest.raises(ValueError, match=rf"^{field} must"):
        DROTimeParams(**{field: value})
    inner = BCLoss(TensorDictModule(torch.nn.Linear(2, 2), ["observation"], ["action"]), reduction="none")
    with pytest.raises(ValueError, match=rf"^{field} must"):
        tar_loss(inner, "dro_time", **{field: value})
    if field == "dro_eta":
        with pytest.raises(ValueError, match=r"^dro_eta must"):
            dro_time_weights(t64([[1.0]]), mask([[1]]), torch.tensor([[0]]), uniform_log_q(2), eta=value)


def test_defaults():
    assert (DROTimeParams.dro_eta, DROTimeParams.dro_bins) == (0.01, 10)
    params = DROTimeParams()
    assert (params.dro_eta, params.dro_bins) == (0.01, 10)
    spec = WEIGHTINGS["dro_time"]
    assert spec.reads_time and spec.initial_state is not None and not spec.stochastic and spec.perturb is None
    assert "Sagawa" in spec.summary
    close(spec.initial_state(params).exp(), [0.1] * 10)


def test_bad_input_is_refused():
    losses, valid, bins = t64([[1.0, 2.0]]), mask([[1, 1]]), torch.tensor([[0, 1]])
    with pytest.raises(ValueError, match="needs per-step losses >= 0"):
        dro_time_weights(t64([[1.0, -2.0]]), valid, bins, uniform_log_q(2))
    with pytest.raises(ValueError, match="non-finite"):
        dro_time_weights(t64([[1.0, math.nan]]), valid, bins, uniform_log_q(2))
    with pytest.raises(ValueError, match=r"time_bin must lie in 0 \.\. 1"):
        dro_time_weights(losses, valid, torch.tensor([[0, 2]]), uniform_log_q(2))
    with pytest.raises(ValueError, match="log_q must be a"):
        dro_time_weights(losses, valid, bins, uniform_log_q(2)[None])
    with pytest.raises(ValueError, match="outside their episode"):
        time_bins(torch.tensor([[0, 5]]), torch.tensor([[5, 5]]), 4)
    with pytest.raises(ValueError, match="outside their episode"):
        time_bins(torch.tensor([[-1, 2]]), torch.tensor([[5, 5]]), 4)
    with pytest.raises(TypeError, match="step must be an integer tensor"):
        time_bins(torch.tensor([[0.0, 1.0]]), torch.tensor([[5, 5]]), 4)
    with pytest.raises(ValueError, match="same shape"):
        time_bins(torch.tensor([[0, 1]]), torch.tensor([[5, 5, 5]]), 4)


# ---------------------------------------------------------------------------------------------
# Hypothesis properties
# ---------------------------------------------------------------------------------------------

SETTINGS = settings(max_examples=40, deadline=None)
_VALUE = st.one_of(st.floats(0.0, 100.0, width=32, allow_subnormal=False), st.sampled_from([0.0, 0.5, 1.0, 7.25]))


@st.composite
def timed_batches(draw):
    """Losses ``[B, L]`` (ties and zeros), a random mask (empty segments included), steps of episodes and G."""
    b, n = draw(st.integers(1, 5)), draw(st.integers(1, 16))
    bins = draw(st.integers(1, 12))
    vals = draw(st.lists(st.lists(_VALUE, min_size=n, max_size=n), min_size=b, max_size=b))
    rows = draw(st.lists(st.lists(st.booleans(), min_size=n, max_size=n), min_size=b, max_size=b))
    lengths = draw(st.lists(st.integers(n, 60), min_size=b, max_size=b))
    starts = [draw(st.integers(0, length - n)) for length in lengths]
    step = torch.tensor([[s + t for t in range(n)] for s in starts])
    length = torch.tensor(lengths)[:, None].expand(b, n).clone()
    return torch.tensor(vals, dtype=torch.float32), torch.tensor(rows, dtype=torch.bool), step, length, bins


@st.composite
def log_qs(draw, bins: int):
    raw = draw(st.lists(st.floats(-30.0, 0.0), min_size=bins, max_size=bins))
    x = torch.tensor(raw, dtype=torch.float64)
    return x - torch.logsumexp(x, 0)


@SETTINGS
@given(
    batch=timed_batches(),
    eta=st.sampled_from([1e-3, 0.01, 1.0, 30.0]),
    mix=st.sampled_from([0.3, 1.0]),
    data=st.data(),
)
def test_nonnegative_unit_mean_zero_on_padding_no_gradient(batch, eta, mix, data):
    losses, valid, step, length, bins = batch
    log_q = data.draw(log_qs(bins))
    losses = losses.clone().requires_grad_(True)
    w, new = dro_time_weights(losses, valid, time_bins(step, length, bins, valid), log_q, eta=eta, mix=mix)
    assert w.shape == losses.shape and w.dtype == losses.dtype
    assert torch.isfinite(w).all() and (w >= 0).all()
    assert (w[~valid] == 0).all()
    for i in range(losses.shape[0]):
        if valid[i].any():
            assert float(w[i][valid[i]].double().mean()) == pytest.approx(1.0, abs=1e-5)
    assert not w.requires_grad and not new.requires_grad
    (g,) = torch.autograd.grad((w * losses).sum(), losses)
    torch.testing.assert_close(g, w, rtol=0, atol=0)
    assert float(new.exp().sum()) == pytest.approx(1.0, abs=1e-12)


@SETTINGS
@given(batch=timed_batches(), eta=st.sampled_from([0.01, 1.0]), data=st.data())
def test_matches_the_plain_reference(batch, eta, data):
    losses, valid, step, length, bins = batch
    log_q = data.draw(log_qs(bins))
    x = losses.double()
    w, new = dro_time_weights(x, valid, time_bins(step, length, bins), log_q, eta=eta, mix=0.6)
    ref_bins = [[ref_bin(s, n, bins) for s, n in zip(sr, nr)] for sr, nr in zip(step.tolist(), length.tolist())]
    ref_w, ref_q = ref_dro_time(x.tolist(), valid.tolist(), ref_bins, log_q.exp().tolist(), eta, mix=0.6)
    close(w, ref_w, rtol=1e-9, atol=1e-9)
    close(new.exp(), ref_q, rtol=1e-9, atol=1e-15)


_EXTREME = st.sampled_from([0.0, 1e-30, 1e-6, 1.0, 1e6, 1e30, 3e38])


@settings(max_examples=15, deadline=None)
@given(
    rows=st.lists(st.lists(_EXTREME, min_size=8, max_size=8), min_size=2, max_size=4),
    eta=st.sampled_from([0.01, 10.0, 1000.0]),
    bins=st.integers(1, 8),
    seed=st.integers(0, 2**16),
)
def test_q_stays_a_distribution_over_many_updates_with_extreme_losses(rows, eta, bins, seed):
    g = torch.Generator().manual_seed(seed)
    log_q = uniform_log_q(bins)
    base = torch.tensor(rows, dtype=torch.float32)
    b, n = base.shape
    for _ in range(100):
        losses = base[:, torch.randperm(n, generator=g)]
        valid = torch.rand(b, n, generator=g) > 0.2
        step = torch.randint(0, 40 - n, (b, 1), generator=g) + torch.arange(n)
        w, log_q = dro_time_weights(losses, valid, time_bins(step, torch.full((b, n), 40), bins), log_q, eta=eta)
        assert torch.isfinite(log_q).all() and float(log_q.max()) <= 1e-12
        assert float(log_q.exp().sum()) == pytest.approx(1.0, abs=1e-9)
        assert torch.isfinite(w).all() and (w >= 0).all() and (w[~valid] == 0).all()
        for i in range(b):
            if valid[i].any():
                assert float(w[i][valid[i]].double().mean()) == pytest.approx(1.0, abs=1e-4)


# ---------------------------------------------------------------------------------------------
# In TARLoss: time input, state, resume
# ---------------------------------------------------------------------------------------------

OBS, ACT, B, L = 3, 2, 6, 8


def make_loss(seed: int = 0, **kwargs) -> TARLoss:
    torch.manual_seed(seed)
    actor = TensorDictModule(torch.nn.Linear(OBS, ACT), ["observation"], ["action"])
    kwargs = {"dro_eta": 0.5, "dro_bins": 4, "return_weights": True, **kwargs}
    return tar_loss(BCLoss(actor, loss_function="mse", reduction="none"), "dro_time", **kwargs)


def make_batch(seed: int) -> TensorDict:
    """Segments of 8 steps from episodes of 12..40 steps, some padded at their episode's end."""
    g = torch.Generator().manual_seed(seed)
    length = torch.randint(12, 41, (B, 1), generator=g)
    start = (torch.rand(B, 1, generator=g) * (length - L + 3)).long()  # some run past the end: padding
    raw = start + torch.arange(L)
    valid = raw < length
    step = torch.minimum(raw, length - 1)  # padding repeats the last real step
    return TensorDict(
        {
            "observation": torch.randn(B, L, OBS, generator=g),
            "action": torch.randn(B, L, ACT, generator=g),
            "step": step,
            "episode_length": length.expand(B, L).clone(),
            ("collector", "mask"): valid,
        },
        [B, L],
    )


class TestInTARLoss:
    def test_weights_follow_the_pure_function_and_the_state_moves_on_training_steps(self):
        loss = make_loss()
        assert loss.time_keys == ("step", "episode_length")
        assert {"step", "episode_length"} <= set(loss.in_keys)
        log_q = uniform_log_q(4)
        close(loss.weighting_state.value, log_q)
        for seed in range(3):
            batch = make_batch(seed)
            out = loss(batch)
            with torch.no_grad():
                step_losses = loss.step_losses(batch)
            valid = batch["collector", "mask"]
            w, log_q = dro_time_weights(
                step_losses, valid, time_bins(batch["step"], batch["episode_length"], 4, valid), log_q, eta=0.5
            )
            torch.testing.assert_close(out["weights"], w)
            torch.testing.assert_close(loss.weighting_state.value, log_q)
            out["loss_tar"].backward()
        assert not torch.allclose(log_q, uniform_log_q(4))

    def test_eval_mode_and_no_grad_leave_the_state(self):
        loss = make_loss()
        loss(make_batch(0))
        before = loss.weighting_state.value.clone()
        train_weights = make_loss()(make_batch(0))["weights"]  # a fresh loss's first step
        with torch.no_grad():
            a = loss(make_batch(1))
        loss.eval()
        b = loss(make_batch(1))
        loss.train()
        assert torch.equal(loss.weighting_state.value, before)
        torch.testing.assert_close(a["weights"], b["weights"])
        assert train_weights.shape == a["weights"].shape
        # the weights of an eval-mode call are those of a training step from the same state
        c = loss(make_batch(1))
        torch.testing.assert_close(c["weights"], a["weights"])
        assert not torch.equal(loss.weighting_state.value, before)

    def test_state_round_trip_and_exact_continuation(self):
        loss = make_loss()
        for seed in range(3):
            loss(make_batch(seed))["loss_tar"].backward()
        state = loss.state_dict()
        assert state["weighting_state.value"].shape == (4,) and state["weighting_state.value"].dtype == torch.float64
        other = make_loss(seed=0)
        close(other.weighting_state.value, uniform_log_q(4))
        other.load_state_dict(state)
        assert torch.equal(other.weighting_state.value, loss.weighting_state.value)
        for seed in range(3, 6):
            a, b = loss(make_batch(seed)), other(make_batch(seed))
            assert torch.equal(a["weights"], b["weights"]) and torch.equal(a["loss_tar"], b["loss_tar"])
        assert torch.equal(other.weighting_state.value, loss.weighting_state.value)
        # a loss of another size of state refuses it
        with pytest.raises(RuntimeError, match=r"weighting_state\.value"):
            make_loss(dro_bins=5).load_state_dict(state)

    def test_only_a_stateful_weighting_has_the_buffer(self):
        actor = TensorDictModule(torch.nn.Linear(OBS, ACT), ["observation"], ["action"])
        for name in WEIGHTINGS:
            loss = tar_loss(BCLoss(actor, loss_function="mse", reduction="none"), name)
            assert ("weighting_state.value" in loss.state_dict()) == (WEIGHTINGS[name].initial_state is not None)
            assert ("step" in loss.in_keys) == WEIGHTINGS[name].reads_time
            assert bool(loss.time_keys) == WEIGHTINGS[name].reads_time

    def test_the_schedule_blends_and_the_state_moves_before_it_starts(self):
        loss = make_loss(schedule=MixSchedule(start=2, ramp=0))
        for seed in range(2):
            out = loss(make_batch(seed))
            valid = make_batch(seed)["collector", "mask"]
            torch.testing.assert_close(out["weights"], valid.float())  # alpha 0: uniform
        assert not torch.allclose(loss.weighting_state.value, uniform_log_q(4))  # q learns from the start
        assert float(loss(make_batch(2))["tar_mix"]) == 1.0

    @pytest.mark.parametrize("missing", ["step", "episode_length"])
    def test_missing_time_entries_are_named(self, missing):
        batch = make_batch(0).exclude(missing)
        with pytest.raises(KeyError, match=rf"dro_time weighting .* no '{missing}' entry"):
            make_loss()(batch)

    def test_time_keys_can_be_renamed_and_are_checked(self):
        batch = make_batch(0)
        renamed = batch.clone()
        renamed["t"] = renamed.pop("step")
        loss = make_loss()
        loss.set_keys(step="t")
        assert loss.time_keys == ("t", "episode_length") and "t" in loss.in_keys
        torch.testing.assert_close(loss(renamed)["weights"], make_loss()(batch)["weights"])
        bad = batch.clone()
        bad["step"] = bad["step"].float()
        with pytest.raises(ValueError, match="'step' must be an integer tensor"):
            make_loss()(bad)
        bad = batch.clone()
        bad["step"] = bad["step"] + 100
        with pytest.raises(ValueError, match="outside their episode"):
            make_loss()(bad)

    def test_always_eager(self):
        loss = make_loss(compile_weights="always")
        assert loss._weight_function(torch.device("cpu")) is WEIGHTINGS["dro_time"].weights
