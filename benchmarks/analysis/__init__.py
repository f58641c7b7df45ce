"""Analyses of the studies' runs: R3 and the chunked heads' R4 and R5 diagnosed (:mod:`.pairs`, :mod:`.diagnosis`,
:mod:`.dims`), how much of TAR's weighting a head's random draw decides (:mod:`.noise`), and rebuilding a finished
run's policy and objective (:mod:`.rebuild`); ``python -m benchmarks.analysis diagnosis [--regime R4] | dims |
noise``. The figures and TAR's weight mass per demonstration phase, which the studies draw too, are in
:mod:`tar_rl.report` (``figures``, ``weight_phases``)."""
