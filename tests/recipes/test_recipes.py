"""The offline BC recipe: config, builders, the training job, checkpoints and resume, `tar-rl eval`.

Real MetaWorld, tiny: one module-scoped dataset (reach, 2 demos) shared by every run; training
runs of 30 steps and evaluations of one short rollout. Expected values are computed by hand or
with the plain-Python reference of Eqs. 3-8 (``tests/tar_reference.py``).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from hydra import compose, initialize
from hydra.errors import ConfigCompositionException
from objective_helpers import tar_loss
from omegaconf.errors import ConfigAttributeError, ValidationError
from paths import REPO
from recipe_helpers import TASK, compose_config, tiny
from tar_reference import ref_tar_segment
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torchrl.objectives import BCLoss

from tar_rl import TARLoss, tar_weights
from tar_rl.cli import main as cli_main
from tar_rl.data import SegmentSampler
from tar_rl.objectives import WEIGHTINGS
from tar_rl.policies import POLICIES, DataInfo
from tar_rl.recipes import (
    ConfigError,
    TrainingError,
    evaluate_checkpoint,
    make_objective,
    make_optimizer,
    make_policy,
    record_weights,
    train,
    validate,
)
from tar_rl.recipes.config import PRESETS, ObjectiveConfig, register_configs, typed_config
from tar_rl.runs import CHECKPOINT, WEIGHTS_COLUMNS, RunLogs, load_checkpoint, weights_columns

# -- Config -------------------------------------------------------------------------------------


@pytest.mark.parametrize("policy", sorted(POLICIES))
@pytest.mark.parametrize("objective", sorted(WEIGHTINGS))
def test_every_registered_objective_and_policy_builds_from_defaults(objective, policy):
    config = compose_config(f"objective={objective}", f"policy={policy}")
    assert config["objective"]["name"] == objective and config["policy"]["name"] == policy
    cfg = typed_config(config)
    torch.manual_seed(0)
    built = make_policy(cfg.policy, DataInfo(chunk_horizon=8, history=2))
    loss = make_objective(cfg.objective, cfg.optim.steps, cfg.seed, built)
    chunk_valid = torch.ones(3, 5, 8, dtype=torch.bool)
    chunk_valid[:, -1, 3:] = False  # chunks running past the end of their episode
    history_valid = torch.ones(3, 5, 2, dtype=torch.bool)
    history_valid[:, 0, 0] = False  # the first step of an episode has no past observation
    batch = TensorDict(
        {
            "observation": torch.randn(3, 5, 39),
            "task_id": torch.randint(0, 50, (3, 5)),
            "action": torch.rand(3, 5, 4) * 2 - 1,
            "action_chunk": torch.rand(3, 5, 8, 4) * 2 - 1,
            "action_chunk_valid": chunk_valid,
            "observation_history": torch.randn(3, 5, 2, 39),
            "observation_history_valid": history_valid,
            "episode": torch.arange(3)[:, None].expand(3, 5).clone(),
            "step": torch.arange(5).expand(3, 5).clone(),
            "episode_length": torch.full((3, 5), 5),
            ("collector", "mask"): torch.tensor([[True] * 5, [True] * 5, [True] * 3 + [False] * 2]),
        },
        [3, 5],
    )
    out = loss(batch)
    assert out["loss_tar"].shape == () and torch.isfinite(out["loss_tar"])
    with torch.no_grad():
        steps, dims = loss.step_and_dim_losses(batch)  # every head: a loss per action dim (weights.csv's loss_dim*)
    assert dims.shape == (3, 5, 4)
    torch.testing.assert_close(dims.mean(-1), steps)  # from the same pass: a step's loss is its dims' mean
    out["loss_tar"].backward()
    assert all(p.grad is not None for p in built.actor.parameters())
    inference = batch[:, 0].select("observation", "task_id").set("is_init", torch.ones(3, 1, dtype=torch.bool))
    action = built.actor.eval()(inference)["action"]
    assert action.shape == (3, 4) and torch.isfinite(action).all()


@pytest.mark.parametrize(("group", "option"), [(g, o) for g, options in PRESETS.items() for o in options])
def test_every_preset_composes_and_validates(group, option):
    config = compose_config(f"{group}={option}")
    assert config[group] == dataclasses.asdict(PRESETS[group][option])
    validate(config)  # raises ConfigError on a bad preset


def test_paper_presets_follow_the_paper():
    config = compose_config("eval=paper", "optim=paper")
    assert (config["eval"]["rollouts"], config["eval"]["seed"], config["eval"]["horizon"]) == (50, 1000, 500)
    cfg = typed_config(config)
    loss = make_objective(cfg.objective, cfg.optim.steps, cfg.seed, make_policy(cfg.policy, DataInfo()))
    assert (config["optim"]["steps"], loss.schedule.start, loss.schedule.ramp) == (100_000, 20_000, 30_000)


def test_objective_override_sets_the_weighting_and_its_parameters():
    config = compose_config("objective=uniform")
    assert config["objective"]["name"] == "uniform"
    config = compose_config("objective=tar", "objective.gamma=2", "objective.cap=exact")
    assert (config["objective"]["gamma"], config["objective"]["cap"]) == (2.0, "exact")


def test_tar_gentle_preset_resolves_to_its_values_and_weights():
    config = compose_config("objective=tar_gentle")
    default = compose_config("objective=tar")["objective"]
    expected = {**default, "gamma": 0.5, "cap": "exact", "w_max": 1.5}  # R3's tuned setting, the rest tar's
    assert config["objective"] == expected
    validate(config)
    cfg = typed_config(config)
    params = make_objective(cfg.objective, cfg.optim.steps, cfg.seed, make_policy(cfg.policy, DataInfo())).params
    assert (params.gamma, params.cap, params.w_max) == (0.5, "exact", 1.5)
    # One step at 9 among three at 1: at gamma 0.5 its uncapped weight is ~1.9-2.1 (z-score 1.5-1.7), above 1.5;
    # the exact cap holds it at 1.5 and the three others share the rest of the unit mean, (4 - 1.5) / 3 each.
    losses, valid = torch.tensor([[1.0, 1.0, 1.0, 9.0]]), torch.ones(1, 4, dtype=torch.bool)
    weights = tar_weights(losses, valid, gamma=params.gamma, w_max=params.w_max, cap=params.cap)
    torch.testing.assert_close(weights[0], torch.tensor([2.5 / 3, 2.5 / 3, 2.5 / 3, 1.5]))


def test_schedule_fractions_become_steps():
    cfg = typed_config(compose_config("optim.steps=1000", "objective.start=0.2", "objective.ramp=0.3"))
    loss = make_objective(cfg.objective, cfg.optim.steps, cfg.seed, make_policy(cfg.policy, DataInfo()))
    assert (loss.schedule.start, loss.schedule.ramp) == (200, 300)


@pytest.mark.parametrize(
    ("override", "error", "named"),
    [
        ("optim.lrr=1", ConfigCompositionException, "lrr"),
        ("seed=abc", ConfigCompositionException, "seed"),
        ("objective=nope", ConfigCompositionException, "shuffle"),  # the valid options are listed
        ("policy=nope", ConfigCompositionException, "mlp"),
        ("objective.temperature=2", ConfigCompositionException, "temperature"),
    ],
)
def test_unknown_keys_and_options_are_refused_at_composition(override, error, named):
    with pytest.raises(error) as info:
        compose_config(override)
    text = str(info.value) + str(info.value.__cause__ or "")
    assert named in text


@pytest.mark.parametrize(
    ("overrides", "named"),
    [
        (["data.tasks=[reach,not-a-task]"], "not-a-task"),
        (["eval.tasks=[nope]"], "eval.tasks"),
        (["data.tasks=[]"], "data.tasks is empty"),
        (["eval.horizon=501"], "eval.horizon"),
        (["objective.cap=loose"], "objective.cap"),
        (["objective.compile=sometimes"], "objective.compile"),
        (["objective.start=1.5"], "objective.start"),
        (["objective.w_max=0.5", "objective.cap=exact"], "objective.w_max >= 1"),
        (["objective.gamma=0"], "objective.gamma"),
        (["objective.w_max=-1"], "objective.w_max"),
        (["objective.eps=0"], "objective.eps"),
        (["objective=tilted", "objective.tilt=0"], "objective.tilt"),
        (["objective=truncate", "objective.truncate_fraction=1.0"], "objective.truncate_fraction"),
        (["objective=keyframe", "objective.keyframe_fraction=0"], "objective.keyframe_fraction"),
        (["objective=keyframe", "objective.keyframe_factor=0.5"], "objective.keyframe_factor"),
        (["objective=focal", "objective.focal_beta=-1"], "objective.focal_beta"),
        (["objective=tar_arm", "objective.gripper_dims=[3,3]"], "objective.gripper_dims"),
        (["objective=tar_arm", "objective.gripper_dims=[]"], "objective.gripper_dims"),
        (["objective=focal", "objective.w_max=0.5"], "objective.w_max must be >= 1"),
        (["objective=dro_time", "objective.dro_eta=0"], "objective.dro_eta must be a finite number > 0"),
        (["objective=dro_time", "objective.dro_eta=-0.5"], "objective.dro_eta must be a finite number > 0"),
        (["objective=dro_time", "objective.dro_eta=nan"], "objective.dro_eta must be a finite number > 0"),
        (["objective=dro_time", "objective.dro_eta=inf"], "objective.dro_eta must be a finite number > 0"),
        (["objective=dro_time", "objective.dro_bins=0"], "objective.dro_bins must be an integer >= 1"),
        (["optim.decay=step"], "optim.decay"),
        (["optim.ema=1.0"], "optim.ema"),
        (["optim.steps=0"], "optim.steps"),
        (["logging.record_weights_at=[5000000]"], "record_weights_at"),
        (["data.seed=1000", "eval.seed=1000"], "eval.seed"),
        (["device=tpu"], "device"),
    ],
)
def test_bad_values_are_refused_before_any_work(tmp_path, overrides, named):
    config = compose_config(f"data.root={tmp_path / 'data'}", f"runs_root={tmp_path / 'runs'}", *overrides)
    with pytest.raises(ConfigError, match=named.replace(".", r"\.")):
        train(config)
    assert not (tmp_path / "data").exists()  # nothing was collected
    assert not (tmp_path / "runs").exists()


@pytest.mark.parametrize("value", [1.5, True])
def test_dro_bins_must_be_an_integer(value):
    # Hydra's typed config refuses a non-integer at composition; a plain dict of settings (a saved run's) is
    # refused by the validation, naming the setting.
    with pytest.raises(ConfigCompositionException):
        compose_config("objective=dro_time", f"objective.dro_bins={str(value).lower()}")
    config = compose_config("objective=dro_time")
    config["objective"]["dro_bins"] = value
    with pytest.raises(ConfigError, match=r"^objective\.dro_bins must be an integer >= 1"):
        validate(config)


@pytest.mark.parametrize("override", ["seed=-1", "data.seed=-1", "eval.seed=-1"])
def test_negative_seeds_are_refused_before_the_run_folder_exists(tmp_path, data_root, override):
    setting = override.split("=")[0]
    config = tiny(tmp_path, data_root, override)
    with pytest.raises(ConfigError, match=rf"^{setting.replace('.', r'[.]')} must be an integer >= 0, got -1"):
        train(config)
    assert not (tmp_path / "runs").exists()


def test_cuda_device_refused_without_cuda(tmp_path):
    if torch.cuda.is_available():
        pytest.skip("CUDA is available here")
    config = compose_config("device=cuda", f"runs_root={tmp_path}")
    with pytest.raises(ConfigError, match="CUDA is not available"):
        train(config)


def test_unwritable_run_directory_is_refused(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    config = compose_config(f"run_dir={blocker / 'run'}", f"data.root={tmp_path / 'data'}")
    with pytest.raises(ConfigError, match="cannot write to the run directory"):
        train(config)


def test_structured_values_are_type_checked():
    register_configs()
    with initialize(version_base="1.3", config_path=None):
        cfg = compose(config_name="train")
    with pytest.raises(ValidationError):
        cfg.optim.steps = "many"
    with pytest.raises(ConfigAttributeError):
        cfg.optim.not_there = 1


# The command line in this process (`python -m tar_rl` itself: tests/test_package.py).


def test_cli_cfg_job_prints_the_config_without_running(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert cli_main(["train", "objective=uniform", "optim.steps=7", "--cfg", "job"]) == 0
    out = capsys.readouterr().out
    assert "name: uniform" in out and "steps: 7" in out
    assert list(tmp_path.iterdir()) == []  # no run directory, no Hydra output folder


def test_cli_reports_a_bad_key_and_fails(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as info:
        cli_main(["train", "optim.lrr=1"])
    assert info.value.code == "tar-rl train: optim.lrr: no such setting (did you mean 'optim.lr'?)"  # printed on exit
    assert list(tmp_path.iterdir()) == []


# -- Builders -----------------------------------------------------------------------------------


def test_learning_rate_schedule_by_hand():
    config = compose_config("optim.steps=110", "optim.warmup=10", "optim.lr=1.0", "optim.min_lr_ratio=0.1")
    param = torch.nn.Parameter(torch.zeros(1))
    optimizer, scheduler = make_optimizer(typed_config(config).optim, [param])
    lrs = []
    for _ in range(110):
        lrs.append(optimizer.param_groups[0]["lr"])
        optimizer.step()
        scheduler.step()
    assert lrs[0] == pytest.approx(0.1)  # (0 + 1) / 10
    assert lrs[9] == pytest.approx(1.0)
    assert lrs[10] == pytest.approx(1.0)  # cosine starts at its peak
    # half way through the decay (step 60 of 10..110): 0.1 + 0.9 * 0.5 * (1 + cos(pi / 2)) = 0.55
    assert lrs[60] == pytest.approx(0.55)
    assert lrs[109] == pytest.approx(0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * 99 / 100)))


def test_record_weights_matches_the_reference_averaged_over_windows():
    # A 1-D action and an actor that always outputs 0: the per-step MSE is action_t ** 2.
    actor = TensorDictModule(torch.nn.Linear(1, 1, bias=False), in_keys=["observation"], out_keys=["action"])
    torch.nn.init.zeros_(actor.module.weight)
    # uniform has no parameters: record_weights weights with TAR at its defaults
    objective = tar_loss(BCLoss(actor, loss_function="mse", reduction="none"), "uniform")
    a = torch.tensor([0.1, 0.5, 0.2, 0.9, 0.3])
    episode = TensorDict({"observation": torch.zeros(5, 1), "action": a[:, None]}, [5])
    rows = record_weights(objective, [("reach", 7, episode)], slice_len=3, step=11)
    losses = [float(v) ** 2 for v in a]
    # Windows of 3 steps: [0..2], [1..3], [2..4]; each step's weight is its mean over the windows holding it.
    windows = [ref_tar_segment(losses[s : s + 3], [True] * 3, gamma=1.0, w_max=3.0) for s in range(3)]
    expected = [
        windows[0][0],
        (windows[0][1] + windows[1][0]) / 2,
        (windows[0][2] + windows[1][1] + windows[2][0]) / 3,
        (windows[1][2] + windows[2][1]) / 2,
        windows[2][2],
    ]
    assert (
        [r[0] for r in rows] == [11] * 5 and [r[2] for r in rows] == [7] * 5 and [r[3] for r in rows] == list(range(5))
    )
    assert [r[4] for r in rows] == pytest.approx(losses, rel=1e-6)
    assert [r[5] for r in rows] == pytest.approx(expected, rel=1e-5)
    assert [r[6] for r in rows] == pytest.approx(a.tolist())  # the last action dim
    # one action dim: its loss column is the step loss
    assert {len(r) for r in rows} == {8} and [r[7] for r in rows] == pytest.approx(losses, rel=1e-6)


def test_record_weights_gives_a_chunked_heads_per_dim_losses_over_its_valid_entries():
    cfg = typed_config(compose_config("policy=octo_linear", "objective=uniform"))
    torch.manual_seed(0)
    policy = make_policy(cfg.policy, DataInfo(chunk_horizon=3, history=1))
    objective = make_objective(cfg.objective, cfg.optim.steps, cfg.seed, policy)
    valid = torch.tensor([[True] * 3, [True] * 3, [True, True, False], [True, False, False]])  # the episode's end
    chunk = torch.rand(4, 3, 4) * 2 - 1
    chunk[~valid] = 100.0  # padding: a mean that took it in would be far off
    episode = TensorDict(
        {
            "observation_history": torch.randn(4, 1, 39),
            "observation_history_valid": torch.ones(4, 1, dtype=torch.bool),
            "task_id": torch.zeros(4, dtype=torch.long),
            "action_chunk": chunk,
            "action_chunk_valid": valid,
            "action": chunk[:, 0],
        },
        [4],
    )
    rows = record_weights(objective, [("reach", 0, episode)], slice_len=2, step=5)
    with torch.no_grad():
        out = policy.loss(episode.unsqueeze(0))
    (key,) = [k for k in out.keys() if k.startswith("loss")]
    elements = out[key][0]  # [T, H, A], padding included
    assert elements.shape == (4, 3, 4)
    for t, row in enumerate(rows):
        kept = [h for h in range(3) if valid[t, h]]
        by_hand = [sum(float(elements[t, h, a]) for h in kept) / len(kept) for a in range(4)]
        assert len(row) == 11 and list(row[7:]) == pytest.approx(by_hand, rel=1e-5)
        assert row[4] == pytest.approx(sum(by_hand) / 4, rel=1e-5)  # the step loss: the mean of its dims'


def test_weights_file_has_the_per_dim_columns_and_leaves_them_empty_on_shorter_rows(tmp_path):
    rows = [(3, "reach", 0, 0, 0.5, 1.0, -1.0), (5, "reach", 0, 0, 0.25, 1.5, -1.0, 0.2, 0.3)]
    logs = RunLogs(tmp_path, weights=rows)
    logs.write()
    table = pd.read_csv(tmp_path / "weights.csv")
    assert list(table.columns) == [*WEIGHTS_COLUMNS, "loss_dim0", "loss_dim1"]
    assert table["loss_dim0"].isna().tolist() == [True, False] and table["loss_dim1"].iloc[1] == 0.3
    assert weights_columns(7) == list(WEIGHTS_COLUMNS)


def test_weights_file_gives_back_every_float32_exactly_with_nine_digits(tmp_path):
    # float32 values whose shortest exact decimal needs all nine significant digits, and a tiny and a huge one
    values = np.array([0.1, 1 / 3, 16777217.0, 1.4e-45, 3.4028235e38, 0.682382524], dtype=np.float32)
    rows = [(1, "reach", 0, t, float(v), float(v), -1.0, float(v)) for t, v in enumerate(values)]
    RunLogs(tmp_path, weights=rows).write()
    text = (tmp_path / "weights.csv").read_text().splitlines()
    assert text[2].split(",")[4] == "0.333333343"  # float32(1/3) = 0.3333333432674408..., nine digits
    table = pd.read_csv(tmp_path / "weights.csv")
    for column in ("loss", "weight", "loss_dim0"):
        back = table[column].to_numpy().astype(np.float32)
        assert back.view(np.int32).tolist() == values.view(np.int32).tolist(), column


# -- The job ------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def smoke_run(tmp_path_factory, data_root):
    tmp = tmp_path_factory.mktemp("smoke")
    config = tiny(tmp, data_root, "logging.record_weights_at=[10,-1]", "eval.every=20")
    return train(config), config


@pytest.mark.parametrize("objective", ["tilted", "truncate", "keyframe", "focal", "tar_arm", "tar_dimnorm"])
def test_each_baseline_trains_through_the_recipe(tmp_path, data_root, objective):
    config = tiny(
        tmp_path,
        data_root,
        f"objective={objective}",
        "objective.start=0",
        "objective.ramp=0",
        "eval.rollouts=0",
        "diagnostics.heldout_demos=0",
        # segments of 8 steps: the default q = 0.1 would drop nothing (floor(0.8) = 0)
        *(["objective.truncate_fraction=0.25"] if objective == "truncate" else []),
    )
    run_dir = train(config)
    assert run_dir.name.startswith(f"{objective}-mlp-s0-")
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["finished"] and summary["objective"] == objective
    metrics = pd.read_csv(run_dir / "metrics.csv")
    train_rows = metrics[metrics.phase == "train"].pivot(index="step", columns="name", values="value")
    assert (train_rows.tar_mix == 1).all() and train_rows.loss.notna().all()
    assert (train_rows.weight_max > 1).all()  # the baseline reweights the steps from the first one


def test_dro_time_trains_through_the_recipe_and_resumes_exactly(tmp_path, data_root, monkeypatch):
    # The sampler draws each step's `step` (the MLP head reads no such entry) and writes `episode_length`; the
    # group weights are part of the objective's state in the checkpoint, so a resumed run continues them exactly.
    overrides = (
        "objective=dro_time",
        "objective.start=0",
        "objective.ramp=0",
        "objective.dro_eta=0.5",
        "objective.dro_bins=4",
        "eval.rollouts=0",
        "diagnostics.heldout_demos=0",
    )
    run_dir = train(tiny(tmp_path / "whole", data_root, *overrides))
    assert run_dir.name.startswith("dro_time-mlp-s0-")
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["finished"] and summary["objective"] == "dro_time"
    assert (summary["config"]["objective"]["dro_eta"], summary["config"]["objective"]["dro_bins"]) == (0.5, 4)
    metrics = pd.read_csv(run_dir / "metrics.csv")
    train_rows = metrics[metrics.phase == "train"].pivot(index="step", columns="name", values="value")
    assert (train_rows.tar_mix == 1).all() and train_rows.loss.notna().all()
    assert (train_rows.weight_max > 1).all()  # the group weights moved from the first step
    whole = _final_state(run_dir)
    log_q = whole["objective"]["weighting_state.value"]
    assert log_q.shape == (4,) and float(log_q.exp().sum()) == pytest.approx(1.0)
    assert float(log_q.max() - log_q.min()) > 0.01

    config = tiny(tmp_path / "resumed", data_root, *overrides)
    original, calls = SegmentSampler.sample, {"n": 0}

    def sample(self):
        calls["n"] += 1
        if calls["n"] == 17:  # steps 1..16 done; the last checkpoint is step 10's
            raise _Crash
        return original(self)

    monkeypatch.setattr(SegmentSampler, "sample", sample)
    with pytest.raises(_Crash):
        train(config)
    (resumed_dir,) = list(Path(config["runs_root"]).iterdir())
    saved = load_checkpoint(resumed_dir)
    assert saved["step"] == 10 and not torch.equal(saved["objective"]["weighting_state.value"], log_q)
    monkeypatch.setattr(SegmentSampler, "sample", original)
    train(config)
    resumed = _final_state(resumed_dir)
    _assert_same_training(whole, resumed)
    assert torch.equal(resumed["objective"]["weighting_state.value"], log_q)


def test_a_flow_run_ranking_by_its_time_normalized_loss_resumes_exactly(tmp_path, data_root, monkeypatch):
    # The running mean per time bin is part of the objective's state in the checkpoint, so a resumed run
    # continues it (and the per-segment draws of the flow head, from the checkpointed torch RNG) exactly.
    overrides = (
        "policy=flow",
        "policy.dim=16",
        "policy.heads=2",
        "policy.layers=1",
        "policy.expert_dim=16",
        "policy.expert_layers=1",
        "policy.time_sampling=segment",
        "objective.signal=time_normalized",
        "objective.start=0",
        "objective.ramp=0",
        "logging.record_weights_at=[-1]",
        "eval.rollouts=0",
        "diagnostics.heldout_demos=0",
    )
    run_dir = train(tiny(tmp_path / "whole", data_root, *overrides))
    whole = _final_state(run_dir)
    weight = whole["objective"]["inner.signal_state.weight"]
    assert weight.shape == (32,) and (weight > 0).any()
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["finished"] and summary["config"]["objective"]["signal"] == "time_normalized"
    rows = pd.read_csv(run_dir / "weights.csv")
    assert rows.weight.notna().all() and rows.loss.notna().all()

    config = tiny(tmp_path / "resumed", data_root, *overrides)
    original, calls = SegmentSampler.sample, {"n": 0}

    def sample(self):
        calls["n"] += 1
        if calls["n"] == 17:  # steps 1..16 done; the last checkpoint is step 10's
            raise _Crash
        return original(self)

    monkeypatch.setattr(SegmentSampler, "sample", sample)
    with pytest.raises(_Crash):
        train(config)
    (resumed_dir,) = list(Path(config["runs_root"]).iterdir())
    saved = load_checkpoint(resumed_dir)
    assert saved["step"] == 10 and not torch.equal(saved["objective"]["inner.signal_state.weight"], weight)
    monkeypatch.setattr(SegmentSampler, "sample", original)
    train(config)
    resumed = _final_state(resumed_dir)
    _assert_same_training(whole, resumed)
    for name in ("total", "weight"):
        key = f"inner.signal_state.{name}"
        assert torch.equal(resumed["objective"][key], whole["objective"][key])


def test_smoke_run_writes_every_output(smoke_run):
    run_dir, _ = smoke_run
    assert run_dir.name.startswith("tar-mlp-s0-")
    metrics = pd.read_csv(run_dir / "metrics.csv")
    assert list(metrics.columns) == ["step", "phase", "name", "value"]
    train_rows = metrics[metrics.phase == "train"]
    assert sorted(train_rows.step.unique()) == [5, 10, 15, 20, 25, 30]
    assert {"loss", "uniform_loss", "tar_mix", "weight_max", "weight_ess", "lr", "grad_norm"} <= set(train_rows.name)
    eval_rows = metrics[metrics.phase == "eval"]
    assert sorted(eval_rows.step.unique()) == [20, 30]  # eval.every=20, then the final one
    assert {"success/overall", "fast20/easy", "neps/overall"} <= set(eval_rows.name)
    rollouts = pd.read_csv(run_dir / "eval_rollouts.csv")
    assert len(rollouts) == 2 and sorted(rollouts.step) == [20, 30] and set(rollouts.task) == {f"{TASK}-v3"}
    weights = pd.read_csv(run_dir / "weights.csv")
    assert sorted(weights.step.unique()) == [10, 30]
    # one demonstration of the task at each recorded step, every step of it
    assert weights.groupby("step").size().nunique() == 1 and len(weights) % 2 == 0
    assert (weights.groupby("step").t.max() + 1 == len(weights) // 2).all()
    # the MLP head's step loss is the plain mean of its 4 action dims' losses
    dims = [f"loss_dim{i}" for i in range(4)]
    assert list(weights.columns) == [*WEIGHTS_COLUMNS, *dims]
    assert weights[dims].mean(axis=1).to_numpy() == pytest.approx(weights["loss"].to_numpy(), rel=1e-6, abs=1e-9)
    assert (weights[dims].std(axis=1) > 0).any()  # the dims differ: the identity is not trivial
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["finished"] and summary["steps"] == 30 and summary["objective"] == "tar"
    overall = next(r for r in summary["final"] if r["level"] == "overall")
    assert overall["n_rollouts"] == 1 and overall["success"] in (0.0, 1.0)
    assert (run_dir / "config.yaml").read_text().count("name: tar") == 1
    state = load_checkpoint(run_dir)
    assert state["step"] == 30 and state["finished"]


def test_training_changes_the_policy_that_is_evaluated(smoke_run, data_root):
    run_dir, config = smoke_run
    state = load_checkpoint(run_dir)
    torch.manual_seed(config["seed"])
    fresh = make_policy(typed_config(config).policy, DataInfo.from_dict(state["data_info"]))
    for name, value in fresh.actor.state_dict().items():
        if name.startswith("module.norm."):
            assert torch.equal(value, state["policy"][name])  # the dataset statistics
        else:
            assert not torch.equal(value, state["policy"][name]), name  # trained
    # the checkpoint's policy is the one that ran in the final evaluation: re-evaluating it agrees
    again = evaluate_checkpoint(run_dir, progress=False)
    rollouts = pd.read_csv(run_dir / "eval_rollouts.csv")
    final = rollouts[rollouts.step == 30].reset_index(drop=True)
    assert again["success"].tolist() == final["success"].tolist()
    assert again["steps"].tolist() == final["steps"].tolist()
    assert (run_dir / "eval-1000.csv").exists()


def test_a_finished_run_is_not_run_again(smoke_run, capsys):
    run_dir, config = smoke_run
    before = (run_dir / CHECKPOINT).stat().st_mtime_ns
    assert train(config) == run_dir
    assert "finished already" in capsys.readouterr().out
    assert (run_dir / CHECKPOINT).stat().st_mtime_ns == before


def test_a_run_directory_holding_other_settings_is_refused(smoke_run, tmp_path, data_root):
    run_dir, _ = smoke_run
    config = tiny(tmp_path, data_root, f"run_dir={run_dir}", "objective.gamma=2")
    with pytest.raises(ConfigError, match=r"objective\.gamma: 1\.0 -> 2\.0"):
        train(config)


def test_eval_command_errors(tmp_path, smoke_run):
    with pytest.raises(FileNotFoundError, match="no checkpoint"):
        evaluate_checkpoint(tmp_path / "missing.pt")
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="not a readable tar-rl checkpoint"):
        evaluate_checkpoint(tmp_path / "junk.pt")
    # a checkpoint whose config no longer fits its weights (hidden sizes changed by hand)
    run_dir, _ = smoke_run
    state = load_checkpoint(run_dir)
    state["config"]["policy"]["hidden"] = [16]
    torch.save(state, tmp_path / "edited.pt")
    with pytest.raises(ValueError, match="do not fit the policy"):
        evaluate_checkpoint(tmp_path / "edited.pt", progress=False)


# -- Resume ----------------------------------------------------------------------------------


def _final_state(run_dir: Path) -> dict:
    return load_checkpoint(run_dir)


def _assert_same_training(a: dict, b: dict) -> None:
    for name in a["policy"]:
        assert torch.equal(a["policy"][name], b["policy"][name]), name
    for name in a["ema_policy"] or {}:
        assert torch.equal(a["ema_policy"][name], b["ema_policy"][name]), name
    assert torch.equal(a["sampler_rng"], b["sampler_rng"])
    assert a["objective"]["schedule_step"] == b["objective"]["schedule_step"] == a["step"]
    sa, sb = a["optimizer"]["state"], b["optimizer"]["state"]
    assert sa.keys() == sb.keys()
    for k in sa:
        assert torch.equal(sa[k]["exp_avg"], sb[k]["exp_avg"])
    train_a = [r for r in a["logs"]["metrics"] if r[1] == "train"]
    train_b = [r for r in b["logs"]["metrics"] if r[1] == "train"]
    assert train_a == train_b


class _Crash(Exception):
    pass


@pytest.mark.slow
def test_a_runs_evaluations_share_one_pool_that_ends_with_the_run(tmp_path, data_root, monkeypatch):
    from tar_rl.collectors.metaworld import suite as metaworld

    pools = []
    real = metaworld.evaluate

    def recording(*args, pool, **kwargs):
        pools.append(pool)
        return real(*args, pool=pool, **kwargs)

    monkeypatch.setattr(metaworld, "evaluate", recording)
    config = tiny(tmp_path, data_root, "eval.every=10")
    train(config)
    assert len(pools) == 3 and all(p is pools[0] for p in pools)  # steps 10 and 20, then the final one
    assert pools[0].closed
    # a run that fails after an evaluation closes its pool too
    pools.clear()
    original = SegmentSampler.sample
    calls = {"n": 0}

    def sample(self):
        calls["n"] += 1
        if calls["n"] == 15:
            raise _Crash
        return original(self)

    monkeypatch.setattr(SegmentSampler, "sample", sample)
    with pytest.raises(_Crash):
        train({**config, "runs_root": str(tmp_path / "crashed")})
    assert len(pools) == 1 and pools[0].closed


LOG_FILES = ("metrics.csv", "eval_rollouts.csv", "weights.csv")


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory, data_root):
    tmp = tmp_path_factory.mktemp("whole")
    # `random` draws from the objective's generator every step; EMA adds its own state. Metrics rows
    # every 4 steps and checkpoints every 10: the checkpoint of step 10 falls inside a logging window
    # (steps 9..12), so a run resumed from it must carry the window's running sums over.
    config = tiny(
        tmp,
        data_root,
        "objective=random",
        "optim.ema=0.9",
        "logging.every=4",
        "eval.every=20",
        "logging.record_weights_at=[10,-1]",
    )
    run_dir = train(config)
    return _final_state(run_dir), config, {name: (run_dir / name).read_bytes() for name in LOG_FILES}


def _assert_same_log_files(logs: dict[str, bytes], run_dir: Path) -> None:
    for name, expected in logs.items():
        assert (run_dir / name).read_bytes() == expected, name


# between checkpoints (and inside a logging window); right after the checkpoint of step 20
@pytest.mark.parametrize("crash_at", [17, 21])
def test_a_killed_run_resumes_to_the_same_weights_and_byte_identical_logs(
    tmp_path, data_root, monkeypatch, uninterrupted, crash_at
):
    whole, whole_config, logs = uninterrupted
    config = {**whole_config, "runs_root": str(tmp_path / "runs")}
    calls = {"n": 0}
    original = SegmentSampler.sample

    def sample(self):
        calls["n"] += 1
        if calls["n"] == crash_at:  # the sample of step crash_at: steps 1..crash_at-1 are done
            raise _Crash
        return original(self)

    monkeypatch.setattr(SegmentSampler, "sample", sample)
    with pytest.raises(_Crash):
        train(config)
    (run_dir,) = list(Path(config["runs_root"]).iterdir())
    assert load_checkpoint(run_dir)["step"] == 10 * ((crash_at - 1) // 10)
    assert not (run_dir / "summary.json").exists()
    monkeypatch.setattr(SegmentSampler, "sample", original)
    train(config)
    _assert_same_training(whole, _final_state(run_dir))
    metrics = pd.read_csv(run_dir / "metrics.csv")
    assert sorted(metrics[metrics.phase == "train"].step.unique()) == [4, 8, 12, 16, 20, 24, 28, 30]  # none twice
    _assert_same_log_files(logs, run_dir)


def test_a_crash_while_writing_a_checkpoint_keeps_the_previous_one(tmp_path, data_root, monkeypatch, uninterrupted):
    whole, whole_config, logs = uninterrupted
    config = {**whole_config, "runs_root": str(tmp_path / "runs")}
    real_save = torch.save
    calls = {"n": 0}

    def failing_save(obj, f, *args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 2:  # the checkpoint of step 20: write half of it, then die
            f.write(b"\x80partial")
            raise _Crash
        return real_save(obj, f, *args, **kwargs)

    monkeypatch.setattr(torch, "save", failing_save)
    with pytest.raises(_Crash):
        train(config)
    (run_dir,) = list(Path(config["runs_root"]).iterdir())
    assert load_checkpoint(run_dir)["step"] == 10  # the intact earlier checkpoint
    assert not [p for p in run_dir.iterdir() if p.name.endswith(".tmp")]
    monkeypatch.setattr(torch, "save", real_save)
    train(config)
    _assert_same_training(whole, _final_state(run_dir))
    _assert_same_log_files(logs, run_dir)


def _nan_after(monkeypatch, step: int) -> None:
    """From training step ``step`` on, every per-step loss of the head is NaN (where a diverging run's NaN arises)."""
    real = TARLoss._step_losses

    def step_losses(self, out, key, tensordict):
        losses = real(self, out, key, tensordict)
        if self.training and int(self.schedule_step) + 1 >= step:
            losses = losses * float("nan")
        return losses

    monkeypatch.setattr(TARLoss, "_step_losses", step_losses)


@pytest.mark.parametrize("objective", ["tar", "uniform"])
def test_a_nan_loss_stops_the_run_and_keeps_the_last_good_checkpoint(tmp_path, data_root, monkeypatch, objective):
    config = tiny(tmp_path, data_root, f"objective={objective}")
    _nan_after(monkeypatch, 15)
    with pytest.raises(TrainingError) as info:
        train(config)
    (run_dir,) = list((tmp_path / "runs").iterdir())
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith("non-finite loss or gradient at step 15 of 30")
    assert f"the last good checkpoint (step 10) is kept in {run_dir / CHECKPOINT}" in message
    assert "optim.skip_nonfinite" in message
    state = load_checkpoint(run_dir)
    assert state["step"] == 10
    assert all(torch.isfinite(v).all() for v in state["policy"].values())


@pytest.mark.parametrize("objective", ["tar", "uniform"])
def test_nan_steps_can_be_skipped(tmp_path, data_root, monkeypatch, capsys, objective):
    config = tiny(tmp_path, data_root, f"objective={objective}", "optim.skip_nonfinite=100")
    _nan_after(monkeypatch, 26)  # steps 26..30 are skipped
    run_dir = train(config)
    metrics = pd.read_csv(run_dir / "metrics.csv")
    skipped = metrics[(metrics.phase == "train") & (metrics.name == "skipped")].set_index("step").value
    assert skipped[25] == 0 and skipped[30] == 5
    assert json.loads((run_dir / "summary.json").read_text())["nonfinite_steps_skipped"] == 5
    last_lines = capsys.readouterr().out.strip().splitlines()[-2:]
    assert any("5 of 30 steps were skipped" in line and "optim.skip_nonfinite=100" in line for line in last_lines)
    state = load_checkpoint(run_dir)
    assert all(torch.isfinite(v).all() for v in state["policy"].values())


def _train_command(argv: list[str]) -> int:
    """``tar-rl train ARGV`` in this process; the logging that a Hydra launcher sets up for its process is undone."""
    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    try:
        return cli_main(["train", *argv])
    finally:
        root.handlers[:] = handlers
        root.setLevel(level)


def test_multirun_sweep_over_objectives_and_its_restart_skips_finished_runs(tmp_path, data_root, monkeypatch, capfd):
    """A sweep through Hydra's joblib launcher; run again, it skips the finished runs.

    Both commands run in this process (`python -m tar_rl` itself: tests/test_package.py); the second finds the
    launcher's worker processes of the first (joblib keeps them for a while)."""
    command = [
        "-m",
        "hydra/launcher=joblib",  # Hydra's joblib launcher plugin: the runs go in parallel processes
        "hydra.launcher.n_jobs=2",
        "objective=uniform,tar",
        f"data.tasks=[{TASK}]",
        "data.n_demos=2",
        "data.workers=1",
        f"data.root={data_root}",
        "optim.steps=10",
        "logging.every=5",
        "logging.progress=false",
        "logging.record_weights_at=[]",
        "eval.rollouts=1",
        "eval.horizon=10",
        "eval.workers=1",
    ]
    monkeypatch.chdir(tmp_path)
    assert _train_command(command) == 0
    runs = sorted(p.name.split("-")[0] for p in (tmp_path / "runs").iterdir() if p.is_dir())
    assert runs == ["tar", "uniform"]
    for run in (tmp_path / "runs").iterdir():
        if run.is_dir():
            assert json.loads((run / "summary.json").read_text())["finished"]
    capfd.readouterr()
    assert _train_command(command) == 0
    assert capfd.readouterr().out.count("finished already") == 2  # printed by the launcher's worker processes


@pytest.mark.gpu
def test_a_tiny_run_trains_on_cuda_with_amp(tmp_path, data_root):
    run_dir = train(tiny(tmp_path, data_root, "device=cuda", "optim.amp=true"))
    state = load_checkpoint(run_dir)
    assert state["step"] == 30 and all(torch.isfinite(v).all() for v in state["policy"].values())
    assert json.loads((run_dir / "summary.json").read_text())["finished"]


def test_report_compares_the_smoke_runs(smoke_run, data_root, tmp_path, capsys):
    from tar_rl.report import main as report_main

    run_dir, config = smoke_run
    common = {f.name for f in dataclasses.fields(ObjectiveConfig)}  # the settings uniform shares with tar
    uniform = {key: value for key, value in config["objective"].items() if key in common}
    baseline = train({**config, "objective": {**uniform, "name": "uniform"}})
    assert baseline.parent == run_dir.parent and baseline.name.startswith("uniform-mlp-s0-")
    out = tmp_path / "report"
    assert report_main([str(run_dir.parent), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "uniform" in printed and "tar" in printed
    table = pd.read_csv(out / "comparison.csv")
    assert sorted(table["objective"]) == ["tar", "uniform"]
    finals = {
        name: json.loads((d / "summary.json").read_text())["final"]
        for name, d in (("tar", run_dir), ("uniform", baseline))
    }
    for name, final in finals.items():
        overall = next(r for r in final if r["level"] == "overall")
        row = table[table["objective"] == name].iloc[0]
        assert row["success_overall_mean"] == pytest.approx(100 * overall["success"])
    for png in ("success_vs_neps.png", "group_success.png", f"weights_{run_dir.name}.png"):
        assert (out / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_slurm_launcher_example_composes(tmp_path, monkeypatch, capsys):
    examples = REPO / "recipes" / "examples"
    monkeypatch.chdir(tmp_path)
    command = ["train", "--config-dir", str(examples), "hydra/launcher=slurm", "hydra.launcher.partition=gpu"]
    assert cli_main([*command, "--cfg", "hydra"]) == 0
    out = capsys.readouterr().out
    assert "SlurmLauncher" in out and "partition: gpu" in out


def test_settings_at_their_default_keep_run_names():
    # A run is named by the settings that differ from its objective's and head's default job: a config saved
    # before a setting existed (the setting absent) and one holding its default are the same run.
    import copy

    from tar_rl.recipes import identity, run_name
    from tar_rl.runs import config_differences

    cfg = compose_config()
    old = copy.deepcopy(cfg)
    del old["data"]["path"], old["data"]["suite"]
    assert cfg["data"]["path"] is None and cfg["data"]["suite"] == "metaworld"
    assert run_name(cfg) == run_name(old)
    assert config_differences(identity(old), identity(cfg)) == []
    assert run_name(compose_config("data.path=/some/dataset")) != run_name(cfg)
    assert run_name(compose_config("data.suite=dm_control")) != run_name(cfg)
    for head in POLICIES:
        cfg = compose_config(f"policy={head}")
        assert identity(cfg) == {}  # the default job of every head differs from nothing
        changed = identity(compose_config(f"policy={head}", "policy.observation=image", "optim.lr=0.002"))
        assert changed == {"policy": {"observation": "image"}, "optim": {"lr": 0.002}}
        assert run_name(compose_config(f"policy={head}", "policy.observation=image")) != run_name(cfg)
    # settings that do not change what a run computes are never part of it
    assert identity(compose_config("data.workers=3", "eval.workers=1", "logging.progress=false", "threads=2")) == {}
