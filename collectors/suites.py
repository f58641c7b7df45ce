"""Simulator suites: where demonstrations are collected and policies evaluated (``data.suite``).

A suite is one :class:`Suite` object in the :data:`SUITES` registry. The recipe asks every suite the
same questions (its tasks, the seeds its demonstrations and evaluations use, a dataset, an
evaluation with the evaluator's per-rollout columns, ``tar_rl.collectors.evaluate.COLUMNS``) and has
no branch for any one of them. Adding a simulator is one module with a :class:`Suite` subclass and
its ``SUITES.register`` call, plus its import at the bottom of this module.

Methods take the job's settings as the resolved config dict (``config["data"]``, ``config["eval"]``).
"""

from __future__ import annotations

from collections.abc import Sequence

from tar_rl.data import DemoDataset
from tar_rl.registry import Registry

__all__ = ["SUITES", "Suite", "suite_for"]


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
        """Refuse demonstration seeds (``data.seed``, ``data.n_demos``) that may meet the evaluation's (``ValueError``)."""
        raise NotImplementedError

    def check_dataset(self, dataset: DemoDataset, eval_seed: int, rollouts: int) -> None:
        """The same for a dataset already collected or given (``ValueError``)."""
        raise NotImplementedError

    def check_config(self, config: dict, given: DemoDataset | None, train: Sequence[str], evaluate: Sequence[str]):
        """The suite's own checks of a job (``ValueError`` naming what is wrong); none by default."""

    def build_dataset(self, config: dict, tasks: Sequence[str], n_demos: int, seed: int, progress: bool):
        """``n_demos`` demonstrations per task collected from ``seed`` (collected once, cached under ``data.root``)."""
        raise ValueError(f"the {self.name} suite collects no demonstrations")

    def evaluate(self, config: dict, actor, tasks: Sequence[str], progress: bool, shard: tuple[int, int]):
        """One row per rollout (``tar_rl.collectors.evaluate.COLUMNS``) of ``eval.rollouts`` per task."""
        raise NotImplementedError


#: The suites by ``data.suite`` name.
SUITES: Registry[Suite] = Registry("suite")


def suite_for(name: str, given: DemoDataset | None) -> Suite | None:
    """The suite that evaluates a job: ``data.suite=name``, or for a given dataset (``data.path``) the suite
    of its source when ``name`` does not evaluate that source (``None``: no simulator here has it).

    Raises:
        ValueError: a suite that only evaluates given datasets without one, or with a dataset of a source
            it does not evaluate.
    """
    suite = SUITES.get(name)
    if given is None:
        if not suite.collects:
            raise ValueError(f"data.suite={name} needs data.path: {suite.no_collection}")
        return suite
    if given.source in suite.sources:
        return suite
    if not suite.collects:
        raise ValueError(
            f"data.suite={name} evaluates demonstrations of the source(s) {list(suite.sources)}; the dataset of "
            f"data.path holds {given.source} demonstrations"
        )
    owners = [s for s in SUITES.values() if given.source in s.sources and s.collects]
    return owners[0] if owners else None


# The suites register themselves on import.
from . import dmc, libero, metaworld  # noqa: E402, F401
