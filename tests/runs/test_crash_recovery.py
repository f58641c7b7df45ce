"""What a crash, a signal or an unwritable folder leaves: nothing counted twice, nothing done lost, one line said.

Tiny jobs on the shared tiny dataset (``recipe_helpers.tiny``: reach, 30 steps, one 20-step rollout per
evaluation) and synthetic run folders (``run_helpers.write_run``). The expected counts follow from those
settings: one task with one rollout gives one evaluation row, and the groups ``easy`` and ``overall`` give
three metrics each (success, fast20, neps).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess

import pandas as pd
import pytest
import torch
import yaml
from disk_helpers import read_only
from recipe_helpers import tiny, train_command, wait_for_checkpoint
from run_helpers import ROLLOUTS, write_run

from tar_rl import io, report
from tar_rl.cli import main
from tar_rl.objectives import TARLoss
from tar_rl.recipes import ConfigError, offline_bc, train
from tar_rl.runs import CHECKPOINT, CHECKPOINT_FORMAT, load_checkpoint, save_checkpoint

DEADLINE = 180  # seconds for a `tar-rl train` process to start, import torch and write its first checkpoint


class _Crash(Exception):
    pass


def _count_evaluations(monkeypatch) -> list[int]:
    """The steps :meth:`Trainer.evaluate` is called at, from now on."""
    steps: list[int] = []
    real = offline_bc.Trainer.evaluate

    def evaluate(self, step):
        steps.append(step)
        return real(self, step)

    monkeypatch.setattr(offline_bc.Trainer, "evaluate", evaluate)
    return steps


@pytest.mark.parametrize("summary_in_checkpoint", [True, False])
def test_a_crash_before_the_summary_counts_the_final_evaluation_once(
    tmp_path, data_root, monkeypatch, summary_in_checkpoint
):
    run_dir = tmp_path / "run"
    config = tiny(tmp_path, data_root, f"run_dir={run_dir}")
    real_open = io._open

    def open_temp(fd, binary, path):  # the job dies where summary.json is written, after the final checkpoint
        if path.name == "summary.json":
            raise _Crash
        return real_open(fd, binary, path)

    monkeypatch.setattr(io, "_open", open_temp)
    with pytest.raises(_Crash):
        train(config)
    monkeypatch.undo()
    assert not (run_dir / "summary.json").exists() and load_checkpoint(run_dir)["finished"]
    if not summary_in_checkpoint:  # a finished checkpoint as earlier versions wrote it: evaluated again
        state = load_checkpoint(run_dir)
        state.pop("summary", None)
        del state["format"]
        save_checkpoint(state, run_dir)
    evaluations = _count_evaluations(monkeypatch)
    assert train(config) == run_dir
    assert evaluations == ([] if summary_in_checkpoint else [30])
    rollouts = pd.read_csv(run_dir / "eval_rollouts.csv")
    assert rollouts["step"].tolist() == [30]  # one task, one rollout: one row, once
    metrics = pd.read_csv(run_dir / "metrics.csv")
    final = metrics[(metrics.phase == "eval") & (metrics.step == 30)]
    assert sorted(final["name"]) == sorted(
        f"{m}/{g}" for m in ("success", "fast20", "neps") for g in ("easy", "overall")
    )
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["finished"] and summary["steps"] == 30
    run = report.load_run(run_dir)
    assert run.finished and int(run.final.set_index("name").loc["overall", "n_rollouts"]) == 1


def test_a_run_whose_every_step_is_skipped_finishes_and_keeps_its_checkpoint(tmp_path, data_root, monkeypatch):
    # Every per-step loss is NaN, in training and in the recordings after it: every step is skipped.
    real = TARLoss._step_losses
    monkeypatch.setattr(TARLoss, "_step_losses", lambda *args: real(*args) * float("nan"))
    config = tiny(
        tmp_path,
        data_root,
        "optim.skip_nonfinite=1000",
        "logging.checkpoint_every=1000",  # no checkpoint inside the 30 steps: the last step's is the only one
        "logging.record_weights_at=[-1]",
    )
    run_dir = train(config)
    state = load_checkpoint(run_dir)
    assert state["step"] == 30 and state["finished"] and state["skipped"] == 30

    def no_nan(text):
        raise AssertionError(f"summary.json holds {text}, which is not JSON")

    summary = json.loads((run_dir / "summary.json").read_text(), parse_constant=no_nan)
    assert summary["nonfinite_steps_skipped"] == 30
    assert summary["fit"]["train_loss"] is None  # the mean of NaN losses
    weights = pd.read_csv(run_dir / "weights.csv")
    assert len(weights) > 0 and weights["weight"].isna().all()


@pytest.fixture(scope="module")
def trained(tmp_path_factory, data_root):
    """A finished tiny run."""
    tmp = tmp_path_factory.mktemp("trained")
    return train(tiny(tmp, data_root, f"run_dir={tmp / 'run'}"))


def test_eval_into_a_read_only_run_folder_refuses_before_any_rollout(trained, monkeypatch):
    def no_rollouts(*args, **kwargs):
        raise AssertionError("the rollouts ran although their file cannot be written")

    monkeypatch.setattr("tar_rl.recipes.evaluate.make_evaluator", no_rollouts)
    with read_only(trained), pytest.raises(SystemExit) as info:
        main(["eval", str(trained), "--rollouts", "1", "--horizon", "5", "--workers", "1", "--no-progress"])
    message = str(info.value.code)
    target = trained / "eval-1000.csv"
    assert message.startswith(f"tar-rl eval: cannot write the rollouts to {target} (")
    assert message.endswith("; choose a writable file with --out") and "\n" not in message
    assert not target.exists()


def test_a_checkpoint_with_its_format_tag_and_nothing_else_is_one_line(tmp_path, data_root):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    torch.save({"format": CHECKPOINT_FORMAT}, run_dir / CHECKPOINT)
    with pytest.raises(ConfigError) as info:
        train(tiny(tmp_path, data_root, f"run_dir={run_dir}"))
    message = str(info.value)
    assert message.startswith(
        f"{run_dir / CHECKPOINT} is a tar-rl checkpoint of format {CHECKPOINT_FORMAT} that lacks ["
    )
    assert message.endswith(
        f"; remove {run_dir / CHECKPOINT} to start the run again from step 0, or choose another run_dir"
    )
    with pytest.raises(SystemExit) as info:
        main(["eval", str(run_dir), "--no-progress"])
    assert str(info.value.code).startswith(f"tar-rl eval: {run_dir / CHECKPOINT} is a tar-rl checkpoint of format")
    assert "\n" not in str(info.value.code)


@pytest.mark.slow  # a `tar-rl train` process (imports torch, trains until terminated): ~10 s
def test_sigterm_says_where_the_run_stopped_and_how_to_resume(tmp_path, data_root):
    args = train_command(tmp_path, data_root, "optim.steps=1000000", "logging.every=10", "logging.checkpoint_every=10")
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        wait_for_checkpoint(proc, tmp_path / "runs", DEADLINE)  # training: it wrote a checkpoint
        os.kill(proc.pid, signal.SIGTERM)  # what a scheduler ending the job sends
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate(timeout=30)
    assert proc.returncode == 143, err
    assert "Traceback" not in err
    (run_dir,) = list((tmp_path / "runs").iterdir())
    last = err.strip().splitlines()[-1]
    step = load_checkpoint(run_dir)["step"]
    assert last.startswith("tar-rl train: terminated (SIGTERM) at step ")
    assert last.endswith(
        f"; the last good checkpoint (step {step}) is kept in {run_dir / CHECKPOINT}: run the same command to resume"
    )


# -- tar-rl report ------------------------------------------------------------------------------


def test_report_into_a_read_only_folder_is_one_line(tmp_path):
    run = write_run(tmp_path / "runs", "uniform", 0, ROLLOUTS[("uniform", 0)])
    out = tmp_path / "out"
    out.mkdir()
    with read_only(out), pytest.raises(SystemExit) as info:
        report.main([str(run), "--out", str(out)])
    message = str(info.value.code)
    assert message.startswith(f"tar-rl report: cannot write to {out} (")
    assert message.endswith("; choose a writable folder with --out") and "\n" not in message
    assert list(out.iterdir()) == []


def test_report_names_a_malformed_config_in_one_line(tmp_path):
    run = write_run(tmp_path / "runs", "uniform", 0, ROLLOUTS[("uniform", 0)])
    (run / "config.yaml").write_text("objective:\n  name: [uniform\nseed: 0\n")  # the list is never closed
    with pytest.raises(SystemExit) as info:
        report.main([str(run), "--out", str(tmp_path / "out")])
    message = str(info.value.code)
    assert message.startswith(f"tar-rl report: {run / 'config.yaml'}: cannot read the run's config: not valid YAML (")
    assert "line 3" in message and "\n" not in message


def test_report_lists_a_run_trained_without_evaluation_as_finished(tmp_path, capsys):
    root = tmp_path / "runs"
    write_run(root, "uniform", 0, ROLLOUTS[("uniform", 0)])
    unevaluated = write_run(root, "tar", 0, {})  # no evaluation rows
    config = yaml.safe_load((unevaluated / "config.yaml").read_text())
    config["eval"]["rollouts"] = 0
    (unevaluated / "config.yaml").write_text(yaml.safe_dump(config))
    run = report.load_run(unevaluated)
    assert run.not_evaluated and not run.finished
    assert report.main([str(root), "--out", str(tmp_path / "out")]) == 0
    out = capsys.readouterr().out
    assert "unfinished" not in out
    line = next(line for line in out.splitlines() if line.strip().startswith("tar-mlp-s0-deadbeef "))
    assert "not evaluated" in line
    assert (
        f"note: tar-mlp-s0-deadbeef ({unevaluated}) is left out of the comparison: finished without evaluation" in out
    )
    # Alone, it is still not an unfinished run: nothing to compare, and no failure.
    assert report.main([str(unevaluated), "--out", str(tmp_path / "out")]) == 0
    assert "nothing to compare: no run has an evaluation" in capsys.readouterr().out
