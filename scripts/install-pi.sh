#!/usr/bin/env bash
# Installs pose-daemon as a systemd service on Raspberry Pi OS Bookworm (32- or 64-bit).
#   sudo scripts/install-pi.sh [--dry-run] [--no-serial] [--no-start] [--prefix DIR] [--root DIR]
# - apt: python3-picamera2, python3-opencv, python3-numpy, python3-serial (+ venv, pip, lxml)
# - a venv with --system-site-packages (apt's OpenCV, numpy and picamera2 are used as they are;
#   pip cannot see apt's OpenCV as opencv-python-headless, hence pip install --no-deps)
# - the system user pose-daemon (groups video, dialout), config in /etc/pose-daemon/ (0640
#   root:pose-daemon: it may hold the signing key),
#   the unit in /etc/systemd/system/, enabled and (re)started
# - the serial console freed so the flight controller link can use /dev/serial0
# Idempotent: run it again after a `git pull` to update. --dry-run prints what it would do.
# --root DIR prefixes every file path (for tests); --prefix is the install dir (/opt/pose-daemon).
set -euo pipefail
repo=$(cd "$(dirname "$0")/.." && pwd)

dry_run=0
serial=1
start=1
prefix=/opt/pose-daemon
root=""
while [ $# -gt 0 ]; do
  case "$1" in
    --dry-run) dry_run=1; shift ;;
    --no-serial) serial=0; shift ;;
    --no-start) start=0; shift ;;
    --prefix) prefix="$2"; shift 2 ;;
    --root) root="${2%/}"; shift 2 ;;
    -h|--help) sed -n '2,12p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
    *) echo "install-pi.sh: unknown argument $1 (see --help)" >&2; exit 2 ;;
  esac
done

user=pose-daemon
venv="$prefix/venv"
etc="$root/etc/pose-daemon"
unit_dir="$root/etc/systemd/system"
apt_packages="python3-venv python3-pip python3-picamera2 python3-opencv python3-numpy python3-serial python3-lxml"

say() { printf '%s\n' "$*"; }
# Runs a command, or prints it under --dry-run.
run() {
  local shown
  shown=$(printf '%q ' "$@")
  if [ "$dry_run" = 1 ]; then
    say "would run: ${shown% }"
  else
    say "+ ${shown% }"
    "$@"
  fi
}

if [ "$dry_run" = 0 ] && [ "$(id -u)" -ne 0 ]; then
  echo "install-pi.sh: run as root (sudo), or with --dry-run to see what it would do" >&2
  exit 2
fi

# --- the system
codename=$( (. "$root/etc/os-release" 2>/dev/null && echo "${VERSION_CODENAME:-unknown}") || echo unknown)
arch=$(dpkg --print-architecture 2>/dev/null || uname -m)
say "== pose-daemon install: $codename on $arch, prefix $prefix$([ "$dry_run" = 1 ] && echo ', dry run')"
case "$codename" in
  bookworm) ;;
  *) say "note: made for Raspberry Pi OS Bookworm; this is $codename, carrying on" ;;
esac
case "$arch" in
  armhf|arm64|armv7l|aarch64) ;;
  *) say "note: $arch is not a Raspberry Pi architecture (armhf, arm64)" ;;
esac

# --- 1. packages from apt
# Python before 3.11 (Bullseye) has no tomllib: Debian's python3-tomli reads the config.
if ! python3 -c 'import sys; sys.exit(sys.version_info < (3, 11))' 2>/dev/null; then
  apt_packages="$apt_packages python3-tomli"
fi
say "== apt packages: $apt_packages"
run apt-get update
# shellcheck disable=SC2086  # the list is meant to split
run env DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends $apt_packages

# --- 2. the service user
say "== service user $user (groups video, dialout)"
if id -u "$user" >/dev/null 2>&1; then
  say "user $user exists"
else
  run useradd --system --user-group --home-dir /var/lib/pose-daemon --no-create-home \
    --shell /usr/sbin/nologin --comment "pose-daemon service" "$user"
fi
run usermod -a -G video,dialout "$user"

# --- 3. the venv and the project
say "== venv $venv (with the system site packages)"
if [ -x "$venv/bin/python" ]; then
  say "venv exists"
else
  run python3 -m venv --system-site-packages "$venv"
fi
run "$venv/bin/python" -m pip install --disable-pip-version-check --no-deps --upgrade pymavlink
run "$venv/bin/python" -m pip install --disable-pip-version-check --no-deps --upgrade "$repo"
run "$venv/bin/pose-daemon" --version

# --- 4. the configuration
# The config may hold secrets (a MAVLink signing_key): readable by root and the service's
# group only, in a folder others cannot list.
say "== configuration $etc/pose-daemon.toml (0640 root:$user, folder 0750)"
run install -d -m 0750 -o root -g "$user" "$etc"
if [ -e "$etc/pose-daemon.toml" ]; then
  say "keeping the existing $etc/pose-daemon.toml (the new default is $repo/config/pose-daemon.toml)"
  # An older install left it 0644: close it, keeping the user's edits.
  run chown root:"$user" "$etc/pose-daemon.toml"
  run chmod 0640 "$etc/pose-daemon.toml"
else
  run install -m 0640 -o root -g "$user" "$repo/config/pose-daemon.toml" "$etc/pose-daemon.toml"
fi

# --- 5. the serial console off, the UART on
if [ "$serial" = 1 ]; then
  say "== serial port for the flight controller (/dev/serial0)"
  if [ -z "$root" ] && command -v raspi-config >/dev/null 2>&1; then
    run raspi-config nonint do_serial_cons 1   # 1 = no login console on the serial port
    run raspi-config nonint do_serial_hw 0     # 0 = the UART enabled
  else
    boot="$root/boot/firmware"
    [ -d "$boot" ] || boot="$root/boot"
    cmdline="$boot/cmdline.txt"
    if [ -f "$cmdline" ] && grep -Eq 'console=(serial0|ttyAMA0|ttyS0)(,[0-9]+)? ?' "$cmdline"; then
      run sed -i -E 's/console=(serial0|ttyAMA0|ttyS0)(,[0-9]+)? ?//g' "$cmdline"
    else
      say "no serial console in $cmdline"
    fi
    config_txt="$boot/config.txt"
    if [ ! -f "$config_txt" ]; then
      say "no $config_txt: not a Raspberry Pi boot partition, UART left alone"
    elif grep -q '^enable_uart=1' "$config_txt"; then
      say "UART already enabled in $config_txt"
    else
      run sed -i -e '$a enable_uart=1' "$config_txt"
    fi
  fi
  say "a reboot makes serial port changes take effect"
fi

# --- 6. the unit
say "== systemd unit $unit_dir/pose-daemon.service"
run install -m 0644 "$repo/systemd/pose-daemon.service" "$unit_dir/pose-daemon.service"
run systemctl daemon-reload
run systemctl enable pose-daemon.service
if [ "$start" = 1 ]; then
  run systemctl restart pose-daemon.service
fi
say "== done: journalctl -u pose-daemon -f shows the status lines; edit $etc/pose-daemon.toml, then"
say "   pose-daemon check-config --syntax-only /etc/pose-daemon/pose-daemon.toml && sudo systemctl restart pose-daemon"
