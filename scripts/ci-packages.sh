#!/usr/bin/env bash
# Installs the Debian packages the test suite uses beyond Python: systemd-analyze (the unit's
# sandbox score), pdftoppm (rasterising printable markers) and chromium (the preview page in a
# real headless browser). Skips what is already there.
set -euo pipefail
need=()
command -v systemd-analyze >/dev/null 2>&1 || need+=(systemd)
command -v pdftoppm >/dev/null 2>&1 || need+=(poppler-utils)
command -v chromium >/dev/null 2>&1 || need+=(chromium)
if [ ${#need[@]} -eq 0 ]; then
  echo "ci-packages.sh: nothing to install"
  exit 0
fi
sudo=""
[ "$(id -u)" -ne 0 ] && sudo="sudo"
echo "ci-packages.sh: installing ${need[*]}"
$sudo apt-get update -qq
DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends "${need[@]}" >/dev/null
