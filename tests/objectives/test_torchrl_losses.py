"""TARLoss around TorchRL's own losses on ``("vla_action", "chunk")`` segments ``[B, L]``: ``ACTLoss`` (with
``ACTModel``) and ``BCLoss``.

Expected values are computed by hand from the networks' outputs (the ACT model's, caught by a forward hook
during ``TARLoss``'s own call, so the latent sample is the same) and weighted with the plain-Python
reference of Eqs. 3-8 (``tests/tar_reference.py``).
"""

from __future__ import annotations

import pytest
import torch
from tar_reference import ref_segment_loss, ref_weights
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.modules.models import ACTModel
from torchrl.objectives import ACTLoss, BCLoss

from tar_rl.objectives import TARLoss, TARParams

B, L, H, OBS, A = 3, 5, 4, 6, 2
CHUNK = ("vla_action", "chunk")


def chunk_segments(seed: int = 1) -> TensorDict:
    """``[B, L]`` segments with a padded step and chunks running past the end of their episode."""
    g = torch.Generator().manual_seed(seed)
    valid = torch.ones(B, L, dtype=torch.bool)
    valid[2, 3:] = False
    chunk_valid = torch.ones(B, L, H, dtype=torch.bool)
    chunk_valid[:, -1, 2:] = False  # True = a real chunk entry
    chunk_valid[1, -2, 3:] = False
    return TensorDict(
        {
            "observation": torch.randn(B, L, OBS, generator=g),
            CHUNK: torch.randn(B, L, H, A, generator=g),
            "chunk_valid": chunk_valid,
            ("collector", "mask"): valid,
        },
        [B, L],
    )


class TestACTLoss:
    def make(self):
        torch.manual_seed(0)
        model = ACTModel(
            obs_dim=OBS,
            action_dim=A,
            chunk_size=H,
            hidden_dim=16,
            nheads=2,
            num_encoder_layers=1,
            num_decoder_layers=1,
            latent_dim=4,
            dropout=0.0,
        )
        outputs = []
        model.register_forward_hook(lambda module, args, out: outputs.append(out))
        actor = TensorDictModule(model, ["observation", "action_chunk"], ["action_pred", "mu", "log_var"])
        inner = ACTLoss(actor, kl_weight=10.0, reduction="none")
        return TARLoss(inner, "tar", params=TARParams(gamma=1.5, w_max=2.0), loss_key="loss_act"), outputs

    def test_weights_each_steps_act_loss_kl_included(self):
        loss, outputs = self.make()
        batch = chunk_segments()
        out = loss(batch)
        pred, mu, log_var = (t.detach() for t in outputs[-1])
        # TorchRL's ACT loss per step: the L1 error over every chunk entry (padded ones too: it does not mask)
        # plus kl_weight times the latent's KL; TAR weights that sum.
        recon = (pred - batch[CHUNK]).abs().mean((-2, -1))
        kl = (-0.5 * (1 + log_var - mu.square() - log_var.exp())).sum(-1)
        per_step = (recon + 10.0 * kl).tolist()
        valid = batch["collector", "mask"].tolist()
        weights = ref_weights(per_step, valid, gamma=1.5, w_max=2.0)
        assert out["loss_tar"].item() == pytest.approx(ref_segment_loss(per_step, weights, valid), rel=1e-5)
        # its detached per-step entries are diagnostics: their mean over the valid steps, not added to the loss
        ones = [[1.0] * L] * B
        assert out["inner_loss_kl"].item() == pytest.approx(ref_segment_loss(kl.tolist(), ones, valid), rel=1e-5)
        assert out["inner_loss_reconstruction"].item() == pytest.approx(
            ref_segment_loss(recon.tolist(), ones, valid), rel=1e-5
        )
        assert [k for k in out.keys() if k.startswith("loss")] == ["loss_tar"]
        assert not out["inner_loss_kl"].requires_grad
        out["loss_tar"].backward()
        assert any(p.grad is not None and bool(p.grad.abs().sum() > 0) for p in loss.parameters())

    def test_the_loss_entry_must_be_named(self):
        loss, _ = self.make()
        loss.loss_key = None
        with pytest.raises(ValueError, match="3 loss entries"):
            loss(chunk_segments())


class TestBCLoss:
    def make_actor(self) -> TensorDictModule:
        torch.manual_seed(0)
        net = nn.Sequential(nn.Linear(OBS, H * A), nn.Unflatten(-1, (H, A)))
        return TensorDictModule(net, ["observation"], [CHUNK])

    def test_weights_the_masked_mean_over_each_chunk(self):
        actor = self.make_actor()
        inner = BCLoss(actor, loss_function="l1", reduction="none")
        inner.set_keys(action=CHUNK)
        loss = TARLoss(inner, "tar", params=TARParams(gamma=1.5, w_max=2.0))
        loss.set_keys(event_valid="chunk_valid")
        batch = chunk_segments()
        out = loss(batch)
        with torch.no_grad():
            error = (actor.module(batch["observation"]) - batch[CHUNK]).abs()
        entries = batch["chunk_valid"][..., None].expand_as(error)
        per_step = ((error * entries).sum((-2, -1)) / entries.sum((-2, -1))).tolist()  # real entries only
        valid = batch["collector", "mask"].tolist()
        weights = ref_weights(per_step, valid, gamma=1.5, w_max=2.0)
        assert out["loss_tar"].item() == pytest.approx(ref_segment_loss(per_step, weights, valid), rel=1e-5)

    def test_a_pad_mask_flattens_the_output_and_is_refused(self):
        inner = BCLoss(self.make_actor(), loss_function="l1", reduction="none")
        inner.set_keys(action=CHUNK, pad_mask="chunk_is_pad")
        batch = chunk_segments()
        batch["chunk_is_pad"] = ~batch["chunk_valid"]
        assert inner(batch)["loss_bc"].ndim == 1  # only the real entries, in one flat tensor
        with pytest.raises(ValueError, match="pad_mask"):
            TARLoss(inner, "tar")(batch)
