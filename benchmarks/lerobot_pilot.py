"""LeRobot policies on tar-rl's MetaWorld evaluator, and the commands of the first measured pair (issue 38, item 6).

``evaluate``: a trained LeRobot checkpoint (any state policy reading one observation step: ``act``, ``act_tar``, ...)
rolled out by tar-rl's evaluator (:func:`tar_rl.collectors.metaworld.evaluate.evaluate`) on MetaWorld's 39-value
state observations. LeRobot cannot be imported here (it needs torch below 2.12), so each process that rolls out
(this one with ``--workers 1``, else every evaluation worker) starts the plugin's policy server ``lerobot-tar serve``
(``lerobot_policy_tar/src/lerobot_policy_tar/serve.py``) in LeRobot's environment on its first chunk and sends it
the current observation and the task's text (tar-rl's instruction of the task, what the exporter wrote as each
frame's ``task``). The server answers the policy's ``predict_action_chunk`` through the checkpoint's own pre- and
post-processors. The chunks are executed by tar-rl's :class:`~tar_rl.policies.chunking.ChunkedActor` with the
``act`` head's default execution, ACT's temporal ensembling (a new chunk every step, decay 0.01), so a LeRobot ACT
is executed exactly as tar-rl's ``act`` is. The run's folder gets ``eval_rollouts.csv`` (the evaluator's columns
and ``step``, the checkpoint's training step) and ``summary.json`` (the final table per group, as a tar-rl run's).

``plan``: the pilot's commands (collect R4's data, export it, train LeRobot's ``act`` and ``act_tar`` at the size of
tar-rl's ``act`` head with R4's schedule, evaluate both here) and their cost; nothing is run.

    .venv/bin/python -m benchmarks.lerobot_pilot evaluate --checkpoint DIR --python .venv-lerobot/bin/python \\
        --tasks mt50 --rollouts 20 --seed 1000 --out DIR [--horizon 500] [--workers N]
    .venv/bin/python -m benchmarks.lerobot_pilot plan
"""

from __future__ import annotations

import argparse
import io
import json
import os
import struct
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from tensordict.nn import TensorDictModuleBase
from torch import nn

from tar_rl.collectors.metaworld import tasks as mw_tasks
from tar_rl.collectors.metaworld.evaluate import MAX_HORIZON, evaluate
from tar_rl.io import check_writable, write_csv_atomic, write_json_atomic
from tar_rl.metrics import summarize
from tar_rl.policies.chunking import ChunkedActor
from tar_rl.runs import ROLLOUTS_FILE, SUMMARY_FILE, git_commit, json_metric, machine, portable_path, print_table

__all__ = [
    "LeRobotChunks",
    "actor_for",
    "evaluate_lerobot",
    "execution_of",
    "main",
    "pilot_commands",
    "resume_commands",
    "task_text",
]

REPO = Path(__file__).resolve().parents[1]
#: The frame of ``lerobot-tar serve``'s protocol: an 8-byte little-endian length, then one ``.npy`` array.
HEADER = struct.Struct("<Q")
#: tar-rl's ``act`` head's default chunk execution (``tar_rl.policies.chunking.ChunkedHeadConfig``).
ENSEMBLE_DECAY = 0.01


def task_text(task_id: int) -> str:
    """The text a LeRobot policy gets for MetaWorld task ``task_id`` (an index of ``TASKS``): its instruction, as
    ``lerobot-tar export-dataset`` writes each frame's ``task`` (the task's name where there is none)."""
    name = mw_tasks.TASKS[task_id]
    return mw_tasks.INSTRUCTIONS.get(name) or name


def _write_frame(stream, array: np.ndarray) -> None:
    buffer = io.BytesIO()
    np.save(buffer, np.ascontiguousarray(array), allow_pickle=False)
    stream.write(HEADER.pack(len(buffer.getvalue())) + buffer.getvalue())


