#!/usr/bin/env bash
# Checks the systemd unit: syntax (systemd-analyze verify, where it can run) and the sandbox's
# exposure score (systemd-analyze security --offline=true), which must be 2.5 or better.
# Installs Debian's systemd package when systemd-analyze is missing (needs root or sudo).
#   scripts/check-unit.sh [UNIT] [--max SCORE]
set -euo pipefail
cd "$(dirname "$0")/.."
unit=systemd/pose-daemon.service
max=2.5
while [ $# -gt 0 ]; do
  case "$1" in
    --max) max="$2"; shift 2 ;;
    -*) echo "check-unit.sh: unknown option $1" >&2; exit 2 ;;
    *) unit="$1"; shift ;;
  esac
done
if ! command -v systemd-analyze >/dev/null 2>&1; then
  sudo=""
  [ "$(id -u)" -ne 0 ] && sudo="sudo"
  echo "check-unit.sh: installing systemd for systemd-analyze" >&2
  $sudo apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq systemd >/dev/null
fi
# Syntax: unknown keys and bad values are errors; a missing ExecStart binary (the daemon is not
# installed here) is not.
verify=$(SYSTEMD_LOG_LEVEL=warning systemd-analyze verify --man=no "$unit" 2>&1 || true)
problems=$(printf '%s\n' "$verify" | grep -v -e 'is not executable' -e '^$' || true)
if [ -n "$problems" ]; then
  printf '%s\n' "$problems" >&2
  echo "check-unit.sh: $unit: systemd-analyze verify reported problems" >&2
  exit 1
fi
out=$(systemd-analyze security --offline=true --no-pager "$unit" 2>&1) || {
  printf '%s\n' "$out" >&2
  echo "check-unit.sh: systemd-analyze security failed on $unit" >&2
  exit 1
}
score=$(printf '%s\n' "$out" | sed -n 's/.*Overall exposure level for [^:]*: \([0-9.]*\).*/\1/p' | tail -1)
if [ -z "$score" ]; then
  printf '%s\n' "$out" >&2
  echo "check-unit.sh: no exposure level in the output of systemd-analyze security" >&2
  exit 1
fi
if awk -v s="$score" -v m="$max" 'BEGIN { exit !(s <= m) }'; then
  echo "check-unit.sh: $unit: exposure $score (at most $max): ok"
else
  printf '%s\n' "$out" | grep '✗' >&2 || true
  echo "check-unit.sh: $unit: exposure $score is worse than $max" >&2
  exit 1
fi
