#!/usr/bin/env bash
# Builds the LeRobot plugin's Python 3.12 environment, .venv-lerobot/ at the repository root (docs/lerobot.md): LeRobot
# 0.6 needs Python >= 3.12 and torch < 2.12, and tar-rl is installed into it without its dependencies (TAR's math
# imports torch alone). About 5.8 GB; an existing environment is reused. Python 3.12 is python3.12 on the PATH,
# pyenv's newest 3.12 (also where pyenv's python3.12 shim is not active) or PYTHON312=/path/to/python3.12.
# An argument names the plugin's extras to install too (test.sh: test).
set -euo pipefail
cd "$(dirname "$0")/.."
is_312() { "$1" -c 'import sys; assert sys.version_info >= (3, 12)' >/dev/null 2>&1; }
python="${PYTHON312:-python3.12}"
if ! is_312 "$python" && [ -z "${PYTHON312:-}" ] && command -v pyenv >/dev/null; then
  version="$(pyenv versions --bare | grep -E '^3\.12(\.[0-9]+)?$' | sort -V | tail -1 || true)"
  [ -n "$version" ] && python="$(pyenv root)/versions/$version/bin/python"
fi
is_312 "$python" || {
  echo "lerobot_policy_tar/env.sh: needs Python 3.12 (python3.12 on the PATH, pyenv install 3.12, or PYTHON312=/path/to/python3.12)" >&2
  exit 1
}
[ -x .venv-lerobot/bin/python ] || "$python" -m venv .venv-lerobot
extras="${1:+[$1]}"
.venv-lerobot/bin/pip install -e "./lerobot_policy_tar$extras" && .venv-lerobot/bin/pip install --no-deps -e .
