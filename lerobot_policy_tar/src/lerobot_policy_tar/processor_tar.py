"""The processors: each TAR policy uses its base policy's pre- and post-processors unchanged (LeRobot looks up
``make_<type>_pre_post_processors`` here by the policy's type)."""

from __future__ import annotations

from lerobot.policies.act.processor_act import make_act_pre_post_processors
from lerobot.policies.diffusion.processor_diffusion import make_diffusion_pre_post_processors
from lerobot.policies.pi0.processor_pi0 import make_pi0_pre_post_processors
from lerobot.policies.pi05.processor_pi05 import make_pi05_pre_post_processors
from lerobot.policies.smolvla.processor_smolvla import make_smolvla_pre_post_processors

make_act_tar_pre_post_processors = make_act_pre_post_processors
make_diffusion_tar_pre_post_processors = make_diffusion_pre_post_processors
make_smolvla_tar_pre_post_processors = make_smolvla_pre_post_processors
make_pi0_tar_pre_post_processors = make_pi0_pre_post_processors
make_pi05_tar_pre_post_processors = make_pi05_pre_post_processors
