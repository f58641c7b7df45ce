"""The element weightings ``tar_arm`` and ``tar_dimnorm``: hand-computed values, properties, ``TARLoss``, bad input.

Expected values come from hand arithmetic or from ``tar_reference`` (an independent plain-Python
reading of Eqs. 4-8) applied to scores worked out here from the definitions.
"""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from objective_helpers import tar_loss
from tar_reference import ref_tar_segment
from tensordict import TensorDict
from torchrl.objectives import LossModule

from tar_rl.objectives import (
    WEIGHTINGS,
    TARArmParams,
    tar_arm_weights,
    tar_dimnorm_weights,
    tar_weights,
)

INF = math.inf


def t64(x) -> torch.Tensor:
    return torch.tensor(x, dtype=torch.float64)


def close(got: torch.Tensor, expected, **kw) -> None:
    torch.testing.assert_close(got.double(), t64(expected), **kw)


def ones_like_bool(x: torch.Tensor) -> torch.Tensor:
    return torch.ones(x.shape, dtype=torch.bool)


# ---------------------------------------------------------------------------------------------
# tar_arm
# ---------------------------------------------------------------------------------------------


class TestTarArm:
    def test_two_steps_by_hand(self):
        # arm scores [0, 2]: z = [-1, 1]; weights 2 e^{-+1} / (e^-1 + e^1); the gripper (dim 1) weighs 1
        losses = t64([[[0.0, 9.0], [2.0, 0.0]]])
        w = tar_arm_weights(losses, ones_like_bool(losses), w_max=INF)
        z = math.exp(-1) + math.exp(1)
        close(w, [[[2 * math.exp(-1) / z, 1.0], [2 * math.exp(1) / z, 1.0]]])

    def test_the_gripper_loss_does_not_move_the_weights(self):
        arm = t64([[[1.0], [4.0], [2.0], [8.0]]])
        small, large = t64([[[0.0]] * 4]), t64([[[100.0], [0.0], [50.0], [3.0]]])
        a = tar_arm_weights(torch.cat([arm, small], -1), torch.ones(1, 4, 2, dtype=torch.bool))
        b = tar_arm_weights(torch.cat([arm, large], -1), torch.ones(1, 4, 2, dtype=torch.bool))
        torch.testing.assert_close(a, b)
        close(a[..., 0], [ref_tar_segment([1.0, 4.0, 2.0, 8.0], [True] * 4)])
        close(a[..., 1], [[1.0] * 4])

    def test_padding_lone_step_and_equal_losses(self):
        # [B=3, L=3, A=3], gripper = the last dim; arm score = mean of dims 0, 1
        losses = t64(
            [
                [[1.0, 3.0, 7.0], [0.0, 0.0, 1.0], [float("nan")] * 3],  # scores 2, 0, padding
                [[5.0, 5.0, 0.0], [float("nan")] * 3, [float("nan")] * 3],  # one valid step
                [[2.0, 4.0, 9.0], [3.0, 3.0, 0.0], [6.0, 0.0, 1.0]],  # equal scores 3, 3, 3
            ]
        )
        steps = torch.tensor([[1, 1, 0], [1, 0, 0], [1, 1, 1]], dtype=torch.bool)
        valid = steps[..., None].expand(3, 3, 3).clone()
        w = tar_arm_weights(losses, valid, gamma=0.5, w_max=INF)
        z = math.exp(0.5) + math.exp(-0.5)  # scores [2, 0]: z-scores [1, -1]
        first = [2 * math.exp(0.5) / z, 2 * math.exp(-0.5) / z]
        close(w[0], [[first[0], first[0], 1.0], [first[1], first[1], 1.0], [0.0, 0.0, 0.0]])
        close(w[1], [[1.0, 1.0, 1.0], [0.0] * 3, [0.0] * 3])
        close(w[2], [[1.0] * 3] * 3)

    @pytest.mark.parametrize("cap", ["paper", "exact"])
    @pytest.mark.parametrize("mix", [1.0, 0.4])
    def test_matches_the_reference_on_arm_scores(self, cap, mix):
        g = torch.Generator().manual_seed(0)
        losses = torch.rand(4, 7, 3, generator=g, dtype=torch.float64) ** 3 * 5
        valid = torch.ones(4, 7, 3, dtype=torch.bool)
        valid[1, 5:] = False
        w = tar_arm_weights(losses, valid, gripper_dims=(0,), gamma=2.0, w_max=2.0, cap=cap, mix=mix)
        for i in range(4):
            steps = valid[i, :, 0].tolist()
            scores = [(losses[i, t, 1] + losses[i, t, 2]).item() / 2 for t in range(7)]
            expected = ref_tar_segment(scores, steps, gamma=2.0, w_max=2.0, cap=cap, mix=mix)
            close(w[i, :, 1], expected)
            close(w[i, :, 2], expected)
            close(w[i, :, 0], [1.0 if ok else 0.0 for ok in steps])

    def test_chunked_losses_score_the_valid_chunk_entries(self):
        # [B=1, L=2, H=2, A=2]: the second step's second chunk entry is padding (NaN there)
        losses = t64([[[[1.0, 0.0], [3.0, 5.0]], [[4.0, 1.0], [float("nan"), float("nan")]]]])
        valid = torch.ones(1, 2, 2, 2, dtype=torch.bool)
        valid[0, 1, 1] = False
        w = tar_arm_weights(losses, valid, w_max=INF)
        # arm scores: step 0 mean(1, 3) = 2, step 1 mean(4) = 4: z = [-1, 1]
        z = math.exp(-1) + math.exp(1)
        lo, hi = 2 * math.exp(-1) / z, 2 * math.exp(1) / z
        close(w, [[[[lo, 1.0], [lo, 1.0]], [[hi, 1.0], [0.0, 0.0]]]])


