"""Two draws of a head's per-step losses (``python -m benchmarks.analysis noise``): the within-segment correlation
and the top-step agreement against hand values, the segments, the presets' settings, and the command on tiny
trained runs (a deterministic MLP loss agrees with itself exactly; a flow head's sampled time and noise do not);
every ranking signal of the flow head (a deterministic draw agrees with itself for each; the action error's
correlation recomputed from two ``inspect_steps`` passes; the warm-up of the time-normalised loss's running mean;
a run with per-segment times reported once), ``octo_diffusion``, and the refusal of a signal a head lacks."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from recipe_helpers import tiny

from benchmarks.analysis import noise
from tar_rl.diagnostics import top_step_agreement, within_segment_correlation

T, F = True, False


def test_within_segment_correlation_by_hand():
    # one segment reversed: -1, whatever the padded step holds
    assert within_segment_correlation([[1, 2, 3, 0]], [[3, 2, 1, 99]], [[T, T, T, F]]) == pytest.approx(-1.0)
    # a per-segment offset and a common positive scale change nothing
    a = [[1.0, 2.0, 3.0], [0.0, 5.0, 1.0]]
    b = [[12.0, 14.0, 16.0], [-4.0, 6.0, -2.0]]
    assert within_segment_correlation(a, b, [[T, T, T], [T, T, T]]) == pytest.approx(1.0)
    # pooled over segments, each centred on its own mean:
    # segment 1: a - mean = (-1, 0, 1), b - mean = (-1, 1, 0); segment 2: (-2, 2) and (2, -2)
    # sum of products 1 - 8 = -7, sums of squares 2 + 8 = 10 each: -0.7
    a = [[1.0, 2.0, 3.0], [0.0, 4.0, 7.0], [5.0, 0.0, 0.0]]
    b = [[1.0, 3.0, 2.0], [4.0, 0.0, -7.0], [9.0, 0.0, 0.0]]
    valid = [[T, T, T], [T, T, F], [T, F, F]]  # the lone valid step of the third segment has no order
    assert within_segment_correlation(a, b, valid) == pytest.approx(-0.7)


def test_within_segment_correlation_refuses_bad_input_and_is_nan_without_variation():
    with pytest.raises(TypeError, match="bool mask"):
        within_segment_correlation([[1, 2]], [[1, 2]], [[1, 1]])
    with pytest.raises(ValueError, match="share one"):
        within_segment_correlation([[1, 2]], [[1, 2, 3]], [[T, T]])
    with pytest.raises(ValueError, match="finite"):
        within_segment_correlation([[1, math.nan]], [[1, 2]], [[T, T]])
    # a non-finite value on padding is not read
    assert within_segment_correlation([[1, 2, math.nan]], [[1, 2, 0]], [[T, T, F]]) == pytest.approx(1.0)
    assert math.isnan(within_segment_correlation([[2, 2]], [[1, 3]], [[T, T]]))


def test_top_step_agreement_by_hand():
    a = [[1.0, 3.0, 2.0], [0.0, 1.0, 2.0], [9.0, 0.0, 1.0]]
    b = [[0.0, 5.0, 1.0], [2.0, 1.0, 0.0], [0.0, 2.0, 1.0]]
    # segment 1: step 1 in both; segment 2: step 2 against step 0; segment 3: step 9.0 is padding, so
    # a's largest valid value is at step 2 and b's at step 1
    valid = [[T, T, T], [T, T, T], [F, T, T]]
    assert top_step_agreement(a, b, valid) == pytest.approx(1 / 3)
    assert math.isnan(top_step_agreement([[1.0, 2.0]], [[1.0, 2.0]], [[T, F]]))


def test_segments_cut_each_episode_and_mask_the_last_piece():
    values, valid = noise.segments([np.arange(1.0, 6.0), np.array([7.0, 8.0])], 2)
    np.testing.assert_array_equal(values, [[1, 2], [3, 4], [5, 0], [7, 8]])
    np.testing.assert_array_equal(valid, [[T, T], [T, T], [T, F], [T, T]])
    with pytest.raises(ValueError, match="slice_len"):
        noise.segments([np.arange(3.0)], 0)


def test_weight_presets_are_the_libraries_defaults_and_the_gentle_preset():
    presets = noise.weight_presets()
    assert presets["tar"] == {"gamma": 1.0, "w_max": 3.0, "eps": 1e-8, "cap": "paper"}
    assert presets["tar_gentle"] == {"gamma": 0.5, "w_max": 1.5, "eps": 1e-8, "cap": "exact"}


@pytest.fixture(scope="module")
def tiny_runs(tmp_path_factory) -> Path:
    """Tiny trained runs in one folder, on a dataset folder of their own: uniform MLP (trained without evaluation:
    the command reads the trained policy only), uniform flow, tar MLP."""
    from tar_rl.recipes import train

    tmp = tmp_path_factory.mktemp("noise")
    data = tmp_path_factory.mktemp("noise_data")
    runs = (("objective=uniform", "eval.rollouts=0"), ("objective=uniform", "policy=flow"), ("objective=tar",))
    for overrides in runs:
        train(tiny(tmp, data, *overrides, "diagnostics.heldout_demos=0", "logging.record_episodes=2"))
    return tmp / "runs"


@pytest.mark.slow
def test_the_command_on_tiny_runs(tiny_runs):
    table = noise.noise_table(tiny_runs)
    assert list(table.columns) == list(noise.COLUMNS)
    assert list(table["head"]) == ["flow", "mlp"]  # the tar run is left out
    mlp = table[table["head"] == "mlp"].iloc[0]
    flow = table[table["head"] == "flow"].iloc[0]
    # the MLP's loss is a function of the step: both draws give the same losses, hence the same weights
    assert mlp["loss_r"] == pytest.approx(1.0) and mlp["top_agree"] == 1.0
    assert mlp["weight_r_tar"] == pytest.approx(1.0) and mlp["weight_r_tar_gentle"] == pytest.approx(1.0)
    # the flow head samples a time and a noise per step: the draws disagree
    assert flow["loss_r"] < 0.99
    assert mlp["segments"] > 0 and mlp["steps"] >= mlp["segments"] * 2


@pytest.mark.slow
def test_a_draw_repeats_with_its_seed(tiny_runs):
    from benchmarks.analysis.rebuild import rebuild_final
    from tar_rl.report import load_run

    run = load_run(next(p for p in tiny_runs.iterdir() if p.name.startswith("uniform-flow")))
    rebuilt = rebuild_final(run, None, {}, "noise")
    first = noise.draw_losses(rebuilt.objective, rebuilt.episodes, [0])
    again = noise.draw_losses(rebuilt.objective, rebuilt.episodes, [0])
    other = noise.draw_losses(rebuilt.objective, rebuilt.episodes, [1])
    assert all(np.array_equal(x, y) for x, y in zip(first, again, strict=True))
    assert not all(np.array_equal(x, y) for x, y in zip(first, other, strict=True))
    # a draw of two passes is the mean of the one-pass draws of its seeds
    both = noise.draw_losses(rebuilt.objective, rebuilt.episodes, [0, 1])
    for x, y, mean in zip(first, other, both, strict=True):
        np.testing.assert_allclose(mean, (x + y) / 2, rtol=1e-12)


def test_the_two_draws_take_disjoint_seeds():
    assert [list(s) for s in noise.draw_seeds(1)] == [[0], [1]]
    assert [list(s) for s in noise.draw_seeds(3)] == [[0, 1, 2], [3, 4, 5]]
    with pytest.raises(ValueError, match="at least one pass"):
        noise.draw_seeds(0)


def test_refusals_name_the_folder_and_the_bad_draws(tmp_path, capsys):
    with pytest.raises(SystemExit, match="is not a folder"):
        noise.noise_table(tmp_path / "absent")
    with pytest.raises(SystemExit, match=r"no trained uniform run with its checkpoint\.pt"):
        noise.noise_table(tmp_path)
    with pytest.raises(SystemExit):
        noise.noise_main(["--from", str(tmp_path), "--draws", "0"])
    assert "each number of passes must be at least 1" in capsys.readouterr().err


@pytest.mark.slow
def test_the_command_line_writes_the_table(tiny_runs, tmp_path, capsys):
    import pandas as pd

    out = tmp_path / "noise.csv"
    assert noise.noise_main(["--from", str(tiny_runs), "--out", str(out), "--draws", "1,4"]) == 0
    written = pd.read_csv(out)
    assert list(written.columns) == list(noise.COLUMNS)
    assert list(zip(written["head"], written["draws"], strict=True)) == [
        ("flow", 1),
        ("flow", 4),
        ("mlp", 1),
        ("mlp", 4),
    ]
    flow = written[written["head"] == "flow"].set_index("draws")
    # four passes per draw cut each draw's noise variance by four: the draws agree more
    assert flow.loc[4, "loss_r"] > flow.loc[1, "loss_r"]
    markdown = out.with_suffix(".md").read_text()
    assert "| flow | 1 | 1 |" in markdown and "| mlp | 4 | 1 | 1.000 | 1.000 | 1.000 | 1.000 |" in markdown
    assert markdown in capsys.readouterr().out


# -- Ranking signals -----------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def signal_runs(tmp_path_factory) -> Path:
    """Tiny finished uniform runs of the heads whose loss is sampled: flow with per-step times (seed 0), flow with
    per-segment times (seed 1), octo_diffusion."""
    from tar_rl.recipes import train

    tmp = tmp_path_factory.mktemp("signals")
    data = tmp_path_factory.mktemp("signals_data")
    for overrides in (
        ("policy=flow",),
        ("policy=flow", "policy.time_sampling=segment", "seed=1"),
        ("policy=octo_diffusion",),
    ):
        train(
            tiny(tmp, data, "objective=uniform", *overrides, "diagnostics.heldout_demos=0", "logging.record_episodes=2")
        )
    return tmp / "runs"


def _named(folder: Path, prefix: str, seed: int) -> str:
    return next(p.name for p in folder.iterdir() if p.name.startswith(f"{prefix}-s{seed}-"))


def _fixed_draw(self, actions, lead):
    """A flow head's draw that depends on the chunk only: the same time and noise in every pass."""
    import torch

    tau = 0.001 + 0.999 * torch.sigmoid(3.0 * actions.sum((-2, -1)))
    return tau, torch.cos(5.0 * actions)


