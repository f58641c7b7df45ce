#!/usr/bin/env bash
# The LeRobot plugin's tests in their own Python 3.12 environment, .venv-lerobot/ at the repository root, built (or
# updated) first by env.sh, the install command of docs/lerobot.md. Some tests run tar-rl's side of the page's commands
# (collecting MetaWorld demonstrations) in tar-rl's own environment, .venv/ (the README's test command makes it first).
set -euo pipefail
cd "$(dirname "$0")/.."
lerobot_policy_tar/env.sh test
.venv-lerobot/bin/python -m pytest lerobot_policy_tar