# ---------------------------------------------------------------------------------------------
# tar_dimnorm
# ---------------------------------------------------------------------------------------------


class TestTarDimnorm:
    def test_by_hand(self):
        # dim 0's mean over the batch = (0 + 4 + 4 + 0) / 4 = 2, dim 1's = (20 + 0 + 20 + 20) / 4 = 15
        losses = t64([[[0.0, 20.0], [4.0, 0.0]], [[4.0, 20.0], [0.0, 20.0]]])
        w = tar_dimnorm_weights(losses, ones_like_bool(losses), w_max=INF)
        # normalised step scores: mean(0, 4/3) = 2/3 < mean(2, 0) = 1 (the raw means 10 > 2 order them the
        # other way); mean(2, 4/3) = 5/3 > mean(0, 4/3) = 2/3. Two steps: z-scores -1 and 1.
        z = math.exp(-1) + math.exp(1)
        lo, hi = 2 * math.exp(-1) / z, 2 * math.exp(1) / z
        close(w, [[[lo, lo], [hi, hi]], [[hi, hi], [lo, lo]]])

    def test_one_dimension_is_tar(self):
        g = torch.Generator().manual_seed(1)
        losses = torch.rand(5, 9, 1, generator=g, dtype=torch.float64)
        valid = torch.ones(5, 9, 1, dtype=torch.bool)
        valid[2, 4:] = False
        torch.testing.assert_close(
            tar_dimnorm_weights(losses, valid)[..., 0], tar_weights(losses[..., 0], valid[..., 0])
        )

    def test_the_scale_comes_from_valid_elements_only_and_a_zero_dimension_scores_zero(self):
        losses = t64([[[1.0, 0.0], [3.0, 0.0], [1e6, 1e6]]])
        valid = torch.tensor([[[True, True], [True, True], [False, False]]])
        w = tar_dimnorm_weights(losses, valid, w_max=INF)
        # dim 0 scale 2 (the padded 1e6 is ignored), dim 1 all 0: scores 0.25, 0.75
        z = math.exp(-1) + math.exp(1)
        close(w, [[[2 * math.exp(-1) / z] * 2, [2 * math.exp(1) / z] * 2, [0.0, 0.0]]])

    def test_the_scale_is_the_batchs(self):
        # the same segment scored beside another: the weights change because dim 1's scale does
        seg = t64([[[1.0, 1.0], [2.0, 0.0], [0.0, 4.0]]])
        other = t64([[[1.0, 100.0], [1.0, 100.0], [1.0, 100.0]]])
        alone = tar_dimnorm_weights(seg, ones_like_bool(seg), w_max=INF)[0]
        together = tar_dimnorm_weights(torch.cat([seg, other]), torch.ones(2, 3, 2, dtype=torch.bool), w_max=INF)[0]
        # alone: scales (1, 5/3): scores [0.8, 1.0, 1.2]; together: scales (1, 305/6)
        close(alone[:, 0], ref_tar_segment([0.5 + 0.3, 1.0, 0.6 * 2], [True] * 3, w_max=INF))
        s = 6 / 305
        close(together[:, 0], ref_tar_segment([(1 + s) / 2, 1.0, 4 * s / 2], [True] * 3, w_max=INF))


