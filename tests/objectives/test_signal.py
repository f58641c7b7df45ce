"""A ranking signal separate from the loss: an inner loss may return a detached ``[B, L]`` entry ``signal`` beside its
per-step loss; ``TARLoss`` (and the perturbation controls' choice of steps) then ranks the steps by it and still
weights the loss. Expected values come from the plain-Python reading of the paper (``tar_reference``)."""

from __future__ import annotations

import pytest
import torch
from objective_helpers import tar_loss
from tar_reference import ref_segment_loss, ref_weights
from tensordict import TensorDict
from torch import nn
from torchrl.objectives import LossModule

from tar_rl import WEIGHTINGS

B, L = 3, 5


class WithSignal(LossModule):
    """Per-step loss ``scale * target`` (one parameter, so the gradient is known) and, unless ``signal`` is None,
    that signal beside it."""

    reduction = "none"

    def __init__(self, signal: torch.Tensor | None, elements: int = 0):
        super().__init__()
        self.scale = nn.Parameter(torch.ones((), dtype=torch.float64))
        self.signal, self.elements = signal, elements

    def forward(self, td):
        loss = self.scale * td["target"]
        if self.elements:
            loss = loss[..., None].expand(*loss.shape, self.elements)
        out = {"loss_x": loss}
        if self.signal is not None:
            out["signal"] = self.signal
        return TensorDict(out, [])


def batch() -> TensorDict:
    target = torch.tensor(
        [[0.5, 1.0, 2.0, 0.1, 0.7], [3.0, 0.2, 0.4, 0.9, 1.1], [1.0, 1.0, 5.0, 0.3, 0.0]], dtype=torch.float64
    )
    valid = torch.ones(B, L, dtype=torch.bool)
    valid[2, 3:] = False
    return TensorDict({"target": target, ("collector", "mask"): valid}, [B, L])


# A signal whose order within each segment differs from the loss's.
SIGNAL = torch.tensor(
    [[2.0, 0.1, 0.3, 4.0, 1.0], [0.1, 5.0, 1.0, 0.2, 0.3], [0.2, 3.0, 0.1, 9.0, 9.0]], dtype=torch.float64
)


@pytest.mark.parametrize("name", ["tar", "uniform", "invert", "focal"])
def test_the_loss_itself_as_signal_changes_nothing(name):
    data = batch()
    plain = tar_loss(WithSignal(None), name, return_weights=True)(data)
    same = tar_loss(WithSignal(data["target"].clone()), name, return_weights=True)(data)
    for key in ("loss_tar", "weights", "weight_max", "weight_ess", "uniform_loss"):
        assert torch.equal(plain[key], same[key]), key


def test_the_weights_rank_the_signal_and_weight_the_loss():
    data = batch()
    inner = WithSignal(SIGNAL)
    out = tar_loss(inner, "tar", return_weights=True)(data)
    valid = data["collector", "mask"]
    w = ref_weights(SIGNAL.tolist(), valid.tolist())
    torch.testing.assert_close(out["weights"], torch.tensor(w, dtype=torch.float64))
    losses = data["target"].tolist()  # scale 1
    assert out["loss_tar"].item() == pytest.approx(ref_segment_loss(losses, w, valid.tolist()), rel=1e-12)
    # d loss / d scale: the weighted mean of the targets (the signal carries no gradient)
    (grad,) = torch.autograd.grad(out["loss_tar"], [inner.scale])
    assert grad.item() == pytest.approx(ref_segment_loss(losses, w, valid.tolist()), rel=1e-12)
    assert out["uniform_loss"].item() == pytest.approx(
        ref_segment_loss(losses, [[1.0] * L] * B, valid.tolist()), rel=1e-12
    )
    assert "signal" not in out.keys()  # not a diagnostic


