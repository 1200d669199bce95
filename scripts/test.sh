#!/usr/bin/env bash
# Sets up a virtual environment and runs the linter, the formatter's check, the type checker and
# the test suite.
#   scripts/test.sh [--stack newest|bookworm] [pytest arguments...]
set -euo pipefail
cd "$(dirname "$0")/.."
stack=newest
if [ "${1:-}" = "--stack" ]; then stack="$2"; shift 2; fi
venv=$(scripts/venv.sh --stack "$stack" --test)
"$venv/bin/python" - <<'PY'
import platform, numpy, cv2
print(f"python {platform.python_version()} on {platform.machine()}, numpy {numpy.__version__}, opencv {cv2.__version__}")
PY
"$venv/bin/python" -m ruff check pose_daemon tests scripts
"$venv/bin/python" -m ruff format --check pose_daemon tests scripts
# The type checker over pose_daemon/ (settings and the allowlist: pyproject.toml [tool.mypy]),
# against each stack's own stubs: numpy 1.24's say what exists on the Pi. One cache per stack.
"$venv/bin/python" -m mypy --cache-dir "$venv/.mypy_cache"
exec "$venv/bin/python" -m pytest "$@"
