"""The MetaWorld suite (``data.suite=metaworld``, the default): scripted-expert demonstrations and the
batched TorchRL evaluator over the v3 tasks (:mod:`tar_rl.collectors.metaworld.tasks`, ``demos``, ``evaluate``)."""

from __future__ import annotations

import os
from collections.abc import Sequence

from tar_rl.data import DemoDataset

from ..suite import EvalSpec, Suite
from . import tasks as mw_tasks
from .dataset import build_dataset, check_disjoint
from .demos import ACTION_DIM, HORIZON
from .evaluate import MAX_HORIZON, RolloutPool, evaluate

__all__ = ["MetaWorldSuite"]


class MetaWorldSuite(Suite):
    """MetaWorld v3: task variations drawn from MT1 seeds, 50 variations per seed."""

    name = "metaworld"
    max_horizon = MAX_HORIZON
    longest_demo = HORIZON
    images = True
    action_dim = ACTION_DIM
    sources = ("metaworld",)
    task_names = mw_tasks.TASKS
    instructions = mw_tasks.INSTRUCTIONS

    def resolve(self, spec: Sequence[str]) -> list[str]:
        return mw_tasks.resolve_tasks(list(spec))

    def demo_seeds(self, seed: int, n_demos: int) -> set[int]:
        return set(mw_tasks.variation_seeds(seed, 3 * n_demos + 5))  # the most attempts collection makes

    def eval_seeds(self, seed: int, rollouts: int) -> set[int]:
        return set(mw_tasks.variation_seeds(seed, rollouts))

    def check_seeds(self, seed: int, n_demos: int, spec: EvalSpec) -> None:
        mw_tasks.check_disjoint(
            sorted(self.demo_seeds(seed, n_demos)), sorted(self.eval_seeds(spec.seed, spec.rollouts))
        )

    def check_dataset(self, dataset: DemoDataset, spec: EvalSpec) -> None:
        check_disjoint(dataset, spec.seed, spec.rollouts)

    def build_dataset(self, data, tasks: Sequence[str], n_demos: int, seed: int, progress: bool):
        return build_dataset(
            data.root,
            list(tasks),
            n_demos=n_demos,
            seed=seed,
            chunk_horizon=data.chunk_horizon,
            history=data.history,
            image_size=data.image_size,
            workers=data.workers,
            progress=progress,
        )

    def evaluation_pool(self) -> RolloutPool:
        return RolloutPool()

    def evaluate(
        self, spec: EvalSpec, actor, tasks: Sequence[str], progress: bool, shard: tuple[int, int], pool: RolloutPool
    ):
        workers = spec.workers
        if workers is None and shard[1] > 1:
            workers = max(1, (os.cpu_count() or 1) // shard[1])
        return evaluate(
            actor,
            list(tasks),
            rollouts_per_task=spec.rollouts,
            seed=spec.seed,
            horizon=spec.horizon,
            workers=workers,
            progress=progress,
            shard=shard,
            image_size=spec.image_size if "pixels" in actor.in_keys else 0,
            pool=pool,
        )
