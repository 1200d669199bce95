#!/usr/bin/env bash
# Runs part of the test suite on the Raspberry Pi 2's own software stack: Debian bookworm
# armhf's python3.11, numpy, OpenCV and pyserial, under QEMU user-mode emulation (armv7l,
# 32-bit default integers, OpenCV 4.6 with the old aruco API).
#   scripts/pi-stack.sh [--build-only] [pytest arguments...]
# With no pytest arguments it runs the tests marked `pi` (`-m pi` over the test files that
# use the marker). The stack is built once and cached in
# ${PI_STACK_CACHE:-$HOME/.cache/pose-daemon-pi-stack}; a re-run with nothing to build takes
# seconds. The first build runs as root. Needs on the host: qemu-user-static (installed with apt-get as root or with sudo
# when missing), apt-get, dpkg-deb, python3 with pip, and the Debian package archive and PyPI
# reachable for the first build.
set -euo pipefail
cd "$(dirname "$0")/.."
repo=$(pwd)
t_start_s=$(date +%s)

build_only=0
if [ "${1:-}" = "--build-only" ]; then build_only=1; shift; fi

cache=${PI_STACK_CACHE:-$HOME/.cache/pose-daemon-pi-stack}
packages="libc-bin cython3 python3 python3-numpy python3-opencv python3-serial python3-pip python3-venv python3-pytest"
pymavlink_req=${PI_STACK_PYMAVLINK:-pymavlink==2.4.50}
# libc-bin (Essential, so in no closure) brings ldconfig; cython3 lets pymavlink's setup.py
# run under emulation when the host cannot build its wheel.
# Bump when the way the root or the venv is made changes, so cached stacks get rebuilt.
layout_version=5
root=$cache/root
venv=$cache/venv
aptdir=$cache/apt

die() {
  echo "pi-stack: cannot build the emulated Raspberry Pi OS stack: $*" >&2
  exit 1
}

log() { echo "pi-stack: $*"; }

# --- host emulator -----------------------------------------------------------------------
if ! command -v qemu-arm-static >/dev/null 2>&1; then
  sudo=""
  [ "$(id -u)" = 0 ] || sudo="sudo -n"
  command -v apt-get >/dev/null 2>&1 ||
    die "qemu-arm-static not found and no apt-get to install qemu-user-static with"
  log "installing qemu-user-static on the host"
  mkdir -p "$cache"
  # Without recommends: binfmt-support would make the host run ARM programs by itself.
  if ! $sudo env DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends \
    qemu-user-static >"$cache/qemu-install.log" 2>&1; then
    $sudo apt-get update -q >>"$cache/qemu-install.log" 2>&1 || true
    $sudo env DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends \
      qemu-user-static >>"$cache/qemu-install.log" 2>&1 ||
      die "apt-get install qemu-user-static failed (as root or with sudo; log: $cache/qemu-install.log)"
  fi
fi
for tool in apt-get dpkg-deb tar python3; do
  command -v "$tool" >/dev/null 2>&1 || die "the host has no $tool"
done
qemu=$(command -v qemu-arm-static)

mkdir -p "$cache"
exec 9>"$cache/.lock"
if command -v flock >/dev/null 2>&1; then flock 9; fi

# Modules are byte-compiled as they are first imported and the result kept in the cache
# (Debian's maintainer scripts, which would compile everything, do not run here).
unset PYTHONDONTWRITEBYTECODE

# Runs a program of the armhf root under emulation, as a Cortex-A7 (the Pi 2's core).
emu() { QEMU_LD_PREFIX="$root" QEMU_CPU=cortex-a7 "$qemu" "$@"; }