def _read_frame(stream) -> np.ndarray | None:
    header = stream.read(HEADER.size)
    if len(header) < HEADER.size:
        return None
    (length,) = HEADER.unpack(header)
    payload = stream.read(length)
    if len(payload) < length:
        return None
    return np.load(io.BytesIO(payload), allow_pickle=False)


class LeRobotChunks(nn.Module):
    """A LeRobot checkpoint's chunks for :class:`ChunkedActor`, from a ``lerobot-tar serve`` process.

    The process starts on the first use in each process (a pickled copy, as an evaluation worker gets, starts its
    own) and ends when this one is closed, collected or its process exits (the server exits at EOF on its stdin).

    Args:
        python: the Python of LeRobot's environment with the plugin (``.venv-lerobot/bin/python``).
        checkpoint: LeRobot's ``pretrained_model`` folder (or the checkpoint folder above it).
        threads: torch threads of the server.
    """

    def __init__(self, python: str | os.PathLike, checkpoint: str | os.PathLike, threads: int = 1):
        super().__init__()
        self.python, self.checkpoint, self.threads = str(python), str(checkpoint), int(threads)
        self._process = self._errors = None
        self.sizes: tuple[int, int, int] | None = None  # (D, H, A), from the server's first frame

    def __getstate__(self):
        state = dict(self.__dict__)
        state["_process"] = state["_errors"] = None
        return state

    def _server_error(self) -> str:
        self._process.wait(timeout=30)
        self._errors.seek(0)
        lines = self._errors.read().decode(errors="replace").strip().splitlines()
        said = lines[-1] if lines else "(nothing on stderr)"
        return f"the policy server ({self.python} -m lerobot_policy_tar.cli serve) ended: {said}"

    def start(self) -> tuple[int, int, int]:
        """Start the server if it is not running; ``(D, H, A)``: observation size, chunk length, action size."""
        if self._process is None or self._process.poll() is not None:
            if not Path(self.python).is_file():
                raise FileNotFoundError(f"no Python at {self.python}: build the plugin's environment (docs/lerobot.md)")
            self._errors = tempfile.TemporaryFile()
            env = {**os.environ, "HF_HUB_OFFLINE": "1"}
            command = [self.python, "-m", "lerobot_policy_tar.cli", "serve", self.checkpoint]
            self._process = subprocess.Popen(
                [*command, f"--threads={self.threads}"],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                stderr=self._errors,
                env=env,
            )
            hello = _read_frame(self._process.stdout)
            if hello is None:
                raise RuntimeError(self._server_error())
            self.sizes = tuple(int(v) for v in hello)
        return self.sizes

    def close(self) -> None:
        """End the server (it exits at EOF)."""
        if self._process is not None:
            self._process.stdin.close()
            self._process.wait(timeout=30)
            self._process.stdout.close()
            self._errors.close()
            self._process = self._errors = None

    def __del__(self):
        try:
            self.close()
        except Exception:  # interpreter shutdown: the server still exits at EOF
            pass

    def predict_chunk(self, history: torch.Tensor, history_valid: torch.Tensor, task_id: torch.Tensor) -> torch.Tensor:
        """The chunks ``[N, H, A]`` for the current observations ``history[:, -1]`` ``[N, 39]`` and their tasks."""
        dims = self.start()[0]
        obs = history[:, -1].detach().to("cpu", torch.float32).numpy()
        if obs.shape[1] != dims:
            raise ValueError(
                f"the checkpoint's policy reads {dims} observation values; the evaluator gives {obs.shape[1]}"
            )
        texts = np.array([task_text(int(i)) for i in task_id.reshape(-1).tolist()])
        try:
            _write_frame(self._process.stdin, obs)
            _write_frame(self._process.stdin, texts)
            self._process.stdin.flush()
        except BrokenPipeError:
            raise RuntimeError(self._server_error()) from None
        chunk = _read_frame(self._process.stdout)
        if chunk is None:
            raise RuntimeError(self._server_error())
        return torch.from_numpy(chunk)


