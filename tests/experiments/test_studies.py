"""The study core (``benchmarks/studies``): stages, the plan's order and digest, the record of a started plan, the
command line's refusals, and the run names every study plans, against the names the earlier per-study scripts
planned (``planned_runs.json``, computed with them at the cpu and ci scales)."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from types import SimpleNamespace

import pytest
from paths import REPO

from benchmarks.studies import baselines, cli, paper, regimes, tuning
from benchmarks.studies.core import Arm, Grid, Planner, Scale, plan_digest, seed_major
from benchmarks.studies.records import check_started
from benchmarks.studies.stages import Digest, plan, stage_grids, stage_specs

PLANNED = json.loads((Path(__file__).parent / "planned_runs.json").read_text())
COMMITTED = REPO / "benchmarks" / "results" / "regimes"
OUT = Path("OUT")  # the folder the recorded names were planned in (R1's runs: the committed regime study's)


def test_a_grid_is_arms_by_seeds_over_its_base_in_the_order_given():
    grid = Grid("s", "a grid", ("a=1", "b=2"), (Arm.objective("uniform"), Arm("x", ("c=3", "d=4"))), (0, 7))
    assert grid.overrides(grid.arms[1], 7) == ("a=1", "b=2", "seed=7", "c=3", "d=4")
    last = Grid("s", "a grid", ("a=1",), (Arm.objective("tar"),), (0,), seed_last=True)
    assert last.overrides(last.arms[0], 0) == ("a=1", "objective=tar", "seed=0")
    one = Grid.single("one", ("a=1", "seed=3"))
    assert [one.overrides(arm, s) for arm in one.arms for s in one.seeds] == [("a=1", "seed=3")]


def test_seed_major_takes_every_arm_of_a_seed_before_the_next_seed():
    specs = {"u": ["u0", "u1", "u2"], "t": ["t0", "t1"], "g": ["g0", "g1", "g2"]}
    assert seed_major(specs) == ["u0", "t0", "g0", "u1", "t1", "g1", "u2", "g2"]
    assert seed_major({}) == []


def test_the_plan_digest_hashes_the_overrides_without_the_machine_folders():
    def spec(*overrides):
        return SimpleNamespace(overrides=overrides)

    specs = {"u": [spec("x=1", "runs_root=/a/runs", "data.root=/d", "seed=0")]}
    moved = {"u": [spec("x=1", "runs_root=/elsewhere", "data.root=d2", "seed=0")]}
    by_hand = hashlib.sha256(json.dumps({"u": [["x=1", "seed=0"]]}, sort_keys=True).encode()).hexdigest()[:16]
    assert plan_digest(specs) == plan_digest(moved) == by_hand
    assert plan_digest({"u": [spec("x=2", "seed=0")]}) != by_hand


def test_a_started_record_is_written_once_and_a_change_refused(tmp_path):
    path = tmp_path / "started.json"

    def refusal(key, recorded, now):
        return f"{key} changed: {recorded} -> {now}"

    check_started(path, {"R4": "abc"}, False, refusal)
    assert not path.exists()  # not recorded without `record`
    check_started(path, {"R4": "abc"}, True, refusal)
    check_started(path, {"R5": "def"}, True, refusal)
    assert json.loads(path.read_text()) == {"R4": "abc", "R5": "def"}
    with pytest.raises(SystemExit, match="R4 changed: abc -> xyz"):
        check_started(path, {"R4": "xyz"}, True, refusal)
    assert json.loads(path.read_text()) == {"R4": "abc", "R5": "def"}


def _chunked_digest(label: str) -> str:
    sizes = regimes.SIZES["cpu"]
    planner = Planner(sizes.scale, COMMITTED, "datasets")
    grid = regimes.chunked_grid(sizes, label)
    overrides = {a.name: [SimpleNamespace(overrides=planner.overrides(*grid.overrides(a, s))) for s in grid.seeds]
                 for a in grid.arms}  # fmt: skip
    return plan_digest(overrides)


def test_the_chunked_plans_are_the_ones_their_runs_started_with():
    """The digests recorded when R4's and R5's first runs started (``chunked_started.json``, written by the study
    commit's code) are what the study plans."""
    recorded = json.loads((COMMITTED / "chunked_started.json").read_text())
    assert recorded == {"R4": "519e5635200b4c2a", "R5": "aaf63c1da10507c5"}
    assert _chunked_digest("R4") == recorded["R4"] == PLANNED["regimes"]["cpu"]["r4_digest"]
    assert _chunked_digest("R5") == recorded["R5"]


def test_the_command_line_refuses_bad_input_naming_it(tmp_path):
    with pytest.raises(SystemExit, match="no study 'nope'"):
        cli.main(["nope", "plan"])
    with pytest.raises(SystemExit, match="run needs a stage, one of r1, r2-screen, r2, r3, r4, r5"):
        cli.main(["regimes", "run", "--out", str(tmp_path)])
    with pytest.raises(SystemExit, match="table takes no stage"):
        cli.main(["regimes", "table", "r4", "--out", str(tmp_path)])
    with pytest.raises(SystemExit, match="--out is required with --scale ci"):
        cli.main(["regimes", "plan", "--scale", "ci"])
    with pytest.raises(SystemExit, match="--jobs must be >= 1"):
        cli.main(["regimes", "run", "r3", "--jobs", "0", "--out", str(tmp_path)])
    with pytest.raises(SystemExit, match="collect needs --from DIR"):
        cli.main(["regimes", "collect", "--out", str(tmp_path)])
    with pytest.raises(SystemExit, match="--seeds does not apply"):
        cli.main(["tuning", "plan", "--seeds", "0", "--out", str(tmp_path)])


def _names(specs) -> list[str]:
    return [s.run_dir.name for s in specs]


def _regimes(scale: str) -> dict:
    sizes = regimes.SIZES[scale]
    out = Path("benchmarks/results/regimes") if scale == "cpu" else OUT
    planner = Planner(sizes.scale, out, "datasets")
    source = regimes.source_spec(sizes, planner)
    screened = json.loads((COMMITTED / "screening.json").read_text())["tasks"]
    got = {"source": [source.run_dir.name], "screen": [planner.spec(*sizes.screen).run_dir.name]}
    r1 = [regimes.r1_grid(sizes, source, n) for n in sizes.r1_budgets] if scale == "cpu" else []
    got["r1"] = [name for grid in r1 for name in _names(seed_major(grid.specs(planner)))]
    got["r2"] = _names(seed_major(regimes.r2_grid(sizes, screened).specs(planner)))
    got["r3"] = _names(seed_major(regimes.r3_grid(sizes).specs(planner)))
    for label in ("R4", "R5"):
        specs = regimes.chunked_grid(sizes, label).specs(planner)
        got[label.lower()], got[f"{label.lower()}_digest"] = _names(seed_major(specs)), plan_digest(specs)
    return got


def _tuning(scale: str) -> dict:
    sizes, planner = tuning.SIZES[scale], Planner(tuning.SIZES[scale].scale, OUT, "datasets")
    selected = json.loads((COMMITTED / "tuning" / "selected.json").read_text())
    if scale == "ci":
        selected = {"cell": "tar-g0.5-paper-w3", "variant": "tar_arm"}
    return {
        "tune": _names(seed_major(tuning.tune_grid(sizes).specs(planner))),
        "final": _names(seed_major(tuning.final_grid(sizes, selected).specs(planner))),
    }


def _baselines(scale: str) -> dict:
    ctx = cli.context(baselines.STUDY, ["plan", "--scale", scale, "--out", str(OUT), "--regimes", str(COMMITTED)])
    return {"run": _names(stage_specs(ctx, baselines.STAGES["baselines"], trained=True))}


def _paper(scale: str) -> dict:
    ctx = cli.context(paper.STUDY, ["plan", "--scale", scale, "--out", str(OUT)])
    return {name: _names(stage_specs(ctx, stage)) for name, stage in paper.STAGES.items() if stage.grids}


PLANS = {"regimes": _regimes, "tuning": _tuning, "baselines": _baselines, "paper": _paper}


@pytest.mark.slow
@pytest.mark.parametrize("scale", ["cpu", "ci"])
@pytest.mark.parametrize("study", sorted(PLANS))
def test_planned_run_names_are_the_earlier_scripts(study, scale):
    assert PLANS[study](scale) == PLANNED[study][scale]


def test_a_scale_names_its_overrides_and_seeds():
    scale = Scale("s", "about", ("a=1",), (0, 1))
    planner = Planner(scale, Path("o"), "d", ("e=2",))
    assert planner.overrides("f=3") == ("a=1", f"runs_root={Path('o') / 'runs'}", "data.root=d", "e=2", "f=3")


@pytest.mark.slow  # two study commands, each a Python process that loads the dataset and tries two runs: ~30 s
@pytest.mark.parametrize("jobs", ["1", "2"])  # runs trained in the command's process, or as subprocesses
def test_a_stage_whose_runs_failed_exits_non_zero(jobs, tmp_path, data_root):
    """Another process holds the runs' folders (as a second `run` on the same study folder does): every run of the
    stage fails, the command says so and exits 1, so that a script or a CI job does not read success."""
    import contextlib
    import subprocess
    import sys

    from tar_rl.runlock import run_lock

    argv = ["regimes", "run", "r3", "--scale", "ci", "--out", str(tmp_path / "out"), "--data-root", str(data_root)]
    argv += ["--seeds", "0", "--jobs", jobs]
    ctx = cli.context(regimes.STUDY, argv[1:])
    specs = stage_specs(ctx, regimes.STAGES["r3"])
    with contextlib.ExitStack() as held:
        for spec in specs:
            spec.run_dir.mkdir(parents=True)
            held.enter_context(run_lock(spec.run_dir))
        done = subprocess.run(
            [sys.executable, "-m", "benchmarks.studies", *argv], cwd=REPO, capture_output=True, text=True, timeout=600
        )
    assert done.returncode == 1, done.stdout + done.stderr
    names = ", ".join(spec.run_dir.name for spec in specs)
    assert f"{len(specs)} run(s) failed: " in done.stdout and all(s.run_dir.name in done.stdout for s in specs), names


def _digests(ctx, study) -> dict[str, str]:
    """Each recorded stage's plan digest as its declaration plans it now, under the name its record files it by."""
    out = {}
    for stage in study.stages.values():
        if isinstance(stage.records, Digest):
            grids = [stage.records.of(ctx)] if stage.records.of else stage_grids(ctx, stage) or []
            out.update({grid.name: plan_digest(grid.specs(ctx.planner)) for grid in grids})
    return out


@pytest.mark.slow  # composes every committed study's plan at the cpu scale: about a minute
@pytest.mark.parametrize("study", ["regimes", "why_act", "tuning", "baselines"])
def test_the_committed_studies_recompute_their_records_and_run_names(study):
    """Every committed study at the cpu scale, planned by its declared stages from its committed records: each plan
    digest its ``started`` records hold recomputes, and every committed run folder is a run the stages plan (by
    name: a renamed run would not be collected into it, nor found by the tables)."""
    mod = cli.load(study)
    ctx = cli.context(mod, ["plan"])
    planned = {s.run_dir.name for specs in plan(ctx).values() for s in specs}
    planned |= {s.run_dir.name for stage in mod.stages.values() for s in stage_specs(ctx, stage, trained=True) or []}
    if study == "regimes":  # R1's source and R2's screening run, which the stages train before their gates
        planned |= {s.run_dir.name for s in stage_specs(ctx, regimes.STAGES["r1"].first[0])}
        planned |= {s.run_dir.name for s in stage_specs(ctx, regimes.STAGES["r2-screen"])}
        started = json.loads((ctx.out / "r2_started.json").read_text())
        screened = json.loads((ctx.out / "screening.json").read_text())
        assert started == {"tasks": screened["tasks"], "digest": screened["digest"]}
    records = {}
    for path in ctx.out.glob("*started.json"):
        if path.name != "r2_started.json":
            records.update(json.loads(path.read_text()))
    assert bool(records) == (study in ("regimes", "why_act"))
    digests = _digests(ctx, mod)
    assert {key: digests[key] for key in records} == records
    committed = {p.name for p in (ctx.out / "runs").iterdir() if p.is_dir()}
    assert committed and committed <= planned, sorted(committed - planned)


def test_the_recorded_digests_are_the_ones_committed():
    """The digests R4's, R5's and R6's placement runs started with (the runs R6 trains now are collected by them)."""
    assert json.loads((COMMITTED / "chunked_started.json").read_text()) == {
        "R4": "519e5635200b4c2a",
        "R5": "aaf63c1da10507c5",
    }
    assert json.loads((COMMITTED / "r6" / "started.json").read_text())["placement"] == "746c15c91d5ef103"
