"""The base class of the simulator suites (:mod:`tar_rl.collectors.suites` holds the registry)."""

from __future__ import annotations

from collections.abc import Sequence

from tar_rl.data import DemoDataset

from .evaluate import RolloutPool

__all__ = ["Suite"]


class Suite:
    """What the recipe needs of a simulator suite.

    Attributes:
        name: its ``data.suite`` name.
        max_horizon: the largest ``eval.horizon``.
        images: whether ``data.image_size > 0`` (camera images) is supported.
        collects: whether it collects its own demonstrations (False: it evaluates imported ones only).
        sources: the dataset sources (``metadata.json``'s ``source``) it evaluates.
        no_collection: why it collects nothing and what to do instead (for a suite that does not collect).
    """

    name: str = ""
    max_horizon: int = 0
    images: bool = False
    collects: bool = True
    sources: tuple[str, ...] = ()
    no_collection: str = "it collects no demonstrations"

    def resolve(self, spec: Sequence[str]) -> list[str]:
        """Task and group names -> task names (``ValueError`` naming the valid ones)."""
        raise NotImplementedError

    def demo_seeds(self, seed: int, n_demos: int) -> set[int]:
        """Every seed collecting ``n_demos`` demonstrations per task from ``seed`` may use."""
        raise NotImplementedError

    def eval_seeds(self, seed: int, rollouts: int) -> set[int]:
        """The seeds ``rollouts`` evaluation rollouts per task from ``seed`` use."""
        raise NotImplementedError

    def check_seeds(self, config: dict) -> None:
        """Refuse demonstration seeds (``data.seed``, ``data.n_demos``) that may meet the evaluation's.

        Raises:
            ValueError: naming the shared seeds.
        """
        raise NotImplementedError

    def check_dataset(self, dataset: DemoDataset, eval_seed: int, rollouts: int) -> None:
        """The same for a dataset already collected or given (``ValueError``)."""
        raise NotImplementedError

    def check_config(self, config: dict, given: DemoDataset | None, train: Sequence[str], evaluate: Sequence[str]):
        """The suite's own checks of a job (``ValueError`` naming what is wrong); none by default."""

    def build_dataset(self, config: dict, tasks: Sequence[str], n_demos: int, seed: int, progress: bool):
        """``n_demos`` demonstrations per task collected from ``seed`` (collected once, cached under ``data.root``)."""
        raise ValueError(f"the {self.name} suite collects no demonstrations")

    def evaluate(
        self, config: dict, actor, tasks: Sequence[str], progress: bool, shard: tuple[int, int], pool: RolloutPool
    ):
        """One row per rollout (``tar_rl.collectors.evaluate.COLUMNS``) of ``eval.rollouts`` per task.

        ``pool``: the job's ``tar_rl.collectors.evaluate.RolloutPool`` (worker processes and envs kept
        between its evaluations), for a suite that runs its rollouts there.
        """
        raise NotImplementedError
