#!/usr/bin/env bash
# The LeRobot plugin's tests in their own Python 3.12 environment, .venv-lerobot/ at the repository root, built (or
# updated) first by env.sh, the install command of docs/lerobot.md. Some tests run tar-rl's side of the page's commands
# (collecting MetaWorld demonstrations) in tar-rl's own environment, .venv/ (the README's test command makes it first).
# Then tar-rl's tests that need both environments (the evaluator bridge, benchmarks/lerobot_pilot.py), which tar-rl's
# own pytest run skips while .venv-lerobot/ does not exist yet.
set -euo pipefail
cd "$(dirname "$0")/.."
lerobot_policy_tar/env.sh test
.venv-lerobot/bin/python -m pytest lerobot_policy_tar
.venv/bin/python -m pytest tests/experiments/test_lerobot_pilot.py