# ---------------------------------------------------------------------------------------------
# Properties
# ---------------------------------------------------------------------------------------------

ELEMENT = ("tar_arm", "tar_dimnorm")


@st.composite
def element_batches(draw):
    b, n, a = draw(st.integers(1, 3)), draw(st.integers(1, 6)), draw(st.integers(2, 4))
    values = draw(st.lists(st.floats(0.0, 50.0), min_size=b * n * a, max_size=b * n * a))
    lengths = draw(st.lists(st.integers(0, n), min_size=b, max_size=b))
    losses = t64(values).reshape(b, n, a)
    steps = torch.arange(n)[None, :] < t64(lengths)[:, None]
    return losses, steps[..., None].expand(b, n, a).clone()


def step_weights(w: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    return (w * valid).sum(-1) / valid.sum(-1).clamp_min(1)


@settings(max_examples=40, deadline=None)
@given(
    batch=element_batches(),
    name=st.sampled_from(ELEMENT),
    mix=st.sampled_from([0.3, 1.0]),
    cap=st.sampled_from(["paper", "exact"]),
)
def test_properties(batch, name, mix, cap):
    losses, valid = batch
    losses.requires_grad_(True)
    fn = WEIGHTINGS[name].weights
    w = fn(losses, valid, WEIGHTINGS[name].params(cap=cap), mix, None)
    assert not w.requires_grad
    assert w.shape == losses.shape and (w >= 0).all() and (w[~valid] == 0).all()
    steps = valid.any(-1)
    per_step = step_weights(w, valid)
    rows = steps.any(-1)
    mean = (per_step * steps).sum(-1)[rows] / steps.sum(-1)[rows]
    torch.testing.assert_close(mean, torch.ones_like(mean), atol=1e-9, rtol=1e-9)
    if name == "tar_arm":
        assert (w[..., -1][valid[..., -1]] == 1).all()


@settings(max_examples=30, deadline=None)
@given(batch=element_batches(), name=st.sampled_from(ELEMENT), data=st.data())
def test_permuting_the_steps_permutes_the_weights(batch, name, data):
    losses, _ = batch
    valid = torch.ones(losses.shape, dtype=torch.bool)
    order = torch.tensor(data.draw(st.permutations(list(range(losses.shape[1])))))
    fn = WEIGHTINGS[name].weights
    w = fn(losses, valid, WEIGHTINGS[name].params(), 1.0, None)
    torch.testing.assert_close(fn(losses[:, order], valid, WEIGHTINGS[name].params(), 1.0, None), w[:, order])


# ---------------------------------------------------------------------------------------------
# Through TARLoss
# ---------------------------------------------------------------------------------------------


class ChunkedLoss(LossModule):
    """Per-element squared error ``[B, L, H, A]`` of a linear head, for the element weightings."""

    def __init__(self, seed: int = 0):
        super().__init__()
        torch.manual_seed(seed)
        self.net = torch.nn.Linear(3, 2 * 4)
        self.reduction = "none"

    def forward(self, td):
        pred = self.net(td["observation"]).reshape(*td.batch_size, 2, 4)
        return TensorDict({"loss_chunk": (pred - td["action_chunk"]).square()}, td.batch_size)


def chunk_batch() -> TensorDict:
    g = torch.Generator().manual_seed(5)
    chunk_valid = torch.ones(3, 5, 2, dtype=torch.bool)
    chunk_valid[:, -1, 1] = False
    return TensorDict(
        {
            "observation": torch.randn(3, 5, 3, generator=g),
            "action_chunk": torch.randn(3, 5, 2, 4, generator=g),
            "action_chunk_valid": chunk_valid,
            ("collector", "mask"): torch.tensor([[True] * 5, [True] * 5, [True] * 2 + [False] * 3]),
        },
        [3, 5],
    )


@pytest.mark.parametrize("name", ELEMENT)
def test_tarloss_equals_the_hand_reduction_in_value_and_gradient(name):
    batch = chunk_batch()
    loss = tar_loss(ChunkedLoss(), name, return_weights=True, gamma=2.0)
    loss.set_keys(event_valid="action_chunk_valid")
    out = loss(batch)
    out["loss_tar"].backward()
    got = [p.grad.clone() for p in loss.parameters()]

    # By hand: element weights from the registered function, each step's loss the mean over its
    # valid elements of weight * loss, a segment the mean over its valid steps, the loss the mean
    # over segments.
    inner = ChunkedLoss()
    elements = inner(batch)["loss_chunk"]
    valid = batch["collector", "mask"]
    event = batch["action_chunk_valid"][..., None].expand(3, 5, 2, 4)
    full = event & valid[..., None, None]
    w = WEIGHTINGS[name].weights(elements.detach(), full, WEIGHTINGS[name].params(gamma=2.0), 1.0, None)
    per_step = (w * elements * event).sum((-1, -2)) / event.sum((-1, -2))
    expected = torch.stack([per_step[i][valid[i]].mean() for i in range(3)]).mean()
    expected.backward()
    torch.testing.assert_close(out["loss_tar"], expected)
    for a, b in zip(got, inner.parameters()):
        torch.testing.assert_close(a, b.grad)
    # the reported step weight: the mean of the step's valid element weights, unit mean per segment
    torch.testing.assert_close(out["weights"], ((w * event).sum((-1, -2)) / event.sum((-1, -2))) * valid)
    steps = out["weights"]
    torch.testing.assert_close((steps * valid).sum(-1) / valid.sum(-1), torch.ones(3))
    uniform = tar_loss(ChunkedLoss(), "uniform")
    uniform.set_keys(event_valid="action_chunk_valid")
    torch.testing.assert_close(out["uniform_loss"], uniform(batch)["uniform_loss"])


def test_an_element_weighting_giving_a_step_one_weight_is_that_step_weighting():
    # one action dim: tar_dimnorm scores each step by its loss over a constant, so its weights are TAR's
    batch = chunk_batch()
    batch["action_chunk"] = batch["action_chunk"][..., :1].expand(3, 5, 2, 4).clone()

    class OneDim(ChunkedLoss):
        def forward(self, td):
            return TensorDict({"loss_chunk": super().forward(td)["loss_chunk"][..., :1]}, td.batch_size)

    a, b = tar_loss(OneDim(), "tar_dimnorm"), tar_loss(OneDim(), "tar")
    for loss in (a, b):
        loss.set_keys(event_valid="action_chunk_valid")
    torch.testing.assert_close(a(batch)["loss_tar"], b(batch)["loss_tar"])


class TestBadInput:
    def test_a_per_step_inner_loss_is_refused_by_name(self):
        class PerStep(ChunkedLoss):
            def forward(self, td):
                return TensorDict({"loss_chunk": super().forward(td)["loss_chunk"].mean((-1, -2))}, td.batch_size)

        for name in ELEMENT:
            with pytest.raises(ValueError, match=f"objective '{name}' weights per-element losses.*one loss per step"):
                tar_loss(PerStep(), name)(chunk_batch())

    def test_nan_at_a_valid_element_is_refused_and_at_padding_ignored(self):
        batch = chunk_batch()
        batch["action_chunk"][2, 4, 0, 0] = float("nan")  # a padded step
        batch["action_chunk"][0, 4, 1, 2] = float("nan")  # a padded chunk entry
        loss = tar_loss(ChunkedLoss(), "tar_arm")
        loss.set_keys(event_valid="action_chunk_valid")
        assert torch.isfinite(loss(batch)["loss_tar"])
        batch["action_chunk"][1, 2, 0, 3] = float("nan")
        with pytest.raises(ValueError, match="non-finite per-element loss"):
            loss(batch)

    @pytest.mark.parametrize("dims", [(), [-1], (1, 1), (True,), (0.5,)])
    def test_gripper_dims_refused_when_built(self, dims):
        with pytest.raises(ValueError, match="gripper_dims must be a non-empty tuple of distinct ints"):
            TARArmParams(gripper_dims=dims)
        with pytest.raises(ValueError, match="gripper_dims"):
            tar_loss(ChunkedLoss(), "tar_arm", gripper_dims=dims)

    @pytest.mark.parametrize(
        "dims, message", [((4,), "outside the loss's 4 action dims"), ((0, 1, 2, -1), "cover all")]
    )
    def test_gripper_dims_that_do_not_fit_the_loss(self, dims, message):
        loss = tar_loss(ChunkedLoss(), "tar_arm", gripper_dims=dims)
        with pytest.raises(ValueError, match=message):
            loss(chunk_batch())