# --- the armhf root filesystem -----------------------------------------------------------
root_stamp="$cache/.root-$(echo "$layout_version $packages" | cksum | cut -d' ' -f1)"
if [ ! -e "$root_stamp" ]; then
  t0=$(date +%s)
  # ldconfig -r chroots into the root; the rest would work as any user.
  [ "$(id -u)" = 0 ] || die "building the armhf root needs root (ldconfig -r chroots into it); run once as root"
  log "building the Debian bookworm armhf root in $root"
  rm -rf "$root" "$venv" "$aptdir" "$cache"/.root-* "$cache"/.venv-*
  mkdir -p "$aptdir"/etc/apt.conf.d "$aptdir"/etc/preferences.d "$aptdir"/etc/sources.list.d \
    "$aptdir"/state/lists/partial "$aptdir"/cache/archives/partial
  : >"$aptdir/state/status"
  # The host's package sources, so the same archive (or mirror) serves the armhf packages;
  # files with another ending (disabled sources) are skipped as apt itself skips them.
  nsrc=0
  if [ -s /etc/apt/sources.list ]; then
    cp /etc/apt/sources.list "$aptdir/etc/sources.list"
    nsrc=1
  fi
  for f in /etc/apt/sources.list.d/*.list /etc/apt/sources.list.d/*.sources; do
    [ -e "$f" ] || continue
    cp "$f" "$aptdir/etc/sources.list.d/"
    nsrc=$((nsrc + 1))
  done
  [ "$nsrc" -gt 0 ] || die "the host has no apt sources to copy (/etc/apt/sources.list*)"
  # The host's download settings (proxy, validity of a snapshot archive's Release files),
  # but none of its hooks: only files that set Acquire:: options and run nothing.
  for f in /etc/apt/apt.conf /etc/apt/apt.conf.d/*; do
    [ -f "$f" ] || continue
    if grep -q 'Acquire::' "$f" && ! grep -qiE 'Invoke|Pre-Install|Dir::|Architecture' "$f"; then
      cp "$f" "$aptdir/etc/apt.conf.d/host-$(basename "$f")"
    fi
  done
  cat >"$aptdir/apt.conf" <<EOF
APT::Architecture "armhf";
APT::Architectures { "armhf"; };
APT::Install-Recommends "false";
APT::Sandbox::User "root";
Acquire::Languages "none";
Acquire::Retries "3";
Dir::Etc "$aptdir/etc";
Dir::Etc::SourceList "$aptdir/etc/sources.list";
Dir::Etc::SourceParts "$aptdir/etc/sources.list.d";
Dir::Etc::Parts "$aptdir/etc/apt.conf.d";
Dir::Etc::PreferencesParts "$aptdir/etc/preferences.d";
Dir::Etc::Trusted "/etc/apt/trusted.gpg";
Dir::Etc::TrustedParts "/etc/apt/trusted.gpg.d";
Dir::State "$aptdir/state";
Dir::State::Lists "$aptdir/state/lists";
Dir::State::status "$aptdir/state/status";
Dir::Cache "$aptdir/cache";
Dir::Cache::Archives "$aptdir/cache/archives";
Dir::Log "$aptdir";
EOF
  export APT_CONFIG="$aptdir/apt.conf"
  # A source without armhf packages (a vendor's amd64-only repository, a failing security
  # index) only warns: the install below says whether what is needed was found.
  apt-get update -q >"$aptdir/update.log" 2>&1 || log "apt-get update reported errors (see $aptdir/update.log); carrying on"
  # shellcheck disable=SC2086
  if ! apt-get install -y -q --download-only $packages >"$aptdir/download.log" 2>&1; then
    tail -n 20 "$aptdir/download.log" >&2
    die "downloading the armhf packages failed (log: $aptdir/download.log)"
  fi
  unset APT_CONFIG
  ndebs=$(find "$aptdir/cache/archives" -maxdepth 1 -name '*.deb' | wc -l)
  log "downloaded $ndebs packages ($(du -sm "$aptdir/cache/archives" | cut -f1) MB) in $(($(date +%s) - t0)) s"

  # Merged /usr, as Debian 12 lays it out; --keep-directory-symlink makes files of
  # packages that still ship /lib/... land in usr/lib/....
  mkdir -p "$root"/usr/bin "$root"/usr/sbin "$root"/usr/lib "$root"/etc
  ln -s usr/bin "$root/bin"
  ln -s usr/sbin "$root/sbin"
  ln -s usr/lib "$root/lib"
  find "$aptdir/cache/archives" -maxdepth 1 -name '*.deb' -print0 |
    xargs -0 -n 16 -P 2 sh -c 'for d in "$@"; do dpkg-deb --fsys-tarfile "$d" | tar -x --keep-directory-symlink -C "'"$root"'" || exit 255; done' sh ||
    die "unpacking the packages failed"
  # Only the logs are kept: the package lists and archives (~280 MB) are not needed again.
  rm -rf "$aptdir/cache" "$aptdir/state/lists"
  log "unpacked after $(($(date +%s) - t0)) s"

  # What the maintainer scripts would have done, as far as python needs it: absolute
  # symlinks made relative (under QEMU_LD_PREFIX an absolute link resolves on the host),
  # the BLAS/LAPACK alternatives numpy loads, and the dynamic linker's cache.
  python3 - "$root" <<'PY' || die "fixing the root's links failed"
import os, sys
root = sys.argv[1]
n = 0
for d, dirs, files in os.walk(root):
    for name in dirs + files:
        p = os.path.join(d, name)
        if os.path.islink(p):
            t = os.readlink(p)
            if t.startswith("/"):
                os.unlink(p)
                os.symlink(os.path.relpath(root + t, d), p)
                n += 1
lib = os.path.join(root, "usr/lib/arm-linux-gnueabihf")
for so, subdirs in (("libblas.so.3", ("openblas-pthread", "blas")),
                    ("liblapack.so.3", ("openblas-pthread", "lapack"))):
    link = os.path.join(lib, so)
    if os.path.lexists(link):
        continue
    for sub in subdirs:
        if os.path.exists(os.path.join(lib, sub, so)):
            os.symlink(os.path.join(sub, so), link)
            break
    else:
        sys.exit(f"no {so} in the root")
print(f"pi-stack: {n} absolute links made relative")
PY
  for d in dev proc sys tmp run home; do
    rmdir "$root/$d" 2>/dev/null || true
  done
  emu "$root/sbin/ldconfig" -r "$root" || die "ldconfig in the root failed"
  [ -x "$root/usr/bin/python3.11" ] || die "no python3.11 in the root"
  emu "$root/usr/bin/python3.11" -c 'import numpy, cv2, serial' ||
    die "python3.11 in the root cannot import numpy, cv2 and serial"
  touch "$root_stamp"
  log "root ready: $(du -sm "$root" | cut -f1) MB in $(($(date +%s) - t0)) s"
fi

# --- the venv with pymavlink and the project ----------------------------------------------
venv_stamp="$cache/.venv-$(echo "$layout_version $pymavlink_req $root_stamp" | cksum | cut -d' ' -f1)"
if [ ! -e "$venv_stamp" ]; then
  t0=$(date +%s)
  log "making the venv in $venv"
  rm -rf "$venv" "$cache"/.venv-* "$cache"/.project-*
  emu "$root/usr/bin/python3.11" -m venv --system-site-packages --without-pip "$venv" ||
    die "python3.11 -m venv failed"
  # The venv's python is a host script that starts the emulator, so that
  # subprocess([sys.executable, ...]) stays on the armhf stack. The link is removed first:
  # writing through it would overwrite the armhf binary.
  rm -f "$venv/bin/python3.11"
  cat >"$venv/bin/python3.11" <<EOF
#!/bin/sh
QEMU_LD_PREFIX='$root' QEMU_CPU=cortex-a7 exec '$qemu' -0 "\$0" '$root/usr/bin/python3.11' "\$@"
EOF
  chmod +x "$venv/bin/python3.11"
  # pymavlink generates its message modules when it is built: pure Python, the same on any
  # machine, so the wheel is built on the host (seconds, not minutes under emulation) without
  # its optional Cython index; its optional lxml and fastcrc are left out as on a bare Pi.
  rm -rf "$cache/wheels"
  wheel=""
  if PYMAVLINK_FAST_INDEX=0 python3 -m pip wheel -q --disable-pip-version-check --no-deps \
    --no-binary pymavlink -w "$cache/wheels" "$pymavlink_req" >"$cache/pymavlink-wheel.log" 2>&1; then
    wheel=$(ls "$cache"/wheels/pymavlink-*-py3-none-any.whl 2>/dev/null | head -n 1)
  fi
  if [ -n "$wheel" ]; then
    "$venv/bin/python" -m pip install -q --disable-pip-version-check --no-deps --no-compile \
      "$wheel" || die "pip install $wheel failed"
  else
    log "the host could not build the pymavlink wheel ($cache/pymavlink-wheel.log); building it under emulation (minutes)"
    PYMAVLINK_FAST_INDEX=0 "$venv/bin/python" -m pip install -q --disable-pip-version-check \
      --no-deps --no-build-isolation --no-compile "$pymavlink_req" || die "pip install $pymavlink_req failed"
  fi
  touch "$venv_stamp"
  log "venv ready in $(($(date +%s) - t0)) s"
fi

# The project, editable, once per checkout (CI clones it afresh elsewhere).
project_stamp="$cache/.project-$(echo "$repo $(cksum <pyproject.toml)" | cksum | cut -d' ' -f1)"
if [ ! -e "$project_stamp" ]; then
  t0=$(date +%s)
  rm -f "$cache"/.project-*
  "$venv/bin/python" -m pip install -q --disable-pip-version-check --no-deps \
    --no-build-isolation -e "$repo" >"$cache/project-install.log" 2>&1 || {
    tail -n 20 "$cache/project-install.log" >&2
    die "pip install -e $repo failed"
  }
  touch "$project_stamp"
  log "project installed (editable) in $(($(date +%s) - t0)) s"
fi

"$venv/bin/python" - <<'PY'
import platform, sys
import numpy, cv2, serial
from importlib.metadata import version
print(f"pi-stack: python {platform.python_version()} on {platform.machine()}, "
      f"numpy {numpy.__version__} (default int {numpy.dtype(numpy.int_).itemsize * 8} bit), "
      f"opencv {cv2.__version__}, pymavlink {version('pymavlink')}, pyserial {serial.__version__}, "
      f"pytest {version('pytest')}")
PY
log "emulator: $("$qemu" --version | head -n 1), CPU cortex-a7"
log "stack ready after $(($(date +%s) - t_start_s)) s"
[ "$build_only" = 0 ] || exit 0

# --- the tests ---------------------------------------------------------------------------
# Only the files that use the marker are collected: importing every test module costs
# minutes under emulation, and some need packages that are not on the Pi stack.
if [ $# -eq 0 ]; then
  mapfile -t files < <(grep -lE 'mark\.pi\b' tests/test_*.py | sort)
  if [ "${#files[@]}" -eq 0 ]; then
    echo "pi-stack: no test file in tests/ uses the pi marker" >&2
    exit 1
  fi
  set -- -m pi -p no:cacheprovider "${files[@]}"
fi
t0=$(date +%s)
set +e
# The venv's bin first, so a test that starts `pose-daemon` by name stays on the armhf stack.
PATH="$venv/bin:$PATH" "$venv/bin/python" -m pytest "$@"
rc=$?
set -e
log "pytest took $(($(date +%s) - t0)) s; the whole job $(($(date +%s) - t_start_s)) s"
exit "$rc"