def actor_for(model: LeRobotChunks) -> ChunkedActor:
    """``model``'s chunks executed as tar-rl's ``act`` head executes its own: temporal ensembling, one
    observation step, actions clipped to [-1, 1]."""
    _, horizon, _ = model.start()
    return ChunkedActor(model, horizon=horizon, history=1, execution="ensemble", ensemble_decay=ENSEMBLE_DECAY)


def execution_of(actor: ChunkedActor) -> dict:
    """How ``actor`` executes chunks, as ``summary.json`` records it."""
    return {"execution": actor.execution, "ensemble_decay": actor.ensemble_decay, "chunk_horizon": actor.horizon}


def training_step(checkpoint: Path) -> int | None:
    """The training step of a ``lerobot-train`` checkpoint (``checkpoints/<step>/training_state``), if known."""
    folder = checkpoint if (checkpoint / "training_state").is_dir() else checkpoint.parent
    file = folder / "training_state" / "training_step.json"
    try:
        return int(json.loads(file.read_text())["step"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def _portable(path: Path) -> str:
    try:
        return portable_path(str(path.resolve()), REPO)
    except ValueError:
        return str(path)


def evaluate_lerobot(
    actor: TensorDictModuleBase,
    *,
    checkpoint: Path,
    tasks: Sequence[str],
    rollouts: int,
    seed: int,
    horizon: int,
    workers: int | None,
    out: Path,
    execution: dict,
    progress: bool = True,
) -> pd.DataFrame:
    """Roll ``actor`` (a :func:`actor_for`) out with tar-rl's evaluator; write ``eval_rollouts.csv`` and
    ``summary.json`` into ``out`` (``execution``: how the actor executes chunks, recorded in the summary)."""
    check_writable(out)
    step = training_step(checkpoint)
    started = time.perf_counter()
    rows = evaluate(actor, tasks, rollouts, seed, horizon, workers=workers, progress=progress)
    seconds = time.perf_counter() - started
    write_csv_atomic(rows.assign(step=step if step is not None else 0), out / ROLLOUTS_FILE)
    table = summarize(rows)
    config_file = checkpoint if (checkpoint / "config.json").is_file() else checkpoint / "pretrained_model"
    policy = json.loads((config_file / "config.json").read_text()).get("type")
    summary = {
        "run_name": out.name,
        "policy": policy,
        "checkpoint": _portable(checkpoint),
        "steps": step,
        "finished": True,
        "final": [
            {**rec, "neps": json_metric(rec["neps"])} for rec in table[table["level"] != "task"].to_dict("records")
        ],
        "final_eval_seconds": seconds,
        "eval": {"tasks": list(tasks), "rollouts": rollouts, "seed": seed, "horizon": horizon, "workers": workers},
        "execution": execution,
        "git_commit": git_commit(),
        "machine": machine(),
        "versions": {"torch": torch.__version__},
    }
    write_json_atomic(summary, out / SUMMARY_FILE)
    return rows


# -- The pilot's commands ------------------------------------------------------------------------------------

#: R4's settings (benchmarks/studies/regimes.py, ``chunked`` and the ``act`` head's defaults, recipes/config.py).
R4_STEPS = 3743  # 20 passes: 20 x 191,624 demonstration steps / (64 x 16)
R4_SEGMENTS, R4_SLICE = 64, 16
R4_PAIRS = R4_SEGMENTS * R4_SLICE  # (observation, chunk) pairs per step
TAR_START, TAR_RAMP = round(0.2 * R4_STEPS), round(0.3 * R4_STEPS)  # tar-rl's objective.start, .ramp fractions
#: Steps between checkpoints: a run (0.4 to 1.1 hours here) may be stopped by the end of a working session, so it is
#: saved every 2 to 10 minutes and resumed from its last checkpoint (:func:`resume_commands`).
SAVE_EVERY = 250
#: The pair's two runs, in the order they train.
ARMS = ("act", "act_tar")
#: tar-rl's ``act`` head at its defaults in LeRobot's ACT's names: width 64, 2 heads, one layer each, FFN 128,
#: latent 16, pre-norm layers, no dropout, KL weight 10, chunks of data.chunk_horizon = 8, temporal ensembling; the
#: whole observation standardised (``policy.normalize_obs``: LeRobot's ACT leaves the environment state as it is).
ACT_SIZE = (
    "--policy.dim_model=64 --policy.n_heads=2 --policy.dim_feedforward=128 --policy.n_encoder_layers=1 "
    "--policy.n_decoder_layers=1 --policy.n_vae_encoder_layers=1 --policy.latent_dim=16 --policy.pre_norm=true "
    "--policy.dropout=0 --policy.kl_weight=10 --policy.chunk_size=8 --policy.n_action_steps=1 "
    '--policy.temporal_ensemble_coeff=0.01 --policy.normalization_mapping=\'{"VISUAL": "MEAN_STD", '
    '"STATE": "MEAN_STD", "ENV": "MEAN_STD", "ACTION": "MEAN_STD"}\''
)
#: tar-rl's optimiser (recipes/config.py OptimConfig): AdamW 1e-3, weight decay 1e-4, 200 warm-up steps, cosine to
#: 0.1 x, gradient norm clipped at 1.
SCHEDULE = (
    "--use_policy_training_preset=false --optimizer.type=adamw --optimizer.lr=1e-3 --optimizer.weight_decay=1e-4 "
    "--optimizer.grad_clip_norm=1.0 --scheduler.type=cosine_decay_with_warmup --scheduler.num_warmup_steps=200 "
    f"--scheduler.num_decay_steps={R4_STEPS} --scheduler.peak_lr=1e-3 --scheduler.decay_lr=1e-4"
)


def pilot_commands(seed: int = 0, root: str = "pilot") -> list[str]:
    """The pilot's command lines, from the repository root (``root``: the folder of its data, runs and results)."""
    train = (
        ".venv-lerobot/bin/lerobot-train --dataset.repo_id=local/metaworld-mt50-r4 "
        f"--dataset.root={root}/lerobot/metaworld-mt50-r4 --policy.device=cpu --policy.push_to_hub=false "
        f"--wandb.enable=false --seed={seed} --steps={R4_STEPS} --save_freq={SAVE_EVERY} --log_freq=100 "
        "--num_workers=2"
    )
    arms = {
        "act": f"--policy.type=act --batch_size={R4_PAIRS}",
        "act_tar": f"--policy.type=act_tar --batch_size={R4_SEGMENTS} --policy.tar.slice_len={R4_SLICE} "
        f"--policy.tar.start={TAR_START} --policy.tar.ramp={TAR_RAMP}",
    }
    lines = [
        'demos=$(.venv/bin/python -c "from tar_rl.collectors.metaworld.dataset import build_dataset; '
        "print(build_dataset('datasets', 'mt50', n_demos=50, seed=0).path)\" | tail -1)",
        f'.venv-lerobot/bin/lerobot-tar export-dataset "$demos" {root}/lerobot/metaworld-mt50-r4',
    ]
    for arm, options in arms.items():
        lines.append(f"{train} {options} {ACT_SIZE} {SCHEDULE} --output_dir={root}/runs/{arm}-seed{seed}")
    for arm in arms:
        lines.append(
            f".venv/bin/python -m benchmarks.lerobot_pilot evaluate "
            f"--checkpoint {root}/runs/{arm}-seed{seed}/checkpoints/last/pretrained_model "
            "--python .venv-lerobot/bin/python --tasks mt50 --rollouts 20 --seed 1000 "
            f"--out {root}/eval/{arm}-seed{seed}"
        )
    return lines


def resume_commands(seed: int = 0, root: str = "pilot") -> list[str]:
    """The command lines that resume each of the pilot's runs from its last checkpoint (LeRobot's ``--resume``: the
    run's own ``train_config.json``, its optimiser, scheduler and step, and its data order)."""
    return [
        ".venv-lerobot/bin/lerobot-train "
        f"--config_path={root}/runs/{arm}-seed{seed}/checkpoints/last/pretrained_model/train_config.json --resume=true"
        for arm in ARMS
    ]


COST = f"""\
Cost, measured by the pair on this machine (2 CPU cores, one run at a time; benchmarks/results/lerobot_pilot/
report.md): `act` trained in 1.10 hours (2.37 s a step in its first segment, 0.97 after it resumed), `act_tar` in
0.44 hours (0.43 s a step; from step 300 its logged waits for data average 0.02 s a step against `act`'s 0.38, its
updates 0.40 s against 0.58); each evaluation (MT50, 20 rollouts per task) took 2.5 to 2.7 minutes on two
workers. The pair took 1.6 hours; a pre-registered study of 8 pairs (seeds 0-7) at these times takes about 13 hours.
One pair reports two success rates; it supports no conclusion about TAR.

A run can outlast a working session here: it saves a checkpoint every {SAVE_EVERY} steps, and a run that stopped
continues from its last one with the lines above. LeRobot's resume continues the run's data order, but its random
draws afterwards differ from an uninterrupted run's (6-step runs resumed at step 4 gave step-5 losses of 28.47 for
`act` and 29.84 for `act_tar`, against 29.10 and 29.65 uninterrupted), so a resumed run is not bit-identical to one
that ran through: the pair records where each run resumed (its checkpoints' steps)."""


def _plan(args) -> int:
    print("\n".join(pilot_commands(args.seed, args.root)))
    print("\n# a run that stopped, resumed from its last checkpoint:")
    print("\n".join(resume_commands(args.seed, args.root)))
    print()
    print(COST)
    return 0


def _evaluate(args) -> int:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    checkpoint = Path(args.checkpoint)
    model = LeRobotChunks(args.python, checkpoint, threads=args.threads)
    try:
        actor = actor_for(model)
        rows = evaluate_lerobot(
            actor,
            checkpoint=checkpoint,
            tasks=args.tasks,
            rollouts=args.rollouts,
            seed=args.seed,
            horizon=args.horizon,
            workers=args.workers,
            out=out,
            execution=execution_of(actor),
        )
    except (RuntimeError, FileNotFoundError, ValueError) as error:
        print(f"lerobot_pilot evaluate: {error}", file=sys.stderr)
        return 1
    finally:
        model.close()
    print(f"{checkpoint}: {args.rollouts} rollouts per task, seed {args.seed}; rollouts and summary in {out}")
    print_table(summarize(rows))
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.lerobot_pilot", description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)
    ev = commands.add_parser("evaluate", help="a LeRobot checkpoint on tar-rl's MetaWorld evaluator")
    ev.add_argument("--checkpoint", required=True, help="LeRobot's pretrained_model folder (or the folder above)")
    ev.add_argument("--python", required=True, help="the Python of LeRobot's environment (.venv-lerobot/bin/python)")
    ev.add_argument("--tasks", nargs="+", default=["mt50"], help="MetaWorld tasks or groups (default mt50)")
    ev.add_argument("--rollouts", type=int, default=20, help="rollouts per task (default 20)")
    ev.add_argument("--seed", type=int, default=1000, help="the evaluation variations' base seed (default 1000)")
    ev.add_argument("--horizon", type=int, default=MAX_HORIZON, help=f"steps per rollout (default {MAX_HORIZON})")
    ev.add_argument("--workers", type=int, help="evaluation processes, each with its server (default every core)")
    ev.add_argument("--threads", type=int, default=1, help="torch threads of each server (default 1)")
    ev.add_argument("--out", required=True, help="the folder of eval_rollouts.csv and summary.json")
    plan = commands.add_parser("plan", help="print the pilot's commands and their cost (runs nothing)")
    plan.add_argument("--seed", type=int, default=0, help="the pair's training seed (default 0)")
    plan.add_argument("--root", default="pilot", help="the folder of the pilot's data, runs and evaluations")
    args = parser.parse_args(argv)
    return _evaluate(args) if args.command == "evaluate" else _plan(args)


if __name__ == "__main__":
    sys.exit(main())
