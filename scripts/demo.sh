#!/usr/bin/env bash
# Sets up .venv and runs the main job: the daemon on the demo config (a rendered camera moving
# in front of a wall marker), poses as JSON lines on stdout and MAVLink to udpout:127.0.0.1:14550
# (open QGroundControl or `mavproxy.py --master=udpin:127.0.0.1:14550 --no-state` to see them
# there; --no-state: no mav.tlog left in the current folder).
#   scripts/demo.sh [--seconds N]   (default: until Ctrl-C)
set -euo pipefail
cd "$(dirname "$0")/.."
seconds=""
if [ "${1:-}" = "--seconds" ]; then seconds="$2"; shift 2; fi
venv=$(scripts/venv.sh)
if [ -z "$seconds" ]; then
  exec "$venv/bin/pose-daemon" run --config config/demo.toml "$@"
fi
# SIGTERM after N seconds: the daemon stops cleanly and exits 0.
exec timeout --preserve-status --signal=TERM "$seconds" "$venv/bin/pose-daemon" run --config config/demo.toml "$@"
