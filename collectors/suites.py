"""Simulator suites: where demonstrations are collected and policies evaluated (``data.suite``).

A suite is one :class:`~tar_rl.collectors.suite.Suite` object in the :data:`SUITES` registry. The
recipe asks every suite the same questions (its tasks, the seeds its demonstrations and evaluations use, a dataset, an
evaluation with the evaluator's per-rollout columns, ``tar_rl.collectors.suite.COLUMNS``) and has
no branch for any one of them. Adding a simulator is one module with a ``Suite`` subclass and its
entry in the registration at the bottom of this module.

A dataset's methods take the recipe's ``data`` section; the evaluation's an
:class:`~tar_rl.collectors.suite.EvalSpec`.
"""

from __future__ import annotations

from tar_rl.data import DemoDataset
from tar_rl.objectives.registry import Registry

from .dmc import DMControlSuite
from .libero import LiberoSuite
from .metaworld.suite import MetaWorldSuite
from .suite import EvalSpec, Suite

__all__ = ["SUITES", "EvalSpec", "Suite", "suite_for"]


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


# The suites, in the order their names are listed.
for _suite in (MetaWorldSuite(), DMControlSuite(), LiberoSuite()):
    SUITES.register(_suite.name, _suite)
