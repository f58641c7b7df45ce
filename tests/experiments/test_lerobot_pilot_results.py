"""``benchmarks/lerobot_pilot_results.py``: the first LeRobot pair's training logs read into segments, its runs
written under the results with paths relative to the repository, and its table; expected values by hand."""

from __future__ import annotations

import gzip
import json

import pandas as pd
import pytest

from benchmarks import lerobot_pilot_results as results

#: A log as ``lerobot-train`` appends it: a run started, stopped after its checkpoint at step 4 (step 5 is lost),
#: resumed and finished at step 8 (save every 4 steps, log every 2). Progress bars share lines, split by ``\r``.
LOG = (
    "INFO 2026-12-06 10:00:00 ot_train.py:272 {'batch_size': 1024,\n"
    "INFO 2026-12-06 10:00:05 ot_train.py:443 dataset.num_episodes=2500\n"
    "Training:   0%|          | 0/8 [00:00<?, ?step/s]"
    "INFO 2026-12-06 10:00:10 ot_train.py:597 Start offline training on a fixed dataset, with batch size: 1024\n"
    "Training:  25%|##   | 2/8 [00:20<01:00, 10.0s/step]"
    "INFO 2026-12-06 10:00:30 ot_train.py:641 step:2 smpl:2K ep:0 epch:0.01 loss:9.5 lr:1.0e-04 l1_loss:0.5\n"
    "Training:  50%|#### | 4/8 [00:40<00:40, 10.0s/step]\r"
    "INFO 2026-12-06 10:00:50 ot_train.py:641 step:4 smpl:4K ep:0 epch:0.02 loss:4.0 lr:2.0e-04 l1_loss:0.25\n"
    "INFO 2026-12-06 10:00:52 ot_train.py:687 Checkpoint policy after step 4\r"
    "Training:  62%|#####| 5/8 [00:55<00:30, 10.0s/step]\n"
    "INFO 2026-12-06 11:00:00 ot_train.py:272 {'batch_size': 1024,\n"
    "INFO 2026-12-06 11:00:03 ot_train.py:489 Resuming data order at epoch 0, sample 4096\n"
    "INFO 2026-12-06 11:00:04 ot_train.py:597 Start offline training on a fixed dataset, with batch size: 1024\n"
    "INFO 2026-12-06 11:00:14 ot_train.py:641 step:6 smpl:6K ep:0 epch:0.03 loss:2.0 lr:3.0e-04 l1_loss:0.125\n"
    "INFO 2026-12-06 11:00:24 ot_train.py:641 step:8 smpl:8K ep:0 epch:0.04 loss:1.0 lr:1.0e-04 l1_loss:0.0625\n"
    "INFO 2026-12-06 11:00:25 ot_train.py:687 Checkpoint policy after step 8\n"
)


def test_a_resumed_runs_log_is_read_into_its_segments_and_step_lines():
    record, lines = results.training_record("act", LOG, log_freq=2, steps=8)
    # segment 1: 10:00:10 -> its checkpoint at step 4, 10:00:52 (42 s, 10.5 s a step); step 5's work is lost.
    # segment 2: from step 4 (the checkpoint it resumed) 11:00:04 -> step 8's checkpoint 11:00:25 (21 s, 5.25 s a step)
    assert record == {
        "arm": "act",
        "steps": 8,
        "finished": True,
        "resumed_at": [4],
        "train_seconds": 63.0,
        "segments": [
            {"started": "2026-12-06 10:00:10", "from_step": 0, "to_checkpoint": 4, "kept_seconds": 42.0,
             "seconds_per_step": 10.5},
            {"started": "2026-12-06 11:00:04", "from_step": 4, "to_checkpoint": 8, "kept_seconds": 21.0,
             "seconds_per_step": 5.25},
        ],
    }  # fmt: skip
    assert lines["step"].tolist() == [2, 4, 6, 8]
    assert lines["loss"].astype(float).tolist() == [9.5, 4.0, 2.0, 1.0]
    assert lines["l1_loss"].astype(float).tolist() == [0.5, 0.25, 0.125, 0.0625]
    assert lines["time"].tolist()[2] == "2026-12-06 11:00:14"


def test_a_run_stopped_before_its_last_step_is_not_finished_and_a_log_without_training_is_refused():
    stopped = LOG.split("INFO 2026-12-06 11:00:00")[0]
    record, _ = results.training_record("act_tar", stopped, 2, steps=8)
    assert not record["finished"] and record["resumed_at"] == [] and record["train_seconds"] == 42.0
    with pytest.raises(ValueError, match="act_tar: its log holds no 'Start offline training' line"):
        results.training_record("act_tar", "INFO 2026-12-06 10:00:00 ot_train.py:272 {'batch_size': 64,\n", 2)


def _steps(*logged: str) -> str:
    """A segment's log whose step lines log ``logged``."""
    lines = [f"INFO 2026-12-06 10:00:00 ot_train.py:597 {results.START}\n"]
    lines += [f"INFO 2026-12-06 10:0{i + 1}:00 ot_train.py:641 step:{s} loss:1.0\n" for i, s in enumerate(logged)]
    return "".join(lines)


