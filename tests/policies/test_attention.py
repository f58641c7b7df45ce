"""The transformer heads' attention path (``tar_rl.policies.attention``) and their unchanged losses.

References: the attention formula in float64 written here; PyTorch's own ``nn.MultiheadAttention``,
``nn.TransformerEncoder`` and ``nn.TransformerDecoder`` forwards for ACT's stacks; and, for every
chunked head, the loss and gradient norm on a fixed batch computed by the code before the speed-up
(commit f402262, by :func:`loss_and_grad_norm` below run against that checkout).
"""

from __future__ import annotations

import dataclasses

import pytest
import torch
from tensordict import TensorDict
from torch import nn

from tar_rl import TARLoss
from tar_rl.policies import POLICIES, DataInfo, build_policy
from tar_rl.policies.act import ACTConfig, ACTModel
from tar_rl.policies.attention import attend, broadcast_attention, key_padding_bias, multihead
from tar_rl.policies.octo import TransformerBlock

H, K, A, D = 8, 2, 4, 39


def reference_attention(q, k, v, bias=None):
    """softmax(q k^T / sqrt(d) + bias) v in float64, written out."""
    q, k, v = q.double(), k.double(), v.double()
    scores = torch.einsum("nhid,nhjd->nhij", q, k) / q.shape[-1] ** 0.5
    if bias is not None:
        scores = scores + bias.double()
    weights = torch.exp(scores - scores.amax(-1, keepdim=True))
    weights = weights / weights.sum(-1, keepdim=True)
    return torch.einsum("nhij,nhjd->nhid", weights, v)


def qkv(n=5, h=2, sq=4, sk=6, d=8, seed=0):
    g = torch.Generator().manual_seed(seed)
    return [torch.randn(n, h, s, d, generator=g) for s in (sq, sk, sk)]


def padding_bias(n=5, sk=6, seed=1):
    g = torch.Generator().manual_seed(seed)
    ignore = torch.rand(n, sk, generator=g) < 0.4
    ignore[:, 0] = False  # every query keeps a key
    return ignore, key_padding_bias(ignore, torch.float32)


def test_key_padding_bias_is_zero_or_minus_infinity_per_key():
    ignore = torch.tensor([[False, True, False]])
    bias = key_padding_bias(ignore, torch.float32)
    assert bias.shape == (1, 1, 1, 3)
    assert bias[0, 0, 0].tolist() == [0.0, float("-inf"), 0.0]


