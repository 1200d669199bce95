#!/usr/bin/env bash
# Creates (idempotently) a virtual environment with pose-daemon installed in editable mode.
#   scripts/venv.sh [--stack newest|bookworm] [--test]
# newest:   the newest releases of the dependencies (.venv)
# bookworm: the versions Raspberry Pi OS Bookworm ships as apt packages (.venv-bookworm):
#           numpy 1.24 and OpenCV 4.6 with its contrib modules (Debian's python3-opencv
#           has cv2.aruco with the pre-4.7 API).
# Works with only python3 and pip: on Debian without python3-venv the venv is made without
# its own pip and uses the system's.
set -euo pipefail
cd "$(dirname "$0")/.."
stack=newest
extras=""
while [ $# -gt 0 ]; do
  case "$1" in
    --stack) stack="$2"; shift 2 ;;
    --test) extras="[test]"; shift ;;
    *) echo "venv.sh: unknown argument $1" >&2; exit 2 ;;
  esac
done
case "$stack" in
  newest) venv=.venv ;;
  bookworm) venv=.venv-bookworm ;;
  *) echo "venv.sh: --stack must be newest or bookworm" >&2; exit 2 ;;
esac
python=${PYTHON:-python3}
if [ ! -x "$venv/bin/python" ]; then
  if ! "$python" -m venv "$venv" >/dev/null 2>&1; then
    rm -rf "$venv"
    "$python" -m venv --without-pip --system-site-packages "$venv"
  fi
fi
pip=("$venv/bin/python" -m pip --disable-pip-version-check -q)
# One stamp per extras set of this pyproject.toml and this script, so that demo.sh (no extras)
# and test.sh ([test]) do not reinstall each other's; [test] holds all that the plain one has.
base="$venv/.installed-$(cat pyproject.toml scripts/venv.sh | cksum | cut -d' ' -f1)"
stamp="$base$extras"
if [ -e "$stamp" ] || { [ -z "$extras" ] && [ -e "$base[test]" ]; }; then
  echo "$venv"
  exit 0
fi
if [ "$stack" = bookworm ]; then
  "${pip[@]}" install "numpy==1.24.*" "opencv-contrib-python-headless==4.6.0.66" \
    "pymavlink>=2.4.30" "pyserial==3.5" "tomli>=1.1; python_version < '3.11'"
  "${pip[@]}" install --no-deps -e .
  if [ -n "$extras" ]; then
    # numpy pinned again: a newer matplotlib would otherwise pull numpy 2. scipy 1.10 is
    # Bookworm's (python3-scipy), for `map build`.
    "${pip[@]}" install "numpy==1.24.*" "pytest>=7" "ruff>=0.4" "mypy>=1.10" "matplotlib>=3.5" "scipy==1.10.*"
  fi
else
  "${pip[@]}" install --upgrade -e ".$extras"
fi
if [ -n "$extras" ]; then
  # A real ground station for the MAVLink tests; see pyproject.toml for why --no-deps.
  "${pip[@]}" install --no-deps "MAVProxy>=1.8"
fi
for old in "$venv"/.installed-*; do  # an older pyproject.toml or script's stamps
  case "$old" in "$base" | "$base[test]") ;; *) rm -f "$old" ;; esac
done
touch "$stamp"
echo "$venv"