@pytest.mark.slow
def test_every_signal_of_a_deterministic_draw_agrees_with_itself(signal_runs, monkeypatch):
    """With the flow head's time and noise fixed by the chunk, both draws of every signal are equal: correlation 1,
    the same top step, the same weights (the time-normalised loss's running mean does not move between draws)."""
    from tar_rl.policies.flow import FlowPolicy

    monkeypatch.setattr(FlowPolicy, "draw", _fixed_draw)
    names = [_named(signal_runs, "uniform-flow", 0), _named(signal_runs, "uniform-flow", 1)]
    table = noise.noise_table(signal_runs, signals=["all"], names=names)
    assert list(table.columns) == list(noise.SIGNAL_COLUMNS)
    measured = list(zip(table["time_sampling"], table["signal"], strict=True))
    assert measured == [("step", "loss"), ("step", "action_error"), ("step", "time_normalized"), ("segment", "loss")]
    for column in noise.SIGNAL_MEASURES:
        assert table[column].tolist() == pytest.approx([1.0] * 4, abs=1e-9), column


def _by_hand(objective, episodes, slice_len: int, seed: int):
    """One pass of ``objective.inspect_steps`` along each episode after ``torch.manual_seed(seed)``, its ranked
    values cut into consecutive segments of ``slice_len`` (the last one shorter)."""
    import torch

    objective.train()
    rows, masks = [], []
    with torch.no_grad():
        torch.manual_seed(seed)
        for _, _, td in episodes:
            ranked = objective.inspect_steps(td.unsqueeze(0))[2][0].double().numpy()
            for start in range(0, len(ranked), slice_len):
                part = ranked[start : start + slice_len]
                rows.append(np.concatenate([part, np.zeros(slice_len - len(part))]))
                masks.append([i < len(part) for i in range(slice_len)])
    return np.array(rows), np.array(masks)


