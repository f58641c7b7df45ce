"""``benchmarks/lerobot_pilot.py``: a LeRobot checkpoint rolled out by tar-rl's MetaWorld evaluator through the
plugin's policy server (``lerobot-tar serve``), against chunks computed in LeRobot's environment by hand from the
checkpoint's network and statistics and executed by a fresh ``ChunkedActor``; and the pilot's printed commands.

The rollouts need the plugin's environment, ``.venv-lerobot/`` at the repository root (``lerobot_policy_tar/env.sh``
builds it; ``LEROBOT_PYTHON`` names another Python of it); without it they are skipped, saying so
(tar-rl's own pytest run, before CI builds it), and ``lerobot_policy_tar/test.sh`` runs this file once it is built.
"""

from __future__ import annotations

import json
import os
import pickle
import subprocess
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from paths import REPO
from tensordict.nn import TensorDictModuleBase
from torch import nn

from benchmarks import lerobot_pilot
from tar_rl.collectors.suite import COLUMNS
from tar_rl.policies.chunking import ChunkedActor
from tar_rl.runs import ROLLOUTS_COLUMNS, ROLLOUTS_FILE, SUMMARY_FILE

LEROBOT_PYTHON = Path(os.environ.get("LEROBOT_PYTHON", REPO / ".venv-lerobot" / "bin" / "python"))
TINY = REPO / "lerobot_policy_tar" / "tests" / "tiny_checkpoint.py"
needs_plugin = pytest.mark.skipif(
    not LEROBOT_PYTHON.is_file(),
    reason=f"the plugin's environment is missing ({LEROBOT_PYTHON}): lerobot_policy_tar/env.sh builds it",
)
REACH = "Reach the goal position with the gripper."  # tar-rl's instruction of reach-v3, the exported frames' task


class Recorder(TensorDictModuleBase):
    """An actor that records what it reads (observation, task_id, is_init) and the action it writes, per call."""

    def __init__(self, actor: TensorDictModuleBase):
        super().__init__()
        self.actor = actor
        self.in_keys, self.out_keys = actor.in_keys, actor.out_keys
        self.calls: list[dict] = []

    def forward(self, tensordict):
        seen = {key: tensordict.get(key).clone() for key in ("observation", "task_id", "is_init")}
        out = self.actor(tensordict)
        self.calls.append({**seen, "action": out.get("action").clone()})
        return out


class Replay(nn.Module):
    """Given chunks, one ``[N, H, A]`` per call, in order."""

    def __init__(self, chunks: np.ndarray):
        super().__init__()
        self.chunks, self.calls = torch.from_numpy(chunks), 0

    def predict_chunk(self, history, history_valid, task_id):
        chunk = self.chunks[self.calls]
        self.calls += 1
        return chunk


#: The plugin environment's side of these tests, one process for all of them (LeRobot starts once): it reads one
#: JSON request a line on stdin and answers each with one ``REPLY <json>`` line on stdout (LeRobot may print too).
#: ``{"write": FOLDER}``: ``tiny_checkpoint.py``'s tiny ``act`` checkpoint; ``{"chunks": [FOLDER, IN, OUT]}``: its
#: chunks computed by hand; ``{"parse": LINES}``: the command lines parsed by LeRobot's config parser as
#: ``lerobot-train`` parses them, after importing the plugin (as ``lerobot-train`` does), a summary of each.
PLUGIN_SIDE = """
import json, runpy, shlex, sys
from pathlib import Path
import numpy as np
import draccus
import lerobot_policy_tar  # registers act_tar
from lerobot.configs.train import TrainPipelineConfig

tiny = runpy.run_path(sys.argv[1])


def parse(lines):
    out = []
    for line in lines:
        cfg = draccus.parse(TrainPipelineConfig, args=shlex.split(line)[1:])
        p = cfg.policy
        out.append({
            "type": p.type, "batch": cfg.batch_size, "steps": cfg.steps, "dim": p.dim_model, "ffn": p.dim_feedforward,
            "pre_norm": p.pre_norm, "dropout": p.dropout, "chunk": p.chunk_size, "ensemble": p.temporal_ensemble_coeff,
            "norm": sorted(k for k, v in p.normalization_mapping.items() if v.value == "MEAN_STD"),
            "lr": cfg.optimizer.lr, "clip": cfg.optimizer.grad_clip_norm, "warmup": cfg.scheduler.num_warmup_steps,
            "tar": [p.tar.start, p.tar.ramp, p.tar.slice_len] if hasattr(p, "tar") else None,
        })
    return out


for request in sys.stdin:
    request = json.loads(request)
    if "write" in request:
        tiny["write"](Path(request["write"]))
        reply = None
    elif "chunks" in request:
        folder, given, out = request["chunks"]
        given = np.load(given)
        np.savez(out, chunks=tiny["chunks"](Path(folder), given["observations"], given["tasks"].tolist()))
        reply = None
    else:
        reply = parse(request["parse"])
    print("REPLY " + json.dumps(reply), flush=True)
"""


