"""The benchmarks and studies of tar-rl: ``studies`` (the experiments as declarations on one harness), ``analysis``
(the analyses of their runs) and the ``bench_*.py`` micro-benchmarks."""
