"""Multi-head attention over the transformer heads' short token sequences, with a compiled CPU path.

Every transformer head runs its attention over many short sequences: a ``[64, 16]`` training batch
folds into ``N = 1024`` sequences of 3 to 10 tokens (the Octo-style backbone's task, observation,
image and readout tokens; ACT's CVAE, encoder and decoder tokens; the flow expert's chunk tokens).
For such shapes PyTorch's CPU kernels spend most of their time on overhead: the flash-attention
kernel of ``scaled_dot_product_attention`` and the batched matrix products of the plain formula
each do a few hundred multiply-adds per ``[S, S]`` block.

:func:`attend` computes ``softmax(q k^T / sqrt(d) + bias) v``. By default (and always without
gradients, on CUDA, and with attention dropout) it calls ``scaled_dot_product_attention``. With
``compiled=True``, a training step on the CPU runs the same formula written as broadcast products
over the short axes, compiled once per shape by ``torch.compile`` (inductor's C++ backend fuses it
into loops over ``N``): the result equals the eager one up to float rounding. The first call of
each shape compiles (seconds; a C++ compiler must be installed), the later ones reuse the kernel.
Training batches keep one shape, so a run compiles each attention once.

:func:`multihead` runs an ``nn.MultiheadAttention`` (``batch_first``) through :func:`attend` with
the module's own parameters, without the module's sequence-first transposes and packed-projection
copies: the same parameters, initialisation and state-dict names, less work per call.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["attend", "broadcast_attention", "compile_once", "key_padding_bias", "multihead", "use_compiled"]


def broadcast_attention(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, bias: torch.Tensor | None) -> torch.Tensor:
    """``softmax(q k^T / sqrt(d) + bias) v`` as broadcast products: the form that compiles into fused loops."""
    scores = (q[..., :, None, :] * k[..., None, :, :]).sum(-1) * (q.shape[-1] ** -0.5)
    if bias is not None:
        scores = scores + bias
    return (scores.softmax(-1)[..., None] * v[..., None, :, :]).sum(-2)


_COMPILED: dict = {}


def compile_once(fn):
    """``torch.compile(fn, dynamic=False)``, made once per function on first use (nothing compiles until called)."""
    if fn not in _COMPILED:
        _COMPILED[fn] = torch.compile(fn, dynamic=False)
    return _COMPILED[fn]


def use_compiled(enabled: bool, x: torch.Tensor, dropout: float) -> bool:
    """Whether a computation on ``x`` takes the compiled CPU path: ``enabled``, a training step (gradients on)
    on the CPU, and no dropout (``dropout``: the probability in effect, 0 outside training)."""
    return enabled and dropout == 0.0 and x.device.type == "cpu" and torch.is_grad_enabled()


def attend(
    q: torch.Tensor,
    k: torch.Tensor,
    v: torch.Tensor,
    bias: torch.Tensor | None = None,
    dropout: float = 0.0,
    compiled: bool = False,
) -> torch.Tensor:
    """``softmax(q k^T / sqrt(d) + bias) v`` with dropout ``dropout`` on the attention weights.

    Args:
        q: ``[N, h, Sq, d]`` queries.
        k, v: ``[N, h, Sk, d]`` keys and values.
        bias: additive float bias broadcastable to ``[N, h, Sq, Sk]`` (``-inf``: not attended to), or ``None``.
        dropout: attention dropout probability (pass 0 outside training).
        compiled: run the compiled CPU kernel where it applies (module docstring).

    Returns:
        ``[N, h, Sq, d]``.
    """
    if use_compiled(compiled, q, dropout):
        return compile_once(broadcast_attention)(q, k, v, bias)
    return F.scaled_dot_product_attention(q, k, v, attn_mask=bias, dropout_p=dropout)


def key_padding_bias(ignore: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """``[N, S]`` bool (True: a key not attended to) -> the additive bias ``[N, 1, 1, S]`` (0 or ``-inf``)."""
    bias = torch.zeros(ignore.shape, dtype=dtype, device=ignore.device).masked_fill_(ignore, float("-inf"))
    return bias[:, None, None, :]


def multihead(
    mha: nn.MultiheadAttention,
    x: torch.Tensor,
    memory: torch.Tensor | None = None,
    bias: torch.Tensor | None = None,
    compiled: bool = False,
) -> torch.Tensor:
    """``mha(x, kv, kv)[0]`` with ``kv = memory`` (cross-attention) or ``x`` (self-attention), through :func:`attend`.

    Args:
        mha: a ``batch_first`` ``nn.MultiheadAttention`` with packed input projections (query, key and value of
            one width).
        x: ``[N, Sq, E]`` queries.
        memory: ``[N, Sk, E]`` keys and values, or ``None`` for self-attention.
        bias: as in :func:`attend`.
        compiled: as in :func:`attend`.

    Returns:
        ``[N, Sq, E]``.
    """
    n, s, e = x.shape
    h = mha.num_heads
    w, b = mha.in_proj_weight, mha.in_proj_bias
    if memory is None:
        q, k, v = F.linear(x, w, b).view(n, s, 3, h, e // h).permute(2, 0, 3, 1, 4)
    else:
        q = F.linear(x, w[:e], None if b is None else b[:e]).view(n, s, h, e // h).transpose(1, 2)
        m = memory.shape[1]
        kv = F.linear(memory, w[e:], None if b is None else b[e:]).view(memory.shape[0], m, 2, h, e // h)
        k, v = kv.permute(2, 0, 3, 1, 4)
    out = attend(q, k, v, bias, dropout=mha.dropout if mha.training else 0.0, compiled=compiled)
    return mha.out_proj(out.transpose(1, 2).reshape(n, s, e))