class PluginSide:
    """:data:`PLUGIN_SIDE` running in the plugin's environment: :meth:`ask` sends a request, returns its reply (a
    request that fails ends the process: the assertion holds its stderr's end)."""

    def __init__(self):
        env = {**os.environ, "HF_HUB_OFFLINE": "1"}
        command = [str(LEROBOT_PYTHON), "-c", PLUGIN_SIDE, str(TINY)]
        self.errors = tempfile.TemporaryFile()
        self.process = subprocess.Popen(
            command, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=self.errors, text=True, env=env
        )

    def ask(self, **request):
        self.process.stdin.write(json.dumps(request) + "\n")
        self.process.stdin.flush()
        for line in self.process.stdout:
            if line.startswith("REPLY "):
                return json.loads(line[len("REPLY ") :])
        self.errors.seek(0)
        raise AssertionError(self.errors.read().decode(errors="replace")[-3000:])

    def close(self):
        self.process.stdin.close()
        assert self.process.wait(timeout=60) == 0
        self.process.stdout.close()
        self.errors.close()


@pytest.fixture(scope="module")
def plugin_side():
    side = PluginSide()
    yield side
    side.close()


@needs_plugin
@pytest.mark.slow
def test_a_server_that_cannot_load_the_checkpoint_is_reported_in_one_line(tmp_path, plugin_side):
    # The first test to use plugin_side: its process imports LeRobot while this server does.
    model = lerobot_pilot.LeRobotChunks(LEROBOT_PYTHON, tmp_path)
    with pytest.raises(RuntimeError, match=r"ended: lerobot-tar serve: .* is not a LeRobot policy checkpoint"):
        model.start()


@needs_plugin
@pytest.mark.slow
def test_a_lerobot_checkpoint_rolls_out_as_its_chunks_computed_in_its_own_environment(tmp_path, plugin_side):
    run = tmp_path / "outputs" / "checkpoints" / "000002"
    checkpoint = run / "pretrained_model"
    plugin_side.ask(write=str(checkpoint))
    (run / "training_state").mkdir()
    (run / "training_state" / "training_step.json").write_text('{"step": 2}')
    model = lerobot_pilot.LeRobotChunks(LEROBOT_PYTHON, checkpoint)
    try:
        actor = lerobot_pilot.actor_for(model)
        assert model.sizes == (39, 8, 4) and actor.horizon == 8 and actor.history == 1
        copy = pickle.loads(pickle.dumps(actor))  # an evaluation worker's: it starts its own server
        assert copy.model._process is None and copy.model.checkpoint == str(checkpoint)
        recorder = Recorder(actor)
        rows = lerobot_pilot.evaluate_lerobot(
            recorder, checkpoint=checkpoint, tasks=["reach"], rollouts=2, seed=1000, horizon=20, workers=1,
            out=tmp_path / "eval", execution=lerobot_pilot.execution_of(actor), progress=False,
        )  # fmt: skip
    finally:
        model.close()
    assert list(rows.columns) == list(COLUMNS) and len(rows) == 2
    assert rows["task"].tolist() == ["reach-v3", "reach-v3"] and rows["variation_index"].tolist() == [0, 1]
    written = pd.read_csv(tmp_path / "eval" / ROLLOUTS_FILE)
    assert set(ROLLOUTS_COLUMNS) <= set(written.columns) and written["step"].tolist() == [2, 2]
    summary = json.loads((tmp_path / "eval" / SUMMARY_FILE).read_text())
    assert summary["policy"] == "act" and summary["steps"] == 2 and summary["finished"]
    assert any(rec["level"] == "overall" for rec in summary["final"])
    assert summary["execution"] == {"execution": "ensemble", "ensemble_decay": 0.01, "chunk_horizon": 8}

    # The same observations through the policy in LeRobot's environment, by hand, then a fresh ChunkedActor.
    calls = recorder.calls
    assert len(calls) >= 20 and all(call["observation"].shape == (2, 39) for call in calls)
    reach = lerobot_pilot.mw_tasks.TASKS.index("reach-v3")
    assert all(call["task_id"].reshape(-1).tolist() == [reach, reach] for call in calls)
    observations = torch.stack([call["observation"] for call in calls]).numpy()  # [T, N, 39]
    t, n = observations.shape[:2]
    np.savez(tmp_path / "in.npz", observations=observations.reshape(t * n, 39), tasks=np.array([REACH] * (t * n)))
    plugin_side.ask(chunks=[str(checkpoint), str(tmp_path / "in.npz"), str(tmp_path / "out.npz")])
    chunks = np.load(tmp_path / "out.npz")["chunks"].reshape(t, n, 8, 4)
    replay = ChunkedActor(Replay(chunks), horizon=8, history=1, execution="ensemble", ensemble_decay=0.01)
    from tensordict import TensorDict

    for call in calls:
        td = TensorDict({k: call[k] for k in ("observation", "task_id", "is_init")}, batch_size=[n])
        expected = replay(td).get("action")
        torch.testing.assert_close(call["action"], expected, rtol=1e-4, atol=1e-5)
    actions = torch.stack([call["action"] for call in calls])
    assert actions.std(0).max() > 1e-3 and (actions.abs() < 1).any()  # actions that move with the observations


