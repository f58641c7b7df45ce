"""Each weighting owns its parameters: its config group, the run names they give, the default job's numbers.

* ``objective=<name>`` composes the weighting's own settings (generated from ``WEIGHTINGS[name].params``) and
  nothing of another weighting's; a preset (``objective=tar_gentle``) works on the command line too.
* A run's name does not change: every committed run under ``benchmarks/results`` maps to its folder's name, and a
  config saved by an older version (every weighting's parameters listed) migrates to the run it names.
* The default job (``tar-rl train``: TAR at gamma 1, w_max 3, eps 1e-8, the paper cap, the paper's schedule
  fractions) computes Eq. 2 with ``tar_weights`` bit for bit, and agrees with the plain-Python reference.
"""

from __future__ import annotations

import dataclasses
import json

import pytest
import torch
import yaml
from paths import REPO
from recipe_helpers import compose_config
from tar_reference import ref_segment_loss, ref_weights
from tensordict import TensorDict

from tar_rl.cli import main as cli_main
from tar_rl.objectives import WEIGHTINGS, MixSchedule, PerturbedTarget, tar_weights
from tar_rl.policies import DataInfo
from tar_rl.recipes import ConfigError, identity, make_objective, make_policy, run_name, validate
from tar_rl.recipes.config import ObjectiveConfig, objective_config, typed_config
from tar_rl.recipes.rundir import migrate_config

COMMON = {f.name for f in dataclasses.fields(ObjectiveConfig)}


@pytest.mark.parametrize("name", list(WEIGHTINGS))
def test_each_weighting_composes_its_own_parameters_and_no_others(name):
    objective = compose_config(f"objective={name}")["objective"]
    own = {f.name: f.default for f in dataclasses.fields(WEIGHTINGS[name].params)}
    assert set(objective) == COMMON | set(own)
    for key, default in own.items():
        assert objective[key] == (list(default) if isinstance(default, tuple) else default)


def test_focal_shows_focal_settings_and_refuses_tar_ones(capsys):
    assert cli_main(["train", "--cfg", "job", "objective=focal"]) == 0
    shown = yaml.safe_load(capsys.readouterr().out)["objective"]
    assert shown == {
        "name": "focal",
        "start": 0.2,
        "ramp": 0.3,
        "shape": "linear",
        "compile": "auto",
        "signal": "loss",
    } | {
        "focal_beta": 1.0,
        "w_max": 3.0,
    }
    with pytest.raises(SystemExit) as refused:
        cli_main(["train", "--cfg", "job", "objective=focal", "objective.gamma=2"])
    message = str(refused.value.code)
    assert "objective.gamma: objective=focal has no such setting" in message and "objective=tar|" in message


def test_tar_gentle_preset_on_the_command_line(capsys):
    assert cli_main(["train", "--cfg", "job", "objective=tar_gentle"]) == 0
    shown = yaml.safe_load(capsys.readouterr().out)["objective"]
    values = (shown["name"], shown["gamma"], shown["cap"], shown["w_max"], shown["eps"])
    assert values == ("tar", 0.5, "exact", 1.5, 1e-8)


def test_a_config_saved_with_every_weightings_parameters_migrates_to_the_run_it_names():
    config = compose_config("objective=tar", "objective.gamma=2")
    listed = json.loads(json.dumps(config))
    listed["objective"] |= {"focal_beta": 1.0, "dro_bins": 10, "gripper_dims": [-1], "perturb_scale": 0.1}
    with pytest.raises(ConfigError, match="focal_beta"):
        validate(listed)  # the typed config reads this version's format only
    migrated = migrate_config(listed)
    assert migrated == config and migrate_config(migrated) == migrated
    assert run_name(migrated) == run_name(config) and identity(migrated) == {"objective": {"gamma": 2.0}}
    listed["objective"]["focal_beta"] = 2.0  # another weighting's parameter at another value: kept, and refused
    assert migrate_config(listed)["objective"]["focal_beta"] == 2.0
    assert run_name(migrate_config(listed)) != run_name(config)
    with pytest.raises(ConfigError, match="focal_beta"):
        validate(migrate_config(listed))


def test_every_committed_run_keeps_its_name():
    configs = sorted((REPO / "benchmarks" / "results").rglob("config.yaml"))
    assert len(configs) >= 200
    for path in configs:
        config = yaml.safe_load(path.read_text())
        summary = json.loads((path.parent / "summary.json").read_text())
        assert path.parent.name == run_name(config) == summary["run_name"], path


def _batch(generator: torch.Generator) -> TensorDict:
    valid = torch.ones(6, 16, dtype=torch.bool)
    valid[2, 10:] = False  # a segment padded at its episode's end
    valid[4, :] = False  # a segment without a valid step
    return TensorDict(
        {
            "observation": torch.randn(6, 16, 39, generator=generator),
            "task_id": torch.randint(0, 8, (6, 16), generator=generator),
            "action": torch.rand(6, 16, 4, generator=generator) * 2 - 1,
            ("collector", "mask"): valid,
        },
        [6, 16],
    )


