"""Run integrity: one writer per run folder, a full disk, and how the commands report what a user meets.

Tiny jobs on the shared tiny dataset (``recipe_helpers.tiny``). The two-process tests start a second
Python process that holds a run folder inside ``train`` (its ``Trainer.run`` waits for its standard
input to close); every wait on another process has a deadline, so a hang fails the test instead of
stalling CI.
"""

from __future__ import annotations

import json
import os
import select
import shutil
import signal
import subprocess
import sys

import numpy as np
import pytest
from disk_helpers import FullDisk
from recipe_helpers import tiny, train_command, wait_for_checkpoint

from tar_rl import io
from tar_rl.cli import main
from tar_rl.data import SegmentSampler
from tar_rl.errors import DEBUG_ENV
from tar_rl.recipes import ConfigError, TrainingError, train
from tar_rl.runlock import LOCK_FILE, RunFolderBusy, run_lock
from tar_rl.runs import CHECKPOINT, load_checkpoint

DEADLINE = 180  # seconds for another process to start, import torch and reach its training loop

# A process that runs `train(config)` and waits at the start of its training loop until its stdin closes.
HOLD = """
import json, sys
from tar_rl.recipes import offline_bc

original = offline_bc.Trainer.run

def run(self):
    print("running", flush=True)
    sys.stdin.read()
    return original(self)

offline_bc.Trainer.run = run
offline_bc.train(json.loads(sys.argv[1]))
"""


# `python -m tar_rl ARGS` with Python's KeyboardInterrupt handler installed.
INTERRUPTIBLE = """
import signal, sys
signal.signal(signal.SIGINT, signal.default_int_handler)
from tar_rl.cli import main
sys.exit(main(sys.argv[1:]))
"""


def _readline(proc: subprocess.Popen, deadline: float = DEADLINE) -> str:
    """The next line the process prints, or a failure once ``deadline`` seconds pass without one."""
    ready, _, _ = select.select([proc.stdout], [], [], deadline)
    if not ready:
        proc.kill()
        pytest.fail(f"no output from process {proc.pid} within {deadline} s")
    return proc.stdout.readline()


def _holding(config: dict, stderr) -> subprocess.Popen:
    """Another process inside `train(config)`, holding its run folder (it said "running")."""
    proc = subprocess.Popen(
        [sys.executable, "-c", HOLD, json.dumps(config)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=stderr,
        text=True,
    )
    line = _readline(proc)
    while line and line.strip() != "running":  # what train printed before its loop
        line = _readline(proc)
    assert line.strip() == "running", f"process {proc.pid} ended before training"
    return proc


def _end(proc: subprocess.Popen) -> int:
    """Its exit status (killed if it has not ended within a minute); its pipes closed."""
    try:
        return proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=30)
        for pipe in (proc.stdin, proc.stdout):
            if pipe is not None and not pipe.closed:
                pipe.close()


@pytest.mark.slow  # starts a second Python process (imports torch): ~5 s
def test_a_second_process_on_a_run_folder_is_refused_until_the_first_ends(tmp_path, data_root, capsys):
    config = tiny(tmp_path, data_root, f"run_dir={tmp_path / 'run'}")
    log = (tmp_path / "holder.err").open("w")
    holder = _holding(config, log)
    try:
        with pytest.raises(RunFolderBusy) as info:
            train(config)
        message = str(info.value)
        assert message.startswith(f"{tmp_path / 'run'} is in use by process {holder.pid} on ")
        assert "(started 20" in message and "choose another run_dir" in message and "\n" not in message
        other = tiny(tmp_path, data_root, f"run_dir={tmp_path / 'run'}", "objective=uniform")
        with pytest.raises(RunFolderBusy, match=f"process {holder.pid}"):
            train(other)  # another config too: the folder is in use
    finally:
        holder.stdin.close()  # it trains, finishes and exits
        code = _end(holder)
        log.close()
    assert code == 0, (tmp_path / "holder.err").read_text()
    assert json.loads((tmp_path / "run" / "summary.json").read_text())["finished"]
    capsys.readouterr()
    assert train(config) == tmp_path / "run"  # released on exit: the folder is free again
    assert "finished already" in capsys.readouterr().out