@pytest.mark.parametrize("masked", [False, True])
def test_both_attention_forms_equal_the_formula(masked):
    q, k, v = qkv()
    bias = padding_bias()[1] if masked else None
    expected = reference_attention(q, k, v, bias)
    torch.testing.assert_close(attend(q, k, v, bias).double(), expected, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(broadcast_attention(q, k, v, bias).double(), expected, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("cross", [False, True])
def test_multihead_equals_the_modules_own_forward(cross):
    torch.manual_seed(0)
    mha = nn.MultiheadAttention(16, 4, batch_first=True)
    x, memory = torch.randn(5, 3, 16), torch.randn(5, 6, 16)
    ignore, bias = padding_bias(sk=6 if cross else 3)
    kv = memory if cross else x
    expected = mha(x, kv, kv, key_padding_mask=ignore, need_weights=False)[0]
    got = multihead(mha, x, memory if cross else None, bias=bias)
    torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-6)


def test_a_blocks_last_tokens_equal_the_full_blocks_last_rows():
    torch.manual_seed(0)
    block = TransformerBlock(16, 4)
    x = torch.randn(5, 6, 16)
    bias = torch.zeros(6, 6).masked_fill_(torch.rand(6, 6) < 0.3, float("-inf")).fill_diagonal_(0.0)
    torch.testing.assert_close(block(x, bias, last=2), block(x, bias)[:, -2:], rtol=1e-5, atol=1e-6)


def test_act_stacks_equal_pytorchs_transformer_modules():
    torch.manual_seed(0)
    model = ACTModel(ACTConfig(dim=16, heads=2, enc_layers=2, dec_layers=2), DataInfo(chunk_horizon=H)).train()
    tokens, memory = torch.randn(5, 6, 16), torch.randn(5, 3, 16)
    ignore, bias = padding_bias(sk=6)
    expected = model.cvae_encoder(tokens, src_key_padding_mask=ignore)
    torch.testing.assert_close(model._encode(model.cvae_encoder, tokens, bias), expected, rtol=1e-5, atol=1e-5)
    expected = model.decoder(model.queries.expand(5, -1, -1), memory)
    torch.testing.assert_close(model._decode(memory), expected, rtol=1e-5, atol=1e-5)


# -- every chunked head's loss, before and after the speed-up --------------------------------------


def fixed_batch(b: int = 6, length: int = 8, seed: int = 3) -> TensorDict:
    """A ``[b, length]`` segment batch with every entry the chunked heads read; some chunks and segments padded."""
    g = torch.Generator().manual_seed(seed)
    obs = torch.randn(b, length, D, generator=g)
    chunk_valid = torch.ones(b, length, H, dtype=torch.bool)
    chunk_valid[0, -3:, 2:] = False
    history_valid = torch.ones(b, length, K, dtype=torch.bool)
    history_valid[1, 0, 0] = False
    mask = torch.ones(b, length, dtype=torch.bool)
    mask[2, -2:] = False
    return TensorDict(
        {
            "observation": obs,
            "task_id": torch.randint(50, (b, 1), generator=g).expand(b, length).clone(),
            "action": torch.rand(b, length, A, generator=g) * 2 - 1,
            "action_chunk": torch.rand(b, length, H, A, generator=g) * 2 - 1,
            "action_chunk_valid": chunk_valid,
            "observation_history": torch.randn(b, length, K, D, generator=g),
            "observation_history_valid": history_valid,
            ("collector", "mask"): mask,
        },
        [b, length],
    )


def loss_and_grad_norm(head: str, compiled: bool = False) -> tuple[float, float]:
    """TAR's loss of ``head`` (config defaults, seed 0) on :func:`fixed_batch` and its gradient's norm."""
    torch.manual_seed(0)
    cfg = POLICIES[head].config()
    if compiled:
        cfg = dataclasses.replace(cfg, compile=True)
    policy = build_policy(cfg, DataInfo(chunk_horizon=H, history=K))
    loss = TARLoss(policy.loss, "tar", loss_key=policy.loss_key)
    loss.set_keys(event_valid=policy.event_valid)
    torch.manual_seed(1)
    out = loss(fixed_batch())
    out["loss_tar"].backward()
    norm = torch.sqrt(sum((p.grad.double() ** 2).sum() for p in loss.parameters() if p.grad is not None))
    return float(out["loss_tar"].detach()), float(norm)


# computed by loss_and_grad_norm at commit f402262, before the attention path existed
BEFORE = {
    "act": (52.59882354736328, 494.5594151778856),
    "flow": (1.9797968864440918, 3.300111413312288),
    "octo_linear": (0.7156615853309631, 3.181233329687594),
    "octo_diffusion": (1.53385591506958, 2.95563222629495),
}


@pytest.mark.parametrize("head", sorted(BEFORE))
def test_each_heads_loss_and_gradient_equal_the_values_before_the_speed_up(head):
    loss, norm = loss_and_grad_norm(head)
    assert loss == pytest.approx(BEFORE[head][0], rel=1e-5)
    assert norm == pytest.approx(BEFORE[head][1], rel=1e-4)


# torch.compile's tracer reads .grad of non-leaf tensors while it builds the graph, which warns
COMPILE_WARNING = "ignore:The .grad attribute of a Tensor that is not a leaf:UserWarning"


@pytest.mark.slow  # compiles one kernel (~10 s on a 2-core machine with an empty compile cache)
@pytest.mark.filterwarnings(COMPILE_WARNING)
def test_the_compiled_attention_equals_the_formula_with_gradients():
    q, k, v = (t.requires_grad_() for t in qkv())
    bias = padding_bias()[1]
    got = attend(q, k, v, bias, compiled=True)
    torch.testing.assert_close(got.double(), reference_attention(q, k, v, bias), rtol=1e-5, atol=1e-6)
    grads = torch.autograd.grad(got.square().sum(), (q, k, v))
    expected = torch.autograd.grad(reference_attention(q, k, v, bias).square().sum(), (q, k, v))
    for g, e in zip(grads, expected):
        torch.testing.assert_close(g.double(), e.double(), rtol=1e-4, atol=1e-5)


# octo_diffusion runs both compiled functions of the heads besides the attention kernel: the whole transformer
# block (full and last-tokens forms) and the denoiser; compiling every head would cost minutes of CI.
@pytest.mark.slow  # compiles three kernels (~40 s with an empty compile cache)
@pytest.mark.filterwarnings(COMPILE_WARNING)
def test_a_compiled_heads_loss_and_gradient_equal_the_values_before_the_speed_up():
    loss, norm = loss_and_grad_norm("octo_diffusion", compiled=True)
    assert loss == pytest.approx(BEFORE["octo_diffusion"][0], rel=1e-5)
    assert norm == pytest.approx(BEFORE["octo_diffusion"][1], rel=1e-4)
