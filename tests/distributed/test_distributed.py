"""Training and evaluation across processes: DDP on gloo (CPU), torchrun jobs, sharded evaluation.

The gradient test runs two processes by hand (``torch.multiprocessing`` + a file store); the job
tests launch ``torchrun --nproc_per_node=2`` on a tiny job (real MetaWorld, ``reach``, 2 demos)
through a small launcher script that can make a rank fail or disagree, as a crash or a
misconfigured cluster would.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import time
from datetime import timedelta
from pathlib import Path

import pandas as pd
import pytest
import torch
import torch.distributed as torch_dist
import torch.multiprocessing as mp
from objective_helpers import tar_loss
from recipe_helpers import compose_config
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torchrl.objectives import BCLoss

from tar_rl import TARLoss
from tar_rl.collectors.metaworld.dataset import build_dataset
from tar_rl.collectors.metaworld.evaluate import ExpertPolicy, evaluate
from tar_rl.recipes import train
from tar_rl.runs import load_checkpoint

B, L = 8, 6


WEIGHTINGS = ("tar", "dro_time")  # TAR weights each segment alone; dro_time's state is learnt from the whole batch


def _objective(weighting: str = "tar", seed: int = 0) -> TARLoss:
    torch.manual_seed(seed)
    net = torch.nn.Sequential(torch.nn.Linear(5, 16), torch.nn.Tanh(), torch.nn.Linear(16, 2))
    actor = TensorDictModule(net, in_keys=["observation"], out_keys=["action"])
    params = {"dro_time": {"dro_eta": 1.0, "dro_bins": 3}, "tar": {"gamma": 1.0, "w_max": 3.0}}[weighting]
    return tar_loss(BCLoss(actor, loss_function="mse", reduction="none"), weighting, **params)


def _batch() -> TensorDict:
    g = torch.Generator().manual_seed(1)
    valid = torch.ones(B, L, dtype=torch.bool)
    valid[[1, 6], 4:] = False  # padded segments on both ranks' halves
    return TensorDict(
        {
            "observation": torch.randn(B, L, 5, generator=g),
            "action": torch.randn(B, L, 2, generator=g),
            # segment i: steps 2i .. 2i+5 of an episode of 20 steps (what dro_time reads)
            "step": 2 * torch.arange(B)[:, None] + torch.arange(L),
            "episode_length": torch.full((B, L), 20),
            ("collector", "mask"): valid,
        },
        [B, L],
    )


def _rank_worker(rank: int, world: int, store_path: str, out_dir: str) -> None:
    from tar_rl.distributed import close_group, data_parallel

    torch.set_num_threads(1)
    store = torch_dist.FileStore(store_path, world)
    torch_dist.init_process_group("gloo", store=store, rank=rank, world_size=world, timeout=timedelta(seconds=120))
    try:
        results = {}
        for weighting in WEIGHTINGS:
            objective = _objective(weighting)
            model = data_parallel(objective)
            share = B // world
            out = model(_batch()[rank * share : (rank + 1) * share])
            out["loss_tar"].backward()
            grads = {n: p.grad.clone() for n, p in objective.named_parameters() if p.grad is not None}
            state = objective.state_dict().get("weighting_state.value")
            results[weighting] = {"loss": out["loss_tar"].detach(), "grads": grads, "state": state}
            del model, out
        torch.save(results, Path(out_dir) / f"rank{rank}.pt")
        close_group()  # the normal path: see tar_rl.distributed.close_group
    finally:
        if torch_dist.is_initialized():
            torch_dist.destroy_process_group()


def _join_after_results(context, results, limit: float = 300.0, grace: float = 30.0) -> None:
    """Join spawned ranks; once every result file is written, give them ``grace`` seconds to exit.

    The check here is the ranks' numbers. A rank stuck in process-group teardown after writing them
    (gloo's threads and the GIL; see ``tar_rl.distributed.close_group``) is terminated rather than
    hanging the suite; a rank that fails raises as ``mp.spawn`` does.
    """
    start = time.monotonic()
    written = None
    while not context.join(timeout=1):
        now = time.monotonic()
        if written is None and all(Path(r).exists() for r in results):
            written = now
        if (written is not None and now - written > grace) or now - start > limit:
            for process in context.processes:
                if process.is_alive():
                    process.terminate()
            assert written is not None, f"the ranks wrote no results within {limit} s"
            return


def test_two_ranks_give_the_loss_and_gradient_of_the_concatenated_batch(tmp_path):
    context = mp.spawn(_rank_worker, args=(2, str(tmp_path / "store"), str(tmp_path)), nprocs=2, join=False)
    _join_after_results(context, [tmp_path / f"rank{r}.pt" for r in range(2)])
    results = [torch.load(tmp_path / f"rank{r}.pt", weights_only=True) for r in range(2)]
    singles = {}
    for weighting in WEIGHTINGS:
        ranks = [r[weighting] for r in results]
        single = singles[weighting] = _objective(weighting)
        out = single(_batch())
        out["loss_tar"].backward()
        # Each rank holds 4 whole segments: TAR weights each segment alone, so the mean of the ranks'
        # losses is the loss on the 8 segments, and DDP's averaged gradient is its gradient. dro_time's
        # group weights are updated from the statistics of all 8 segments (summed over the ranks), so
        # every rank weights its segments with the group weights of the single process.
        expected = float(out["loss_tar"].detach())
        assert (ranks[0]["loss"] + ranks[1]["loss"]) / 2 == pytest.approx(expected, rel=1e-6), weighting
        for name, p in single.named_parameters():
            if p.grad is None:
                continue
            for r in ranks:
                torch.testing.assert_close(r["grads"][name], p.grad, rtol=1e-5, atol=1e-7)
    state = singles["dro_time"].weighting_state.value
    for r in results:
        torch.testing.assert_close(r["dro_time"]["state"], state, rtol=1e-12, atol=1e-12)
    alone = _objective("dro_time")
    alone(_batch()[:4])  # rank 0's share alone would move the group weights elsewhere
    assert not torch.allclose(alone.weighting_state.value, state)


def test_shards_of_an_evaluation_make_the_whole_evaluation():
    kwargs = dict(rollouts_per_task=3, seed=1000, horizon=120, workers=1, progress=False)
    whole = evaluate(ExpertPolicy(), ["reach", "button-press-topdown"], **kwargs)
    parts = [evaluate(ExpertPolicy(), ["reach", "button-press-topdown"], shard=(i, 4), **kwargs) for i in range(4)]
    assert [len(p) for p in parts] == [2, 2, 1, 1]  # 6 rollouts dealt round-robin over 4 shards
    merged = pd.concat(parts, ignore_index=True).sort_values(["task_id", "variation_index"]).reset_index(drop=True)
    pd.testing.assert_frame_equal(merged, whole)


@pytest.mark.parametrize("shard", [(2, 2), (-1, 2), (0, 0)])
def test_bad_shard_is_refused(shard):
    with pytest.raises(ValueError, match="shard"):
        evaluate(ExpertPolicy(), "reach", rollouts_per_task=1, horizon=5, workers=1, progress=False, shard=shard)


# -- torchrun jobs ------------------------------------------------------------------------------

LAUNCHER = textwrap.dedent(
    """
    # Test launcher: `tar-rl train` with optional failures injected through the environment.
    import os
    import sys

    from tar_rl.data import SegmentSampler

    rank = os.environ.get("RANK", "0")
    crash_at = int(os.environ.get("CRASH_AT", "0"))
    if crash_at and os.environ.get("CRASH_RANK", rank) == rank:
        original = SegmentSampler.sample
        calls = [0]

        def sample(self):
            calls[0] += 1
            if calls[0] == crash_at:
                raise RuntimeError(f"injected failure on rank {rank}")
            return original(self)

        SegmentSampler.sample = sample
    args = sys.argv[1:]
    if os.environ.get("SEED_BY_RANK"):
        args.append(f"seed={rank}")
    from tar_rl.cli import main

    sys.exit(main(["train", *args]))
    """
)


@pytest.fixture(scope="module")
def job(tmp_path_factory):
    root = tmp_path_factory.mktemp("dist")
    data_root = root / "datasets"
    build_dataset(data_root, ["reach"], 2, seed=0, workers=1, progress=False, verbose=False)
    (root / "launcher.py").write_text(LAUNCHER)
    overrides = [
        "data.tasks=[reach]",
        "data.n_demos=2",
        "data.workers=1",
        f"data.root={data_root}",
        "data.batch_segments=8",
        "data.slice_len=8",
        "policy.hidden=[32,32]",
        "optim.steps=20",
        "optim.warmup=2",
        "logging.every=4",  # the checkpoint of step 10 falls inside a logging window (steps 9..12)
        "logging.checkpoint_every=10",
        "logging.progress=false",
        "eval.rollouts=2",
        "eval.horizon=20",
        "eval.workers=1",
    ]
    return root, overrides


def _launch(root: Path, overrides: list[str], runs: str, nproc: int, **env) -> subprocess.CompletedProcess:
    command = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc_per_node={nproc}"]
    environment = {**os.environ, "OMP_NUM_THREADS": "1", **{k: str(v) for k, v in env.items()}}
    return subprocess.run(
        [*command, str(root / "launcher.py"), *overrides, f"runs_root={root / runs}"],
        cwd=root,
        env=environment,
        capture_output=True,
        text=True,
        timeout=600,
    )


def _only_run(runs: Path) -> Path:
    (run_dir,) = [p for p in runs.iterdir() if p.is_dir()]
    return run_dir


@pytest.fixture(scope="module")
def two_ranks(job):
    root, overrides = job
    done = _launch(root, overrides, "two", 2)
    assert done.returncode == 0, done.stderr[-3000:]
    return _only_run(root / "two"), done


@pytest.mark.slow
def test_a_two_rank_job_follows_the_single_process_run(job, two_ranks):
    root, overrides = job
    run_dir, done = two_ranks
    assert done.stdout.count("final evaluation") == 1  # rank 0 alone prints and writes
    # The single-process run in this process: without WORLD_SIZE (or with WORLD_SIZE=1, as under
    # `torchrun --nproc_per_node=1`) a job is one process, with the same settings.
    train(compose_config(*overrides, f"runs_root={root / 'one'}"))
    single = load_checkpoint(_only_run(root / "one"))
    double = load_checkpoint(run_dir)
    assert double["world_size"] == 2 and single["world_size"] == 1
    # Same global batches in the same order; only the order of floating-point sums differs.
    for name, value in single["policy"].items():
        torch.testing.assert_close(double["policy"][name], value, rtol=1e-4, atol=1e-5)
    losses = [[r[3] for r in s["logs"]["metrics"] if r[2] == "loss"] for s in (single, double)]
    assert losses[0] == pytest.approx(losses[1], rel=1e-4)
    rows = [pd.read_csv(d / "eval_rollouts.csv") for d in (_only_run(root / "one"), run_dir)]
    assert rows[0][["task", "variation_index", "step"]].equals(rows[1][["task", "variation_index", "step"]])
    assert sorted(p.name for p in run_dir.iterdir() if not p.name.startswith(".")) == [
        "checkpoint.pt",
        "config.yaml",
        "eval_rollouts.csv",
        "metrics.csv",
        "summary.json",
        "weights.csv",
    ]


@pytest.fixture(scope="module")
def crashed(job):
    """A two-rank job whose rank 1 fails at its 15th batch, after the checkpoint of step 10."""
    root, overrides = job
    return _launch(root, overrides, "resumed", 2, CRASH_AT=15, CRASH_RANK=1)


@pytest.mark.slow
def test_a_killed_two_rank_job_resumes_to_the_same_weights(job, two_ranks, crashed):
    root, overrides = job
    whole = load_checkpoint(two_ranks[0])
    assert crashed.returncode != 0
    run_dir = _only_run(root / "resumed")
    assert load_checkpoint(run_dir)["step"] == 10
    again = _launch(root, overrides, "resumed", 2)
    assert again.returncode == 0, again.stderr[-3000:]
    assert "resuming at step 10" in again.stdout
    final = load_checkpoint(run_dir)
    for name, value in whole["policy"].items():
        assert torch.equal(final["policy"][name], value), name
    for name in ("metrics.csv", "eval_rollouts.csv", "weights.csv"):  # each rank's logging window was kept
        assert (run_dir / name).read_bytes() == (two_ranks[0] / name).read_bytes(), name


@pytest.mark.slow
def test_a_rank_that_dies_stops_the_job(crashed):
    assert crashed.returncode != 0
    assert "injected failure on rank 1" in crashed.stderr


@pytest.mark.slow
def test_ranks_with_different_settings_are_refused(job):
    root, overrides = job
    done = _launch(root, overrides, "mismatch", 2, SEED_BY_RANK=1)
    assert done.returncode != 0
    assert "different settings (rank 0 vs rank 1: seed: 0 -> 1)" in done.stderr
    assert not (root / "mismatch").exists() or not any((root / "mismatch").iterdir())


@pytest.mark.slow
def test_batch_must_split_evenly_over_ranks(job):
    root, overrides = job
    done = _launch(root, [*overrides, "data.batch_segments=7"], "odd", 2)
    assert done.returncode != 0
    assert "data.batch_segments=7 is not divisible by the 2 processes" in done.stderr


@pytest.mark.slow
def test_bench_scale_quick_writes_csv(tmp_path):
    from benchmarks import bench_scale as bench  # its spawned ranks import it by that name

    out = tmp_path / "scale.csv"
    assert bench.main(["--quick", "--procs", "2", "--out", str(out)]) == 0
    df = pd.read_csv(out)
    assert set(df.section) == {"train", "eval"} and set(df.rep.astype(str)) == {"0", "median"}
    assert (df.one_process > 0).all() and (df.n_processes > 0).all()
    assert ((df.efficiency - df.n_processes / (2 * df.one_process)).abs() < 1e-9).all()
