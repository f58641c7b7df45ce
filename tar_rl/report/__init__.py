"""``tar-rl report``: read training-run directories, print and plot comparisons.

* :mod:`~tar_rl.report.load`: :func:`load_run` reads one run directory into a :class:`Run`, its final
  metrics recomputed from its evaluation rollouts; :func:`expand_run_dirs` turns a sweep folder into
  its run directories.
* :mod:`~tar_rl.report.stats`: :func:`compare` pools finished runs over seeds, one row per (policy,
  objective), with the paired difference of each objective to ``uniform``; :func:`paired_table`,
  :func:`paired_t`, :func:`holm` and :func:`min_detectable_effect` are the paired statistics over
  matched seeds; :func:`run_percent` is one run's final metrics in percent.
* :mod:`~tar_rl.report.tables`: the text tables the command prints (:func:`runs_table`, ...).
* :mod:`~tar_rl.report.plots`: :func:`plot_success_vs_neps` (the paper's Fig. 3),
  :func:`plot_group_bars` and :func:`plot_weights` (Fig. 5), :func:`plot_paired_deltas` (per-seed paired
  differences with their mean and 95% CI; :func:`paired_summary`, the numbers it draws), and the figure helpers.
* :mod:`~tar_rl.report.phases`: :data:`PHASES`, :func:`first_gripper_close` and :func:`phase_labels`,
  a demonstration's phases from its gripper action; :func:`~tar_rl.report.phases.switch_steps` and
  :func:`~tar_rl.report.phases.label_steps`, its gripper switches and the labels of many demonstrations.
* :mod:`~tar_rl.report.figures`: the studies' figures (Fig. 3(c), Fig. 4, the critical windows, Fig. 5 with
  phases, the budget curve, the sensitivity grid), built on :mod:`~tar_rl.report.plots`.
* :mod:`~tar_rl.report.weight_phases`: TAR's weight mass per demonstration phase and the critical windows.
* :mod:`~tar_rl.report.cli`: :func:`main`, the body of ``tar-rl report RUN_DIR... [--out DIR]``.

The paper experiments' own tables (Tables I and III) are in ``benchmarks/studies``, built on these.
"""

from __future__ import annotations

from tar_rl.report.cli import main
from tar_rl.report.load import Run, expand_run_dirs, load_run, run_file
from tar_rl.report.phases import PHASES, first_gripper_close, phase_labels
from tar_rl.report.plots import (
    paired_summary,
    plot_group_bars,
    plot_paired_deltas,
    plot_success_vs_neps,
    plot_weights,
)
from tar_rl.report.stats import (
    BASELINE,
    OBJECTIVE_ORDER,
    PAIRED_COLUMNS,
    compare,
    holm,
    min_detectable_effect,
    paired_t,
    paired_table,
    run_percent,
)
from tar_rl.report.tables import runs_table

__all__ = [
    "BASELINE",
    "OBJECTIVE_ORDER",
    "PAIRED_COLUMNS",
    "PHASES",
    "Run",
    "compare",
    "expand_run_dirs",
    "first_gripper_close",
    "holm",
    "load_run",
    "main",
    "min_detectable_effect",
    "paired_summary",
    "paired_t",
    "paired_table",
    "phase_labels",
    "plot_group_bars",
    "plot_paired_deltas",
    "plot_success_vs_neps",
    "plot_weights",
    "run_file",
    "run_percent",
    "runs_table",
]