@pytest.mark.slow  # starts a second Python process (imports torch): ~5 s
def test_the_lock_of_a_killed_process_is_taken_over(tmp_path, data_root, capsys):
    config = tiny(tmp_path, data_root, f"run_dir={tmp_path / 'run'}")
    holder = _holding(config, subprocess.DEVNULL)
    holder.kill()  # SIGKILL: no clean-up runs; the OS releases its lock
    _end(holder)
    assert json.loads((tmp_path / "run" / LOCK_FILE).read_text())["pid"] == holder.pid  # its note is left
    capsys.readouterr()
    assert train(config) == tmp_path / "run"
    out = capsys.readouterr().out
    assert f"taking over the lock left by process {holder.pid}" in out and "no longer running" in out
    assert (tmp_path / "run" / LOCK_FILE).read_text() == ""  # released at the end of the run


def test_the_lock_is_released_when_the_block_raises(tmp_path):
    with pytest.raises(ZeroDivisionError), run_lock(tmp_path) as me:
        assert json.loads((tmp_path / LOCK_FILE).read_text()) == me
        assert me["pid"] == os.getpid()
        with pytest.raises(RunFolderBusy, match=f"process {os.getpid()}"), run_lock(tmp_path):
            pass  # a second holder, even in the same process, is refused
        1 / 0  # noqa: B018
    with run_lock(tmp_path):  # free again
        pass


class _Crash(Exception):
    pass


def _crash_at_sample(monkeypatch, n: int) -> None:
    calls = {"n": 0}
    original = SegmentSampler.sample

    def sample(self):
        calls["n"] += 1
        if calls["n"] == n:
            raise _Crash
        return original(self)

    monkeypatch.setattr(SegmentSampler, "sample", sample)


def test_a_started_run_folder_refuses_another_config_before_its_first_checkpoint(tmp_path, data_root, monkeypatch):
    run_dir = tmp_path / "run"
    config = tiny(tmp_path, data_root, f"run_dir={run_dir}")
    _crash_at_sample(monkeypatch, 1)  # stopped in its first step: config.yaml, no checkpoint
    with pytest.raises(_Crash):
        train(config)
    assert (run_dir / "config.yaml").exists() and not (run_dir / CHECKPOINT).exists()
    monkeypatch.undo()
    other = tiny(tmp_path, data_root, f"run_dir={run_dir}", "objective.gamma=2")
    with pytest.raises(ConfigError, match=r"holds a run with other settings \(objective\.gamma: 1\.0 -> 2\.0\)"):
        train(other)
    # The same config starts: its config.yaml reads back as the same run.
    assert train(config) == run_dir
    assert load_checkpoint(run_dir)["step"] == 30


@pytest.mark.parametrize(
    ("target", "nth", "kept"),
    [
        (CHECKPOINT, 2, 10),  # the checkpoint of step 20
        ("metrics.csv", 2, 10),  # written right after the checkpoint of step 10
        ("summary.json", 1, 30),  # after the final checkpoint
    ],
)
def test_a_full_disk_stops_with_one_line_and_the_last_checkpoint_loadable(
    tmp_path, data_root, monkeypatch, target, nth, kept
):
    run_dir = tmp_path / "run"
    config = tiny(tmp_path, data_root, f"run_dir={run_dir}")
    real_open = io._open
    writes = {"n": 0}

    def open_temp(fd, binary, path):
        f = real_open(fd, binary, path)
        if path.name == target:
            writes["n"] += 1
            if writes["n"] == nth:
                return FullDisk(f)
        return f

    monkeypatch.setattr(io, "_open", open_temp)
    with pytest.raises(TrainingError) as info:
        train(config)
    assert str(info.value) == (
        f"no space left on device while writing {run_dir / target} (disk full); the last good checkpoint "
        f"(step {kept}) is kept in {run_dir / CHECKPOINT}: free some space, then run the same command to resume"
    )
    assert load_checkpoint(run_dir)["step"] == kept
    assert not [p for p in run_dir.iterdir() if p.name.endswith(".tmp")]
    monkeypatch.undo()
    assert train(config) == run_dir  # space again: it resumes and finishes
    assert json.loads((run_dir / "summary.json").read_text())["finished"]


# -- What the commands print -------------------------------------------------------------------


