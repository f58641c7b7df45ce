"""Analyses of the studies' runs: the phases of a demonstration and TAR's weight mass in them (:mod:`.phases`), the
figures (:mod:`.figures`), and R3 and the chunked heads' R4 and R5 diagnosed (:mod:`.pairs`, :mod:`.diagnosis`,
:mod:`.dims`; ``python -m benchmarks.analysis diagnosis [--regime R4] | dims``)."""
