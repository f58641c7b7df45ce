"""``python -m benchmarks.studies``: the studies' command line (:mod:`benchmarks.studies.cli`)."""

from benchmarks.studies.cli import main

raise SystemExit(main())