@pytest.mark.slow
def test_the_action_errors_correlation_is_that_of_two_inspect_steps_passes(tiny_runs):
    """The command's ``signal_r`` of ``action_error``: two passes (torch seeds 0 and 1) of an objective built with
    ``objective.signal=action_error`` on the run's policy, compared by hand; it is not the loss's."""
    from dataclasses import replace

    from benchmarks.analysis.rebuild import rebuild_final
    from tar_rl.recipes.builders import make_objective
    from tar_rl.report import load_run

    name = _named(tiny_runs, "uniform-flow", 0)
    table = noise.noise_table(tiny_runs, signals=["loss", "action_error"], names=[name])
    rows = {r["signal"]: r for r in table.to_dict("records")}
    rebuilt = rebuild_final(load_run(tiny_runs / name), None, {}, "test")
    cfg = rebuilt.cfg
    objective = make_objective(replace(cfg.objective, signal="action_error"), cfg.optim.steps, cfg.seed, rebuilt.policy)
    (a, valid), (b, _) = (_by_hand(objective, rebuilt.episodes, cfg.data.slice_len, seed) for seed in (0, 1))
    assert rows["action_error"]["signal_r"] == pytest.approx(within_segment_correlation(a, b, valid), abs=1e-12)
    assert rows["action_error"]["top_agree"] == pytest.approx(top_step_agreement(a, b, valid), abs=1e-12)
    assert rows["action_error"]["signal_r"] != pytest.approx(rows["loss"]["signal_r"], abs=1e-6)


