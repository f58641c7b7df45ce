"""The experiments as declarations on one harness: ``python -m benchmarks.studies STUDY plan | run STAGE | table |
collect``.

* :mod:`.core`: a scale (the overrides every run shares), an arm (a name and overrides), a grid (arms x seeds
  over a base), run specs and the planner that composes them;
* :mod:`.stages`: a stage as a declaration (its grids, gates, records), a study as its stages and its table, and
  the one function that plans and runs any stage;
* :mod:`.sweep`: the resumable, parallel sweep of a stage's runs;
* :mod:`.records`: provenance, ``collect``, the records of a plan once its runs started, reproduction checks;
* :mod:`.compare`: the paired comparison of arms with a baseline (Holm, MDE, the same-commit-and-machine check)
  and the fit and weight statistics of runs;
* :mod:`.writers`: number formats, the markdown tables shared by the studies, atomic output files;
* :mod:`.cli`: the command line;
* the studies: :mod:`.regimes` (R1-R5), :mod:`.tuning` (TAR's tuning in R3), :mod:`.baselines` (the literature's
  weightings in R3), :mod:`.why_act` (R6), :mod:`.flow_signal` (R7) and :mod:`.paper` (the paper's experiments).
"""
