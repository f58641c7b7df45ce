"""TAR's math is importable with torch alone: ``tar_rl.objectives.tar`` and ``from tar_rl.objectives import
tar_weights`` load no torchrl, tensordict or simulator, and give the hand-computed weights there.

A fresh interpreter blocks those packages (an import of any of them raises ``ImportError``) before it imports
tar_rl, so the check holds whether or not they are installed here.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys

BLOCKED = ("torchrl", "tensordict", "metaworld", "mujoco", "gymnasium", "dm_control")

SCRIPT = """
import importlib.abc
import json
import sys

BLOCKED = {blocked!r}


class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in BLOCKED:
            raise ImportError(f"{{name}} is blocked")
        return None


sys.meta_path.insert(0, Block())

import torch

import tar_rl.objectives.tar as tar
from tar_rl.objectives import tar_weights

losses = torch.tensor([[1.0, 1.0, 1.0, 9.0]], dtype=torch.float64)
valid = torch.ones_like(losses, dtype=torch.bool)
out = {{
    "same": tar_weights is tar.tar_weights,
    "none": tar.tar_weights(losses, valid, gamma=1.0, w_max=float("inf"))[0].tolist(),
    "paper": tar.tar_weights(losses, valid, gamma=1.0, w_max=3.0, cap="paper")[0].tolist(),
    "exact": tar.tar_weights(losses, valid, gamma=1.0, w_max=3.0, cap="exact")[0].tolist(),
    "loaded": sorted(m for m in sys.modules if m.split(".")[0] in BLOCKED),
}}
print(json.dumps(out))
"""

# Losses [1, 1, 1, 9], all four steps valid, gamma 1 (eps 1e-8 changes the weights by ~1e-9 relative here):
#   Eq. 4: mu = 12 / 4 = 3; sigma^2 = (4 + 4 + 4 + 36) / 4 = 12, sigma = 2 sqrt(3).
#   Eq. 5: z = (-2, -2, -2, 6) / (2 sqrt(3)) = (-1/sqrt(3), -1/sqrt(3), -1/sqrt(3), sqrt(3)).
#   Eq. 6: softmax; the last step's probability is r = e^(sqrt(3) + 1/sqrt(3)) = e^(4/sqrt(3)) (about 10.068)
#          times another step's: p = (1, 1, 1, r) / (3 + r).
#   Eq. 7: w = 4 p = (a, a, a, b) with a = 4 / (3 + r) (about 0.3061) and b = 4 r / (3 + r) (about 3.0818).
R = math.exp(4 / math.sqrt(3))
A = 4 / (3 + R)
B = 4 * R / (3 + R)
#   Eq. 8, cap "paper", w_max 3: clip b to 3, then rescale by 4 / (3 a + 3) so the mean is 1:
#          (a, a, a, 3) * 4 / (3 a + 3) (about 0.3125 and 3.0626: after renormalising the last weight is above 3).
PAPER = [A * 4 / (3 * A + 3)] * 3 + [3 * 4 / (3 * A + 3)]
#   cap "exact", w_max 3: the last step sits at 3 and the other three share the remaining mass 4 - 3 equally
#          (their scaled weights c a = 1/3 stay under 3, and c b = b / (3 a) = r / 3 is above 3, so it is capped).
EXACT = [1 / 3, 1 / 3, 1 / 3, 3.0]


def test_tar_math_imports_with_torch_alone_and_gives_the_hand_computed_weights():
    code = SCRIPT.format(blocked=BLOCKED)
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    out = json.loads(done.stdout.strip().splitlines()[-1])
    assert out["loaded"] == []
    assert out["same"]
    for got, want in ((out["none"], [A, A, A, B]), (out["paper"], PAPER), (out["exact"], EXACT)):
        assert len(got) == 4
        for g, w in zip(got, want):
            assert math.isclose(g, w, rel_tol=1e-7), (got, want)  # eps shifts the z-scores by ~1e-9 relative
    assert out["paper"][3] > 3.0  # the paper's cap leaves the top weight above w_max after renormalising