@pytest.mark.slow  # a `tar-rl train` process (imports torch): ~5 s
def test_a_corrupt_checkpoint_is_one_line_naming_the_file_and_debug_shows_the_traceback(
    tmp_path, data_root, monkeypatch
):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / CHECKPOINT).write_bytes(b"not a checkpoint")
    out = subprocess.run(
        train_command(tmp_path, data_root, f"run_dir={run_dir}"), capture_output=True, text=True, timeout=DEADLINE
    )
    assert out.returncode == 1
    assert "Traceback" not in out.stderr
    (line,) = out.stderr.strip().splitlines()
    assert line.startswith(f"tar-rl train: {run_dir / CHECKPOINT} is not a readable tar-rl checkpoint: ")
    assert line.endswith(
        f"; remove {run_dir / CHECKPOINT} to start the run again from step 0, or choose another run_dir"
    )
    # --debug, in this process: the error itself leaves the command (Python prints its traceback).
    monkeypatch.setenv(DEBUG_ENV, "0")  # restored afterwards (--debug sets it to 1)
    with pytest.raises(ConfigError, match="is not a readable tar-rl checkpoint"):
        main([*train_command(tmp_path, data_root, f"run_dir={run_dir}")[3:], "--debug"])


@pytest.mark.slow  # a `tar-rl train` process (imports torch, trains until interrupted): ~10 s
def test_ctrl_c_prints_one_line_with_the_step_and_how_to_resume(tmp_path, data_root):
    args = train_command(tmp_path, data_root, "optim.steps=1000000", "logging.every=10", "logging.checkpoint_every=10")
    # Python's own Ctrl-C handling in the child, even where this process was started with SIGINT ignored
    # (a background job of a shell), which the child would inherit.
    args[1:3] = ["-c", INTERRUPTIBLE]
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        wait_for_checkpoint(proc, tmp_path / "runs", DEADLINE)  # training: it wrote a checkpoint
        os.killpg(proc.pid, signal.SIGINT)  # what Ctrl-C in a terminal does: the whole process group
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate(timeout=30)
    assert proc.returncode == 130
    assert "Traceback" not in err
    (run_dir,) = list((tmp_path / "runs").iterdir())
    last = err.strip().splitlines()[-1]
    assert last.startswith("tar-rl train: interrupted at step ")
    step = load_checkpoint(run_dir)["step"]
    assert last.endswith(
        f"; the last good checkpoint (step {step}) is kept in {run_dir / CHECKPOINT}: run the same command to resume"
    )
    assert step <= int(last.split("interrupted at step ")[1].split()[0]) < 1_000_000


def test_a_run_resumes_only_on_the_data_it_trained_on(tmp_path, monkeypatch):
    from data_helpers import robomimic_file
    from recipe_helpers import compose_config

    from tar_rl.data import content_digest
    from tar_rl.importers import import_robomimic

    source = robomimic_file(tmp_path / "lift.hdf5")
    ds = import_robomimic(source, "state", out=tmp_path / "data", verbose=False)
    run_dir = tmp_path / "run"
    config = compose_config(
        f"data.path={ds.path}",
        "data.batch_segments=4",
        "data.slice_len=3",
        "policy.hidden=[16]",
        "optim.steps=8",
        "optim.warmup=1",
        "logging.every=2",
        "logging.checkpoint_every=4",
        "logging.progress=false",
        "logging.record_weights_at=[]",
        "eval.rollouts=0",
        f"run_dir={run_dir}",
    )
    _crash_at_sample(monkeypatch, 6)  # stopped in step 6, after the checkpoint of step 4
    with pytest.raises(_Crash):
        train(config)
    monkeypatch.undo()
    # The dataset's content changes under the run: one action value (whoever changed it recorded its digest).
    actions = ds.path / "buffer" / "storage" / "action.memmap"
    values = np.fromfile(actions, dtype=np.float32)
    values[0] = 0.5 if values[0] != 0.5 else -0.5
    values.tofile(actions)
    (ds.path / "digest.json").write_text(json.dumps(content_digest(ds.path)))
    with pytest.raises(ConfigError, match=rf"{run_dir}: the dataset {ds.path} differs from the data the run trained"):
        train(config)
    assert load_checkpoint(run_dir)["step"] == 4  # nothing more was trained
    # The same data imported again is the same data: the run resumes and finishes.
    shutil.rmtree(ds.path)
    again = import_robomimic(source, "state", out=tmp_path / "data", verbose=False)
    assert again.path == ds.path
    assert train(config) == run_dir
    state = load_checkpoint(run_dir)
    assert state["step"] == 8 and state["data_digest"] == again.digest == ds.digest
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["data"] == {"path": str(ds.path), "digest": ds.digest}
