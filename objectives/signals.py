"""The state of a ranking signal (what ``TARLoss`` may rank steps by instead of their loss): torch only, so that
LeRobot's plugin (``lerobot_policy_tar``) imports it without torchrl.

:class:`TimeNormalizer` keeps a running mean of a sampled per-step loss at each drawn time, for the
``time_normalized`` signal of a head whose loss is one draw of a time and a noise (``tar_rl.policies.flow``; the
plugin's diffusion and flow-matching policies): a step's loss over that mean ranks it against the loss expected at
its draw.
"""

from __future__ import annotations

import torch
import torch.distributed as torch_dist
from torch import nn

__all__ = ["TIME_BINS", "TIME_DECAY", "TimeNormalizer"]

#: :class:`TimeNormalizer`'s bins of equal probability under the time distribution (the first, under Beta(1.5, 1),
#: holds ``tau`` up to about 0.1), and the decay of its running means (a window of about 100 training steps).
TIME_BINS = 32
TIME_DECAY = 0.99


class TimeNormalizer(nn.Module):
    """A running estimate of the mean per-step loss at each training time, for the ``time_normalized`` signal.

    The times are binned into ``bins`` bins of equal probability under the time distribution (a step's bin:
    ``floor(bins * F(tau))``, ``F`` the CDF). Each bin's estimate is an exponential moving average, bias-corrected
    as in Adam: on every training step with valid steps in the bin, ``total <- decay * total + (1 - decay) * m`` and
    ``weight <- decay * weight + (1 - decay)``, ``m`` the mean of the finite losses of the batch's valid steps in
    the bin (summed over the ranks of a distributed job first); the estimate is ``total / weight``. A call computes
    that update and divides by it, so a step's estimate always holds its own batch (every bin it meets is seen);
    only a training step keeps it. Non-finite losses never enter it.

    Buffers ``total`` and ``weight`` (``[bins]``, float64) are in ``state_dict()``: a resumed run continues them
    exactly.
    """

    def __init__(self, bins: int = TIME_BINS, decay: float = TIME_DECAY):
        super().__init__()
        self.bins, self.decay = int(bins), float(decay)
        self.register_buffer("total", torch.zeros(self.bins, dtype=torch.float64))
        self.register_buffer("weight", torch.zeros(self.bins, dtype=torch.float64))

    def forward(self, losses: torch.Tensor, position: torch.Tensor, valid: torch.Tensor, update: bool) -> torch.Tensor:
        """``losses`` divided by the estimate of their bins: ``position`` is each step's ``F(tau)`` in ``[0, 1]``,
        ``valid`` ``True`` on real steps, all ``[*B]``; ``update``: keep the update (a training step)."""
        index = (position.double() * self.bins).floor().long().clamp(0, self.bins - 1).reshape(-1)
        counted = (valid & torch.isfinite(losses)).reshape(-1)
        x = torch.where(
            counted, losses.reshape(-1).double(), torch.zeros((), dtype=torch.float64, device=losses.device)
        )
        stats = torch.zeros(2, self.bins, dtype=torch.float64, device=losses.device)
        stats[0].index_add_(0, index, x)
        stats[1].index_add_(0, index, counted.double())
        if update and torch_dist.is_available() and torch_dist.is_initialized():
            torch_dist.all_reduce(stats)
        seen = stats[1] > 0
        mean = stats[0] / stats[1].clamp_min(1)
        total = torch.where(seen, self.decay * self.total + (1 - self.decay) * mean, self.total)
        weight = torch.where(seen, self.decay * self.weight + (1 - self.decay), self.weight)
        if update:
            self.total.copy_(total)
            self.weight.copy_(weight)
        estimate = (total / weight).clamp_min(torch.finfo(torch.float64).tiny)  # a bin of zero losses: 0 / tiny
        return (losses.double() / estimate[index].reshape(losses.shape)).to(losses.dtype)
