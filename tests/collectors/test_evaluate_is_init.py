"""The evaluator tells stateful policies where rollouts start: ``is_init`` (TorchRL's InitTracker)."""

from __future__ import annotations

import torch
from tensordict.nn import TensorDictModuleBase

from tar_rl.collectors.metaworld.evaluate import evaluate


class _Probe(TensorDictModuleBase):
    """Records ``is_init`` at every call and outputs zero actions (reach never succeeds with them)."""

    in_keys = ["observation", "is_init"]
    out_keys = ["action"]

    def __init__(self):
        super().__init__()
        self.seen: list[list[bool]] = []

    def forward(self, td):
        assert td["is_init"].dtype == torch.bool and td["is_init"].shape == (td.batch_size[0], 1)
        self.seen.append(td["is_init"].reshape(-1).tolist())
        td.set("action", torch.zeros(td.batch_size[0], 4))
        return td


def test_is_init_marks_the_first_step_of_every_rollout_including_refilled_slots():
    probe = _Probe()
    # 3 rollouts of 4 steps on 2 slots: slot 0 runs rollouts 0 then 2, slot 1 runs rollout 1 then idles.
    evaluate(probe, ["reach"], rollouts_per_task=3, horizon=4, workers=1, envs_per_worker=2, progress=False)
    expected = [[True, True]] + [[False, False]] * 3 + [[True, False]] + [[False, False]] * 3
    assert probe.seen == expected
