"""A finished run's policy and objective rebuilt from its final checkpoint and config, with the demonstrations its
``weights.csv`` records: what the analyses that compute again from a checkpoint (:mod:`.dims`, :mod:`.noise`)
start from."""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass
from pathlib import Path

from tar_rl.report import Run

__all__ = ["Rebuilt", "checkpoint_parser", "matching_datasets", "read_checkpoint", "rebuild_final", "training_demos"]


@dataclass
class Rebuilt:
    """A run's objective (its policy inside) at the final step, its validated config and the recorded
    demonstrations: ``(task, episode, TensorDict)`` per episode, the first ``logging.record_episodes`` of each
    training task (:func:`tar_rl.recipes.record.demo_episodes`); ``policy``, the head the objective wraps (what
    another objective on the same weights is built from, :meth:`objective_with`)."""

    objective: object
    cfg: object
    episodes: list
    policy: object = None

    def objective_with(self, signal: str):
        """The run's objective ranking by ``signal`` (``objective.signal``): :attr:`objective` itself where the
        run trained with that signal (its state, e.g. a running mean, as the checkpoint holds it), else a new one
        on the same policy, built as the recipe builds it (a signal's state, if any, fresh)."""
        from dataclasses import replace

        from tar_rl.recipes.builders import make_objective

        if signal == self.cfg.objective.signal:
            return self.objective
        obj = replace(self.cfg.objective, signal=signal)
        return make_objective(obj, self.cfg.optim.steps, self.cfg.seed, self.policy)


def read_checkpoint(path: Path, who: str) -> dict:
    """A run's final checkpoint as saved, of any checkpoint format (R3's are of format 1: their ``data_info``
    lacks the task instructions, which the MLP head with a task embedding does not read); ``who`` names the
    command in the error."""
    import torch

    if not path.is_file():
        raise SystemExit(f"{who}: no checkpoint at {path} (the analysis needs the final policy)")
    state = torch.load(path, map_location="cpu", weights_only=True)
    missing = [k for k in ("config", "data_info", "objective", "step", "finished") if k not in state]
    if missing:
        raise SystemExit(f"{who}: {path} is not a training checkpoint (no {', '.join(missing)})")
    return state


def matching_datasets(root: Path, wanted: dict, recorded: str | None, version: int) -> list[Path]:
    """The dataset folders under ``root`` whose ``metadata.json`` has every setting of ``wanted``; where there are
    several, those named as ``recorded`` (a run's recorded dataset path) if any, else those of format ``version``
    if any, else all of them."""
    found = {}
    for meta_path in sorted(root.glob("*/metadata.json")):
        metadata = json.loads(meta_path.read_text())
        if all(metadata.get(k) == v for k, v in wanted.items()):
            found[meta_path.parent] = metadata.get("format_version")
    if len(found) <= 1:
        return list(found)
    named = [p for p in found if recorded is not None and p.name == Path(recorded).name]
    return named or [p for p, v in found.items() if v == version] or list(found)


def training_demos(root: Path, cfg, tasks: tuple[str, ...], info: dict, who: str, recorded: str | None = None):
    """The run's training dataset under ``root``, opened by :func:`tar_rl.data.load_dataset` (every check of a
    dataset; nothing written).

    The dataset is the folder whose metadata names the run's tasks, demonstrations per task, seed, chunk
    horizon and history. Where several folders have those settings (the same demonstrations collected by two
    versions of the package, in two formats), the one of the name the run recorded (``recorded``: its summary's
    ``data.path``) is taken, else the one of the format this package reads. Its observation statistics must equal
    the checkpoint's (the data the policy was trained on). A dataset of a format the package no longer reads is
    refused with how to build it again (the scripted demonstrations of a seed are the same, which the statistics
    check confirms).
    """
    from tar_rl.data import FORMAT_VERSION, DatasetError, load_dataset

    wanted = {
        "tasks": list(tasks),
        "n_demos": cfg.data.n_demos,
        "seed": cfg.data.seed,
        "chunk_horizon": cfg.data.chunk_horizon,
        "history": cfg.data.history,
    }
    found = matching_datasets(root, wanted, recorded, FORMAT_VERSION)
    if len(found) != 1:
        raise SystemExit(
            f"{who}: {len(found)} datasets under {root} have the settings {wanted} (one is needed); "
            "name the folder holding the runs' training data with --data"
        )
    try:
        demos = load_dataset(found[0])
    except DatasetError as err:
        raise SystemExit(f"{who}: {err}") from None
    if list(demos.metadata["stats"]["observation"]["mean"]) != list(info["obs_mean"]):
        raise SystemExit(f"{who}: {found[0]} holds other data than the checkpoint was trained on")
    return demos


