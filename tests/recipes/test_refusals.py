"""Settings refused before any work, and how `tar-rl train` names a bad command line: one line, with a suggestion.

The limits are the documented ones (``tar_rl.recipes.validate``: at most 1e9 steps, a peak learning rate in
(0, 1]; the paper cap's floor is the smallest normal float32, 2**-126; MetaWorld's actions have 4 dims).
"""

from __future__ import annotations

import pytest
from recipe_helpers import compose_config

from tar_rl.cli import main as cli_main
from tar_rl.recipes import ConfigError, validate


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (
            ["optim.steps=100000000000000000000"],
            "optim.steps must be an integer between 1 and 1000000000, got 100000000000000000000",
        ),
        (["optim.lr=1e300"], "optim.lr must be a number in (0, 1], got 1e+300"),
        (
            ["objective=tar_arm", "objective.gripper_dims=[4]"],
            "objective.gripper_dims [4] name dims outside the loss's 4 action dims: [4] (valid: -4 .. 3).",
        ),
        (
            ["objective=tar_arm", "objective.gripper_dims=[-5,-1]"],
            "objective.gripper_dims [-5, -1] name dims outside the loss's 4 action dims: [-5] (valid: -4 .. 3).",
        ),
        (
            ["objective.w_max=0.5"],  # the paper cap's too: unit-mean weights renormalise above any cap under 1
            "objective.w_max >= 1 is needed (weights of mean 1 cannot all lie below a smaller cap: cap='paper' "
            "renormalises them above it, cap='exact' cannot reach it), got 0.5; use a number >= 1 (math.inf for no "
            "cap)",
        ),
        (
            ["objective.start=0.8", "objective.ramp=0.3"],
            "objective.start + objective.ramp must be <= 1 (the ramp ends by the last step), got 0.8 + 0.3 = 1.1: "
            "TAR would never reach full strength; lower one of them",
        ),
        (
            ["objective.start=1.0", "objective.ramp=0"],
            "objective.start is a fraction of optim.steps and must lie in [0, 1), got 1.0 (the weighting would start "
            "after the last step: TAR would never reach full strength)",
        ),
    ],
)
def test_values_that_would_fail_after_work_starts_are_refused_first(overrides, message):
    with pytest.raises(ConfigError) as info:
        validate(compose_config(*overrides))
    assert str(info.value) == message


def test_the_limits_themselves_are_accepted():
    validate(compose_config("optim.steps=1000000000", "optim.lr=1.0", "objective.start=0.7", "objective.ramp=0.3"))
    validate(compose_config("objective=tar_arm", "objective.gripper_dims=[-4,2]", "objective.w_max=1.0"))


@pytest.mark.parametrize(
    ("argument", "line"),
    [
        ("optim.lrr=1", "tar-rl train: optim.lrr: no such setting (did you mean 'optim.lr'?)"),
        ("lr=0.1", "tar-rl train: lr: no such setting (did you mean 'optim.lr'?)"),
        ("seed=abc", "tar-rl train: seed: 'abc' is not an integer; seed must be an integer >= 0"),
        (
            "optim.steps=1e20",
            "tar-rl train: optim.steps: '1e+20' is not an integer; optim.steps must be an integer between 1 and "
            "1000000000",
        ),
        ("optim.amp=maybe", "tar-rl train: optim.amp: 'maybe' is not a boolean (true or false)"),
        (
            "objective=tarr",
            "tar-rl train: objective: no option 'tarr' (did you mean 'tar'?); options: uniform, tar, shuffle, random, "
            "invert, perturb_high, perturb_low, tilted, truncate, keyframe, focal, dro_time, tar_arm, tar_dimnorm, "
            "tar_gentle",
        ),
        (
            "policy=mpl",
            "tar-rl train: policy: no option 'mpl' (did you mean 'mlp'?); options: mlp, act, octo_linear, "
            "octo_diffusion, flow",
        ),
    ],
)
def test_a_bad_command_line_is_one_line_with_a_suggestion(tmp_path, monkeypatch, capsys, argument, line):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as info:
        cli_main(["train", argument, f"runs_root={tmp_path / 'runs'}", f"data.root={tmp_path / 'data'}"])
    assert info.value.code == line
    assert list(tmp_path.iterdir()) == []


def test_a_mistyped_task_is_named_with_the_closest_one(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as info:
        cli_main(["train", "data.tasks=[reech]", f"runs_root={tmp_path / 'runs'}", f"data.root={tmp_path / 'data'}"])
    assert str(info.value.code).startswith(
        "tar-rl train: data.tasks: unknown MetaWorld task or group ['reech'] (did you mean 'reach'?). Groups: "
    )
    assert list(tmp_path.iterdir()) == []