@pytest.mark.slow
def test_the_running_mean_is_warmed_up_deterministically_on_the_recorded_segments(tiny_runs):
    """``warm_up``: one update a batch of ``data.batch_segments`` segments per pass, the parameters untouched, the
    bias-corrected weight of a bin at most ``1 - 0.99 ** updates``, the same state from the same seed."""
    import math

    import torch

    from benchmarks.analysis.rebuild import rebuild_final
    from tar_rl.report import load_run

    rebuilt = rebuild_final(load_run(tiny_runs / _named(tiny_runs, "uniform-flow", 0)), None, {}, "test")
    cfg = rebuilt.cfg
    pieces = noise.recorded_segments(rebuilt.episodes, cfg.data.slice_len)
    assert len(pieces) == 13  # the two recorded demonstrations' segments, as the table counts them
    before = {k: v.clone() for k, v in rebuilt.policy.loss.state_dict().items()}
    states = []
    for _ in range(2):
        objective = rebuilt.objective_with("time_normalized")
        state = objective.clean_inner.signal_state
        assert float(state.weight.sum()) == 0.0
        updates = noise.warm_up(objective, pieces, cfg.data.batch_segments, passes=3)
        assert updates == 3 * math.ceil(13 / cfg.data.batch_segments)  # 3 passes of 2 batches of 8 and 5
        assert 0.0 < float(state.weight.max()) <= 1 - 0.99**updates + 1e-12
        states.append(state.total.clone())
    torch.testing.assert_close(states[0], states[1], rtol=0, atol=0)
    after = rebuilt.policy.loss.state_dict()
    assert all(torch.equal(before[k], after[k]) for k in before)
    assert all(p.requires_grad for p in rebuilt.policy.loss.parameters())


@pytest.mark.slow
def test_a_run_with_per_segment_times_is_reported_once_and_octo_diffusion_measured(signal_runs):
    table = noise.noise_table(signal_runs, signals=["all"])
    rows = list(zip(table["head"], table["time_sampling"], table["signal"], strict=True))
    assert rows == [
        ("flow", "step", "loss"),
        ("flow", "step", "action_error"),
        ("flow", "step", "time_normalized"),
        ("flow", "segment", "loss"),
        ("octo_diffusion", "step", "loss"),
    ]
    diffusion = table[table["head"] == "octo_diffusion"].iloc[0]
    assert diffusion["signal_r"] < 0.99  # its per-step loss is a draw of a diffusion time and noise
    segment = table[table["time_sampling"] == "segment"].iloc[0]
    assert segment["segments"] == 13 and segment["steps"] == 95  # the same segments as the per-step runs'


@pytest.mark.slow
def test_a_signal_the_head_does_not_offer_is_refused_naming_the_head_and_its_signals(tiny_runs, tmp_path):
    with pytest.raises(SystemExit, match=r"the mlp head offers the ranking signals \['loss'\], not 'action_error'"):
        noise.noise_main(["--from", str(tiny_runs), "--signals", "action_error", "--out", str(tmp_path / "n.csv")])
    assert not (tmp_path / "n.csv").exists()
    with pytest.raises(SystemExit, match=r"offers the ranking signals \['loss', 'action_error', 'time_normalized'\]"):
        noise.noise_table(tiny_runs, signals=["velocity"], names=[_named(tiny_runs, "uniform-flow", 0)])
    with pytest.raises(SystemExit, match=r"absent-run: not a trained uniform run"):
        noise.noise_table(tiny_runs, names=["absent-run"])


def test_the_training_dataset_is_picked_by_the_runs_recorded_name_then_by_format(tmp_path):
    """Two folders with a run's settings (the same demonstrations collected by two versions of the package):
    the one the run recorded, else the readable format's; a folder of other settings is never a candidate."""
    import json

    from benchmarks.analysis.rebuild import matching_datasets

    wanted = {"tasks": ["reach-v3"], "n_demos": 5, "seed": 0, "chunk_horizon": 8, "history": 2}
    for name, version, n_demos in (("old", 3, 5), ("new", 4, 5), ("newer", 4, 5), ("other", 4, 9)):
        (tmp_path / name).mkdir()
        meta = {**wanted, "n_demos": n_demos, "format_version": version}
        (tmp_path / name / "metadata.json").write_text(json.dumps(meta))
    assert matching_datasets(tmp_path, wanted, "/elsewhere/old", 4) == [tmp_path / "old"]
    assert matching_datasets(tmp_path, wanted, None, 4) == [tmp_path / "new", tmp_path / "newer"]
    assert matching_datasets(tmp_path, wanted, "/elsewhere/gone", 3) == [tmp_path / "old"]
    assert matching_datasets(tmp_path, {**wanted, "n_demos": 9}, None, 3) == [tmp_path / "other"]
    assert matching_datasets(tmp_path, {**wanted, "seed": 1}, None, 4) == []
