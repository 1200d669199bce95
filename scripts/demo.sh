#!/usr/bin/env bash
# Sets up .venv and runs the main job.
set -euo pipefail
cd "$(dirname "$0")/.."
venv=$(scripts/venv.sh)
exec "$venv/bin/pose-daemon" paper table1 "$@"