def rebuild_final(run: Run, data_root: Path | None, demos: dict, who: str) -> Rebuilt:
    """``run``'s objective and policy from its final checkpoint, and its recorded demonstrations.

    The policy and objective are built from the checkpoint's config and weights, the policy eager
    (``policy.compile`` off where the head has it: an analysis trains nothing, and the compiled kernels, which
    only a step with gradients on takes, would compile once per batch shape for the same numbers up to float
    rounding); ``data_root`` defaults to the run's ``data.root``; ``demos`` caches the datasets read, across runs
    (updated here).

    Raises:
        SystemExit: no checkpoint, an unfinished one, or no training data (``who`` names the command).
    """
    import torch

    from tar_rl.policies import DataInfo
    from tar_rl.recipes.builders import make_objective, make_policy
    from tar_rl.recipes.record import demo_episodes
    from tar_rl.recipes.rundir import with_defaults
    from tar_rl.recipes.validate import validate
    from tar_rl.runs import CHECKPOINT

    state = read_checkpoint(run.path / CHECKPOINT, who)
    config = with_defaults(state["config"])
    config["init"] = {"from": None}  # rebuilding needs neither a post-training source nor held-out data
    config["diagnostics"]["heldout_demos"] = 0
    if "compile" in config["policy"]:
        config["policy"]["compile"] = False
    job = validate(config)
    cfg = job.config
    if not state["finished"] or state["step"] != cfg.optim.steps:
        raise SystemExit(f"{who}: {run.path} holds step {state['step']} of {cfg.optim.steps}, not the final one")
    torch.manual_seed(cfg.seed)
    policy = make_policy(cfg.policy, DataInfo.from_dict(state["data_info"]))
    objective = make_objective(cfg.objective, cfg.optim.steps, cfg.seed, policy)
    objective.load_state_dict(state["objective"])
    root = Path(data_root or cfg.data.root)
    recorded = (run.summary.get("data") or {}).get("path")
    key = (root, cfg.data.n_demos, cfg.data.seed, cfg.data.chunk_horizon, cfg.data.history, job.train_tasks, recorded)
    if key not in demos:
        demos[key] = training_demos(root, cfg, job.train_tasks, state["data_info"], who, recorded)
    episodes = demo_episodes(demos[key], job.train_tasks, cfg.logging.record_episodes, policy.keys, "cpu")
    return Rebuilt(objective, cfg, episodes, policy)


def checkpoint_parser(prog: str, description: str, runs: str, out: Path) -> argparse.ArgumentParser:
    """The command line of an analysis that computes from final checkpoints: ``--from DIR`` (``runs`` says which
    runs), ``--data DIR`` and ``--out FILE`` (default ``out``); a command adds its own options."""
    p = argparse.ArgumentParser(prog=f"python -m benchmarks.analysis {prog}", description=description)
    p.add_argument("--from", dest="runs", required=True, help=f"the folder holding {runs} with their checkpoints")
    p.add_argument("--data", default=None, help="the folder holding their training datasets (default: data.root)")
    p.add_argument("--out", default=str(out), help=f"the CSV to write (default: {out.parent.name}/{out.name})")
    return p