def test_a_missing_environment_is_named():
    model = lerobot_pilot.LeRobotChunks(REPO / "no-such-venv" / "bin" / "python", REPO)
    with pytest.raises(FileNotFoundError, match="build the plugin's environment"):
        model.start()


def test_task_texts_are_the_exporters():
    # lerobot-tar export-dataset writes each frame's task as the task's instruction from the dataset's metadata,
    # which tar-rl's MetaWorld collector fills from tasks.INSTRUCTIONS.
    assert lerobot_pilot.task_text(lerobot_pilot.mw_tasks.TASKS.index("reach-v3")) == REACH


def test_the_plan_matches_r4_and_the_act_head():
    from benchmarks.studies.regimes import SIZES, chunked_base
    from tar_rl.policies.act import ACTConfig

    lines = lerobot_pilot.pilot_commands(seed=0, root="pilot")
    r4 = chunked_base(SIZES["cpu"], "R4")
    assert f"optim.steps={lerobot_pilot.R4_STEPS}" in r4 and "data.n_demos=50" in r4 and "data.seed=0" in r4
    act, act_tar = (next(line for line in lines if f"--policy.type={arm} " in line) for arm in ("act", "act_tar"))
    assert "--batch_size=1024 " in act and "--batch_size=64 " in act_tar and "--policy.tar.slice_len=16" in act_tar
    assert "--policy.tar.start=749 --policy.tar.ramp=1123" in act_tar  # round(0.2 x 3743), round(0.3 x 3743)
    head = ACTConfig()
    for option, value in (("dim_model", head.dim), ("n_heads", head.heads), ("dim_feedforward", head.ffn_dim),
                          ("n_encoder_layers", head.enc_layers), ("n_decoder_layers", head.dec_layers),
                          ("n_vae_encoder_layers", head.cvae_layers), ("latent_dim", head.latent_dim)):  # fmt: skip
        assert f"--policy.{option}={value} " in act and f"--policy.{option}={value} " in act_tar
    assert all("--steps=3743 " in line and "--seed=0 " in line for line in (act, act_tar))
    assert lines[-1].endswith("--tasks mt50 --rollouts 20 --seed 1000 --out pilot/eval/act_tar-seed0")
    # saved every 250 steps, and each run resumed from the last checkpoint under its own output folder
    assert all("--save_freq=250 " in line for line in (act, act_tar))
    resume = lerobot_pilot.resume_commands(seed=0, root="pilot")
    for line, arm in zip(resume, ("act", "act_tar"), strict=True):
        assert f"--output_dir=pilot/runs/{arm}-seed0" in (act if arm == "act" else act_tar)
        assert line == (
            ".venv-lerobot/bin/lerobot-train --config_path="
            f"pilot/runs/{arm}-seed0/checkpoints/last/pretrained_model/train_config.json --resume=true"
        )


@needs_plugin
@pytest.mark.slow
def test_lerobot_train_reads_the_plans_lines_as_meant(plugin_side):
    lines = [line for line in lerobot_pilot.pilot_commands() if "lerobot-train" in line]
    act, act_tar = plugin_side.ask(parse=lines)
    common = {"steps": 3743, "dim": 64, "ffn": 128, "pre_norm": True, "dropout": 0.0, "chunk": 8, "ensemble": 0.01}
    common |= {"norm": ["ACTION", "ENV", "STATE", "VISUAL"], "lr": 1e-3, "clip": 1.0, "warmup": 200}
    assert act == {**common, "type": "act", "batch": 1024, "tar": None}
    assert act_tar == {**common, "type": "act_tar", "batch": 64, "tar": [749, 1123, 16]}