def test_steps_logged_rounded_past_999_are_counted_exactly_and_a_line_out_of_place_is_refused():
    # LeRobot logs 1,000 as 1K and 1,500 as 2K (0 decimals): the counted steps are 500, 1000, 1500, 2000
    _, lines = results.training_record("act", _steps("500", "1K", "2K", "2K"), log_freq=500)
    assert lines["step"].tolist() == [500, 1000, 1500, 2000]
    # resumed from a checkpoint at step 1,250: the next lines are at 1,500 and 2,000
    saved = "INFO 2026-12-06 10:09:00 ot_train.py:687 Checkpoint policy after step 1250\n"
    resumed = results.training_segments(_steps("500", "1K") + saved + _steps("2K", "2K"), 500)[1]
    assert resumed["from_step"] == 1250 and [line["step"] for line in resumed["steps"]] == [1500, 2000]
    # one line missing: the third counts 1,500 where 3K (2,500 to 3,499) was logged
    with pytest.raises(ValueError, match=r"^act: the step line at 2026-12-06 10:03:00 logs step 3K, where counting "
                                         r"from step 0 every 500 gives 1500$"):  # fmt: skip
        results.training_record("act", _steps("500", "1K", "3K"), log_freq=500)
    with pytest.raises(ValueError, match="logs step 600, where counting from step 0 every 500 gives 500"):
        results.training_record("act", _steps("600"), log_freq=500)


def _pilot(tmp_path, arm="act", summary=None):
    root = tmp_path / "pilot-root"
    config = root / "runs" / f"{arm}-seed0" / "checkpoints" / "last" / "pretrained_model" / "train_config.json"
    config.parent.mkdir(parents=True)
    config.write_text(
        json.dumps(
            {"dataset": {"root": f"{root}/lerobot/mt50"}, "output_dir": f"{root}/runs/x", "log_freq": 2, "steps": 3743}
        )
    )
    (root / f"{arm}.log").write_text(LOG)
    if summary is not None:
        evaluation = root / "eval" / f"{arm}-seed0"
        evaluation.mkdir(parents=True)
        (evaluation / "summary.json").write_text(json.dumps({**summary, "checkpoint": f"{root}/runs/x/last"}))
        (evaluation / "eval_rollouts.csv").write_text("task,rollout,success\nreach-v3,0,1\n")
    return root


def test_record_writes_a_trained_and_evaluated_run_with_paths_relative_to_the_repository(tmp_path):
    root = _pilot(tmp_path, summary={"final": [], "final_eval_seconds": 60.0})
    written = results.record_pilot(root, tmp_path / "out")
    assert written == ["act-seed0: trained to step 8 of 3743", "act-seed0: evaluated"]
    out = tmp_path / "out" / "act-seed0"
    assert json.loads((out / "train_config.json").read_text()) == {
        "dataset": {"root": "pilot/lerobot/mt50"},
        "output_dir": "pilot/runs/x",
        "log_freq": 2,
        "steps": 3743,
    }
    assert json.loads((out / "summary.json").read_text())["checkpoint"] == "pilot/runs/x/last"
    assert gzip.decompress((out / "eval_rollouts.csv.gz").read_bytes()) == b"task,rollout,success\nreach-v3,0,1\n"
    assert json.loads((out / "training.json").read_text())["resumed_at"] == [4]
    assert pd.read_csv(out / "train_log.csv")["step"].tolist() == [2, 4, 6, 8]
    assert not (out / "checkpoints").exists() and sorted(p.name for p in out.iterdir()) == [
        "eval_rollouts.csv.gz", "summary.json", "train_config.json", "train_log.csv", "training.json",
    ]  # fmt: skip


def test_record_refuses_a_path_it_cannot_write_relative_to_the_repository(tmp_path):
    root = _pilot(tmp_path)
    config = next(root.glob("runs/*/checkpoints/last/pretrained_model/train_config.json"))
    config.write_text(json.dumps({"cache": "/nowhere-known/hub", "log_freq": 2, "steps": 3743}))
    with pytest.raises(ValueError, match="cannot write /nowhere-known/hub relative to the repository"):
        results.record_pilot(root, tmp_path / "out")


def _group(name, success, fast20, neps, tasks=50):
    return {"level": "group", "name": name, "n_tasks": tasks, "n_rollouts": 20 * tasks,
            "success": success, "fast20": fast20, "neps": neps}  # fmt: skip