def test_the_default_job_computes_eq2_with_tar_defaults_bit_for_bit():
    cfg = typed_config(compose_config())
    assert dataclasses.asdict(cfg.objective) == {
        "name": "tar",
        "start": 0.2,
        "ramp": 0.3,
        "shape": "linear",
        "compile": "auto",
        "signal": "loss",
        "gamma": 1.0,
        "w_max": 3.0,
        "eps": 1e-8,
        "cap": "paper",
    }
    torch.manual_seed(0)
    policy = make_policy(cfg.policy, DataInfo())
    objective = make_objective(cfg.objective, 10, cfg.seed, policy).train()  # 10 steps: start 2, ramp 3
    actor = policy.actor.module
    generator = torch.Generator().manual_seed(1)
    for step in range(6):
        batch = _batch(generator)
        out = objective(batch)
        out["loss_tar"].backward()
        with torch.no_grad():  # the head's per-step MSE, by hand from its network
            predicted = actor(batch["observation"], batch["task_id"])
            losses = (predicted - batch["action"]).square().mean(-1)
        valid = batch["collector", "mask"]
        mix = MixSchedule(start=2, ramp=3)(torch.tensor(step))
        weights = tar_weights(losses, valid, gamma=1.0, w_max=3.0, eps=1e-8, cap="paper", mix=mix)
        per_step = torch.where(valid, weights * losses, torch.zeros(()))
        n_valid = valid.sum(-1)
        expected = (per_step.sum(-1) / n_valid.clamp_min(1)).sum() / (n_valid > 0).sum()
        assert torch.equal(out["loss_tar"].detach(), expected), step
        reference_weights = ref_weights(losses.tolist(), valid.tolist(), mix=min(max((step - 2) / 3, 0.0), 1.0))
        reference = ref_segment_loss(losses.tolist(), reference_weights, valid.tolist())
        assert out["loss_tar"].item() == pytest.approx(reference, rel=1e-5)


@pytest.mark.parametrize("name", list(WEIGHTINGS))
def test_the_job_wraps_a_perturbation_controls_head_loss_and_no_other(name):
    policy = make_policy(typed_config(compose_config()).policy, DataInfo())
    objective = make_objective(objective_config(name)(name=name), 10, 3, policy)
    which = WEIGHTINGS[name].perturb
    if which is None:
        assert objective.inner is policy.loss
        return
    assert isinstance(objective.inner, PerturbedTarget) and objective.inner.inner is policy.loss
    assert objective.inner.which == which and objective.inner.params == objective.params
    assert torch.equal(objective.inner.generator.get_state(), torch.Generator().manual_seed(3).get_state())


def test_the_ranking_signal_and_time_sampling_at_their_defaults_name_the_same_runs():
    for default, explicit in (
        ((), ("objective.signal=loss",)),
        (("policy=flow",), ("policy=flow", "objective.signal=loss", "policy.time_sampling=step")),
        (("policy=flow", "objective=uniform"), ("policy=flow", "objective=uniform", "objective.signal=loss")),
    ):
        assert run_name(compose_config(*explicit)) == run_name(compose_config(*default))
    saved_before = compose_config("policy=flow")  # a config saved before the settings existed
    del saved_before["objective"]["signal"], saved_before["policy"]["time_sampling"]
    assert run_name(saved_before) == run_name(compose_config("policy=flow")) and identity(saved_before) == {}
    chosen = compose_config("policy=flow", "objective.signal=action_error", "policy.time_sampling=segment")
    assert identity(chosen) == {"objective": {"signal": "action_error"}, "policy": {"time_sampling": "segment"}}
    validate(chosen)


def test_a_signal_the_head_does_not_offer_is_refused_naming_the_head_and_its_signals():
    with pytest.raises(ConfigError) as refused:
        validate(compose_config("objective.signal=action_error"))
    assert str(refused.value) == (
        "objective.signal='action_error' is not a ranking signal of the mlp head, which offers ['loss']; use loss, "
        "or with policy=flow action_error or time_normalized"
    )
    with pytest.raises(ConfigError, match=r"the flow head, which offers \['loss', 'action_error', 'time_normalized'\]"):
        validate(compose_config("policy=flow", "objective.signal=action_errors"))
    with pytest.raises(ConfigError, match=r"objective=tar_arm scores per-element losses; use objective.signal=loss"):
        validate(compose_config("policy=flow", "objective=tar_arm", "objective.signal=time_normalized"))
    with pytest.raises(ConfigError, match=r"policy.time_sampling must be one of \['step', 'segment'\], got 'batch'"):
        validate(compose_config("policy=flow", "policy.time_sampling=batch"))


def test_the_help_shows_the_signal_and_the_time_sampling(capsys):
    for args, line in (
        (["train", "--help"], "  signal: loss"),
        (["train", "policy=flow", "--help"], "  time_sampling: step"),
    ):
        with pytest.raises(SystemExit) as done:
            cli_main(args)
        assert not done.value.code
        assert line in capsys.readouterr().out.splitlines()