def test_the_perturbation_control_chooses_the_highest_signal_steps():
    seen = []

    class Recorder(WithSignal):
        def forward(self, td):
            seen.append(td["action"].clone())
            out = super().forward(td)
            out["loss_x"] = out["loss_x"] + 0 * td["action"].sum(-1)
            return out

    data = batch()
    data["action"] = torch.zeros(B, L, 2)
    loss = tar_loss(Recorder(SIGNAL), "perturb_high", perturb_fraction=0.4, perturb_scale=1.0)
    loss(data)
    changed = (seen[0] != seen[1]).any(-1)
    # round(0.4 * M) steps per segment: 2, 2 and 1 (M = 5, 5, 3), the highest-signal valid ones
    assert [sorted(row.nonzero().flatten().tolist()) for row in changed] == [[0, 3], [1, 2], [1]]


class TestBadSignal:
    def test_non_finite_at_a_valid_step_is_refused_naming_it(self):
        signal = SIGNAL.clone()
        signal[1, 2] = float("nan")
        with pytest.raises(
            ValueError,
            match=r"non-finite per-step ranking signal 'signal' at a valid step.*first at index \(1, 2\), value nan",
        ):
            tar_loss(WithSignal(signal), "tar")(batch())
        with pytest.raises(ValueError, match=r"ranking signal 'signal'.*index \(1, 2\)"):
            tar_loss(WithSignal(signal), "perturb_high")(batch())

    def test_non_finite_propagates_as_a_non_finite_loss_does(self):
        signal = SIGNAL.clone()
        signal[0, 4] = float("inf")
        assert torch.isnan(tar_loss(WithSignal(signal), "tar", nonfinite="propagate")(batch())["loss_tar"])
        finite = tar_loss(WithSignal(SIGNAL), "tar")(batch())["loss_tar"]
        assert torch.equal(tar_loss(WithSignal(SIGNAL), "tar", nonfinite="propagate")(batch())["loss_tar"], finite)

    def test_non_finite_on_padding_is_ignored(self):
        signal = SIGNAL.clone()
        signal[2, 4] = float("nan")  # a padded step
        out = tar_loss(WithSignal(signal), "tar", return_weights=True)(batch())
        assert torch.isfinite(out["loss_tar"]) and out["weights"][2, 4] == 0

    def test_a_signal_not_of_the_batch_shape_is_refused(self):
        with pytest.raises(ValueError, match=r"ranking signal 'signal' must be a floating tensor of the batch shape"):
            tar_loss(WithSignal(SIGNAL[:, :4]), "tar")(batch())
        with pytest.raises(ValueError, match="one value per step"):
            tar_loss(WithSignal(SIGNAL.long()), "tar")(batch())

    @pytest.mark.parametrize("name", [n for n in WEIGHTINGS if WEIGHTINGS[n].elementwise])
    def test_an_element_weighting_refuses_a_signal(self, name):
        with pytest.raises(ValueError, match=rf"objective '{name}' scores per-element losses.*rank by the loss"):
            tar_loss(WithSignal(SIGNAL, elements=2), name)(batch())


def test_the_recorded_weights_rank_the_signal():
    """``weights.csv``'s weight along a demonstration is TAR's window weight of what TAR ranks, its loss the loss."""
    from tar_rl.objectives import window_weights
    from tar_rl.recipes.record import record_weights

    target = torch.tensor([0.5, 1.0, 2.0, 0.1, 0.7, 3.0], dtype=torch.float64)
    signal = torch.tensor([[2.0, 0.1, 0.3, 4.0, 1.0, 0.2]], dtype=torch.float64)
    episode = TensorDict({"target": target, "action": torch.zeros(6, 2)}, [6])
    rows = record_weights(tar_loss(WithSignal(signal), "tar"), [("reach", 0, episode)], 4, 10)
    assert [row[4] for row in rows] == pytest.approx(target.tolist())
    assert [row[5] for row in rows] == pytest.approx(window_weights(signal[0].float(), 4).tolist())
    assert [row[5] for row in rows] != pytest.approx(window_weights(target.float(), 4).tolist())
