#!/usr/bin/env bash
# The LeRobot plugin's tests in their own Python 3.12 environment, .venv-lerobot/ at the repository root (LeRobot 0.6
# needs Python >= 3.12 and torch < 2.12; tar-rl is installed into it without its dependencies: TAR's math imports
# torch alone). Builds the environment on first use; docs/lerobot.md describes it.
set -euo pipefail
cd "$(dirname "$0")/.."
python="${PYTHON312:-python3.12}"
if ! "$python" -c 'import sys; assert sys.version_info >= (3, 12)' 2>/dev/null && command -v pyenv >/dev/null; then
  python="$(pyenv root)/versions/$(pyenv versions --bare | grep -E '^3\.12(\.[0-9]+)?$' | tail -1)/bin/python"
fi
"$python" -c 'import sys; assert sys.version_info >= (3, 12)' 2>/dev/null \
  || { echo "lerobot_policy_tar/test.sh: needs Python 3.12 (python3.12, pyenv, or PYTHON312=/path/to/python)" >&2; exit 1; }
[ -x .venv-lerobot/bin/python ] || "$python" -m venv .venv-lerobot
.venv-lerobot/bin/pip install -e './lerobot_policy_tar[test]' && .venv-lerobot/bin/pip install --no-deps -e .
.venv-lerobot/bin/python -m pytest lerobot_policy_tar
