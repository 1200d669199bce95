#!/usr/bin/env bash
# Sets up a virtual environment and runs the linter and the test suite.
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
exec "$venv/bin/python" -m pytest "$@"
