#!/usr/bin/env bash
# Runs scripts/test.sh N times in a row, the two stacks alternately (newest, bookworm, ...),
# under an added stress-like load, and stops at the first failure, keeping its log.
#   scripts/stress-suite.sh [--hogs K] [--mem-mb M] [--io] [--logs DIR] [--first S | --stack S] N [pytest arguments...]
# --hogs K     busy loops (one Python process each spinning `while 1: pass`); default one per core
# --mem-mb M   one more process that holds M MB and keeps touching every page of it (default 0: none)
# --io         one more process that keeps writing, syncing and deleting a 64 MB file in the log folder
# --logs DIR   where each run's log goes (default: a new folder under ${TMPDIR:-/tmp})
# --first S    the stack of the first run (default newest)
# --stack S    every run on stack S (newest or bookworm), not alternately: two of these, one per
#              stack, run side by side load each other as well
# A flaky test shows up as a failure here: each one is a test that measures time through a clock
# it does not control, or a bound a loaded machine can break -- or a real bug. Prints one line per
# run (stack, result, seconds) and a summary; exits 1 at the first failed run, 0 when all passed.
set -euo pipefail
cd "$(dirname "$0")/.."
hogs=$(nproc)
mem_mb=0
io=0
logs=""
stack=newest
only=0
while [ $# -gt 0 ]; do
  case "$1" in
    --hogs) hogs="$2"; shift 2 ;;
    --mem-mb) mem_mb="$2"; shift 2 ;;
    --io) io=1; shift ;;
    --logs) logs="$2"; shift 2 ;;
    --first) stack="$2"; shift 2 ;;
    --stack) stack="$2"; only=1; shift 2 ;;
    *) break ;;
  esac
done
if [ $# -lt 1 ] || ! [[ "$1" =~ ^[1-9][0-9]*$ ]]; then
  echo "stress-suite.sh: usage: scripts/stress-suite.sh [--hogs K] [--mem-mb M] [--io] [--logs DIR] [--first S | --stack S] N [pytest arguments...]" >&2
  exit 2
fi
case "$stack" in
  newest | bookworm) ;;
  *) echo "stress-suite.sh: --first and --stack take newest or bookworm" >&2; exit 2 ;;
esac
runs="$1"
shift
if [ -z "$logs" ]; then logs=$(mktemp -d "${TMPDIR:-/tmp}/stress-suite.XXXXXX"); fi
mkdir -p "$logs"

pids=()
stop_load() {
  for p in "${pids[@]}"; do kill "$p" 2>/dev/null || true; done
  for p in "${pids[@]}"; do wait "$p" 2>/dev/null || true; done
  pids=()
  rm -f "$logs/io-hog.tmp"
}
trap stop_load EXIT
trap 'exit 130' INT
trap 'exit 143' TERM

# Each hog is started with `&` and its id taken from $! (never through a command substitution,
# which would wait for the background process's output and hang).
for _ in $(seq 1 "$hogs"); do
  python3 -c 'while 1: pass' >/dev/null 2>&1 &
  pids+=($!)
done
if [ "$mem_mb" -gt 0 ]; then
  python3 -c '
import sys, time
b = bytearray(int(sys.argv[1]) << 20)
while 1:
    for i in range(0, len(b), 4096):
        b[i] = (b[i] + 1) & 255
    time.sleep(0.05)
' "$mem_mb" >/dev/null 2>&1 &
  pids+=($!)
fi
if [ "$io" = 1 ]; then
  python3 -c '
import os, sys
path = os.path.join(sys.argv[1], "io-hog.tmp")
chunk = os.urandom(1 << 20)
while 1:
    with open(path, "wb") as f:
        for _ in range(64):
            f.write(chunk)
        f.flush()
        os.fsync(f.fileno())
    os.unlink(path)
' "$logs" >/dev/null 2>&1 &
  pids+=($!)
fi
if [ "$only" = 1 ]; then order="all on $stack"; else order="first on $stack"; fi
echo "stress-suite: $runs runs, $order; load: $hogs busy loops, ${mem_mb} MB memory hog, io hog $io; logs in $logs"

summary=()
passed=0
declare -A streak=([newest]=0 [bookworm]=0)
status=0
for i in $(seq 1 "$runs"); do
  log="$logs/run-$i-$stack.log"
  start=$(date +%s)
  if scripts/test.sh --stack "$stack" -q -p no:cacheprovider "$@" >"$log" 2>&1; then
    result=pass
    passed=$((passed + 1))
    streak[$stack]=$((streak[$stack] + 1))
  else
    result=FAIL
  fi
  seconds=$(($(date +%s) - start))
  line="run $i/$runs $stack $result ${seconds}s ($(grep -v '^[[:space:]]*$' "$log" | tail -n 1))"
  summary+=("$line")
  echo "$line"
  if [ "$result" = FAIL ]; then
    echo "stress-suite: run $i failed on $stack; its log: $log"
    grep -E '^(FAILED|ERROR) ' "$log" || tail -n 20 "$log"
    status=1
    break
  fi
  if [ "$only" = 0 ]; then
    if [ "$stack" = newest ]; then stack=bookworm; else stack=newest; fi
  fi
done
stop_load
echo "stress-suite: summary: $passed of ${#summary[@]} runs passed (of $runs asked); passes in a row: newest ${streak[newest]}, bookworm ${streak[bookworm]}"
for line in "${summary[@]}"; do echo "  $line"; done
exit "$status"
