"""The base class of the simulator suites (:mod:`tar_rl.collectors.suites` holds the registry)."""

from __future__ import annotations

import contextlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType

from tar_rl.data import DemoDataset

__all__ = ["COLUMNS", "EvalSpec", "Suite"]

# The per-rollout columns every suite's evaluation returns, in this order.
COLUMNS = (
    "task",
    "task_id",
    "group",
    "variation_seed",
    "variation_index",
    "success",
    "steps",
    "rho",
    "return",
    "failure",
)


@dataclass(frozen=True)
class EvalSpec:
    """One job's evaluation, as a suite's evaluator reads it (the recipe builds it once from its config).

    Attributes:
        rollouts: rollouts per task, each on its own variation (at least 1).
        seed: base seed of the evaluation variations.
        horizon: step budget per rollout (a suite with its own budgets, LIBERO, does not read it).
        workers: evaluation processes (None: every core).
        image_size: the size of the camera images a policy reading ``pixels`` sees (0: none).
        dataset: the folder of a given dataset (``data.path``) whose task ids and observation keys a suite
            evaluating imported demonstrations reads; None for a dataset the suite collected.
    """

    rollouts: int
    seed: int
    horizon: int
    workers: int | None = None
    image_size: int = 0
    dataset: str | None = None


class Suite:
    """What the recipe needs of a simulator suite.

    A dataset's methods take the recipe's ``data`` section (``DataConfig``: ``data.root``, ``data.path``, ...); the
    evaluation's take an :class:`EvalSpec`.

    Attributes:
        name: its ``data.suite`` name.
        max_horizon: the largest ``eval.horizon``.
        longest_demo: the most steps a demonstration it collects can have (its episodes end there), known before
            collecting; 0: not known.
        images: whether ``data.image_size > 0`` (camera images) is supported.
        action_dim: the action size of the datasets it collects (0: it collects none; a given dataset has its own).
        collects: whether it collects its own demonstrations (False: it evaluates imported ones only).
        sources: the dataset sources (``metadata.json``'s ``source``) it evaluates.
        no_collection: why it collects nothing and what to do instead (for a suite that does not collect).
        task_names: the fixed task list whose indices are the task ids of the datasets it collects (a dataset's
            ``task_names``); empty for a suite that collects nothing (an imported dataset numbers its own tasks).
        instructions: the instruction text of each task of ``task_names``.
    """

    name: str = ""
    max_horizon: int = 0
    longest_demo: int = 0
    images: bool = False
    action_dim: int = 0
    collects: bool = True
    sources: tuple[str, ...] = ()
    no_collection: str = "it collects no demonstrations"
    task_names: tuple[str, ...] = ()
    instructions: Mapping[str, str] = MappingProxyType({})

    def resolve(self, spec: Sequence[str]) -> list[str]:
        """Task and group names -> task names (``ValueError`` naming the valid ones)."""
        raise NotImplementedError

    def demo_seeds(self, seed: int, n_demos: int) -> set[int]:
        """Every seed collecting ``n_demos`` demonstrations per task from ``seed`` may use."""
        raise NotImplementedError

    def eval_seeds(self, seed: int, rollouts: int) -> set[int]:
        """The seeds ``rollouts`` evaluation rollouts per task from ``seed`` use."""
        raise NotImplementedError

    def check_seeds(self, seed: int, n_demos: int, spec: EvalSpec) -> None:
        """Refuse demonstration seeds (``n_demos`` per task from ``seed``) that may meet the evaluation's.

        Raises:
            ValueError: naming the shared seeds.
        """
        raise NotImplementedError

    def check_dataset(self, dataset: DemoDataset, spec: EvalSpec) -> None:
        """The same for a dataset already collected or given (``ValueError``)."""
        raise NotImplementedError

    def check_config(self, data, given: DemoDataset | None, train: Sequence[str], evaluate: Sequence[str]):
        """The suite's own checks of a job (``ValueError`` naming what is wrong); none by default."""

    def build_dataset(self, data, tasks: Sequence[str], n_demos: int, seed: int, progress: bool):
        """``n_demos`` demonstrations per task collected from ``seed`` (collected once, cached under ``data.root``)."""
        raise ValueError(f"the {self.name} suite collects no demonstrations")

    def evaluation_pool(self) -> contextlib.AbstractContextManager:
        """What the evaluations of one job share (worker processes, idle environments), as a context manager the
        job leaves when its evaluations are over; nothing for a suite whose rollouts run in the calling process."""
        return contextlib.nullcontext()

    def evaluate(self, spec: EvalSpec, actor, tasks: Sequence[str], progress: bool, shard: tuple[int, int], pool):
        """One row per rollout (``tar_rl.collectors.suite.COLUMNS``) of ``spec.rollouts`` per task.

        ``pool``: the job's :meth:`evaluation_pool`.
        """
        raise NotImplementedError
