"""Where the repository is, for tests that read its files (benchmarks, documentation, examples)."""

from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