def test_the_report_gives_both_runs_their_times_and_the_cost_of_eight_pairs(tmp_path):
    for arm, success, eval_seconds in (("act", 0.5, 1800.0), ("act_tar", 0.625, 1620.0)):
        folder = tmp_path / f"{arm}-seed0"
        folder.mkdir()
        record, _ = results.training_record(arm, LOG, 2, steps=8)
        record["train_seconds"] = 3600.0 if arm == "act" else 5400.0
        (folder / "training.json").write_text(json.dumps(record))
        final = [_group("easy", success, 0.1, 0.2, 28), {**_group("overall", success, 0.25, 0.375), "level": "overall"}]
        (folder / "summary.json").write_text(json.dumps({"final": final, "final_eval_seconds": eval_seconds}))
    text = results.pilot_report(tmp_path)
    assert "| act-seed0 | 1.00 h | 4 | 10.50, 5.25 | 30.0 min | 50.0 | 25.0 | 37.5 |" in text
    assert "| act_tar-seed0 | 1.50 h | 4 | 10.50, 5.25 | 27.0 min | 62.5 | 25.0 | 37.5 |" in text
    assert "| act_tar-seed0 | easy | 28 | 560 | 62.5 | 10.0 | 20.0 |" in text
    # 3600 + 1800 + 5400 + 1620 = 12,420 s = 3.45 h a pair; 8 pairs: 27.6 h
    assert "The pair took 3.5 hours here" in text and "8 pairs at these times takes 28 hours" in text
    assert "no conclusion" in text


def test_the_report_says_what_is_not_finished(tmp_path):
    (tmp_path / "act-seed0").mkdir()
    record, _ = results.training_record("act", LOG.split("INFO 2026-12-06 11:00:00")[0], 2, steps=8)
    (tmp_path / "act-seed0" / "training.json").write_text(json.dumps(record))
    text = results.pilot_report(tmp_path)
    assert "| act-seed0 | 0.01 h | - | 10.50 | - | - | - | - |" in text
    assert "| act_tar-seed0 | - | - | - | - | - | - | - |" in text
    assert "Not finished: act, act_tar" in text and "hours here" not in text


def test_the_command_line_refuses_a_folder_without_runs_in_one_line(tmp_path, capsys):
    assert results.main(["record", "--root", str(tmp_path), "--out", str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err.strip()
    assert err == f"lerobot_pilot_results record: {tmp_path} holds no runs folder (the plan's --root)"
    assert not (tmp_path / "out").exists()
    assert results.main(["report", "--results", str(tmp_path / "none")]) == 1


def _log_lines(*losses: float, first: int = 100) -> pd.DataFrame:
    return pd.DataFrame(
        {"time": [f"10:0{i}" for i in range(len(losses))], "step": [first + 100 * i for i in range(len(losses))],
         "loss": list(losses), "updt_s": [0.5 + i for i in range(len(losses))], "tar_mix": [0.0] * len(losses)}
    )  # fmt: skip


def test_two_runs_agree_before_a_step_in_every_value_but_the_timings():
    tar, uniform = _log_lines(9.0, 4.0, 2.0, 1.5), _log_lines(9.0, 4.0, 2.0, 1.0)
    uniform["time"], uniform["updt_s"] = "11:00", 0.25  # timings differ between equal runs
    assert results.same_before(tar, uniform, 400) == (True, 3)  # steps 100-300; step 400 differs, not compared
    assert results.same_before(tar, uniform, 401) == (False, 4)
    uniform.loc[0, "tar_mix"] = 0.5
    assert results.same_before(tar, uniform, 400) == (False, 3)
    assert results.same_before(tar, uniform.iloc[:0], 400) == (False, 0)


def test_the_report_sets_the_exploratory_run_beside_the_pair(tmp_path):
    start = results.TAR_START  # 749: the step lines 100-700 are compared
    before = [1.0 + i for i in range(start // 100)]
    for run, success, last_loss in (("act", 0.714, 0.5), ("act_tar", 0.653, 0.4), ("act_tar_uniform", 0.70, 0.3)):
        folder = tmp_path / f"{run}-seed0"
        folder.mkdir()
        record, _ = results.training_record(run, LOG, 2, steps=8)
        (folder / "training.json").write_text(json.dumps(record))
        final = [{**_group("overall", success, 0.25, 0.5), "level": "overall"}]
        (folder / "summary.json").write_text(json.dumps({"final": final, "final_eval_seconds": 3600.0}))
        _log_lines(*before, last_loss).to_csv(folder / "train_log.csv", index=False)
    text = results.pilot_report(tmp_path)
    assert "| act_tar_uniform-seed0 (exploratory) | 0.02 h | 4 | 10.50, 5.25 | 60.0 min | 70.0 | 25.0 | 50.0 |" in text
    assert "agree in every value but the timings before TAR's start at step 749 (7 lines compared)" in text
    # 65.3 - 70.0 = -4.7 (TAR on the same segments); 70.0 - 71.4 = -1.4 (segments against independent frames)
    assert "(TAR on the same segments): -4.7 points" in text and "uniform both): -1.4 points" in text
    # the pair's cost leaves the exploratory run out: (63 + 3600) x 2 = 7,326 s a pair (2.0 h), x 8 = 16.3 h
    assert "The pair took 2.0 hours here" in text and "8 pairs at these times takes 16 hours" in text
    uniform = tmp_path / "act_tar_uniform-seed0" / "train_log.csv"
    _log_lines(*before[:-1], 99.0, 0.3).to_csv(uniform, index=False)  # step 700 differs
    assert "do NOT agree" in results.pilot_report(tmp_path)
