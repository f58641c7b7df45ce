"""The benchmarks and studies of tar-rl: ``studies`` (the experiments as declarations on one harness; ``protocol``
holds what their plans share), ``analysis`` (the analyses of their runs, above the studies: the studies import
nothing from it) and the speed micro-benchmarks ``bench_*`` (with ``common`` and ``head_steps``), each run from the
repository root as ``python -m benchmarks.<name>``."""
