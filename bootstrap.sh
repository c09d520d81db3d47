#!/usr/bin/env bash
# One script does all the set-up, then runs what you asked for:
#   bash bootstrap.sh demo [ARGS...]   -> set up, then `scanner demo ARGS...` on the virtual cell
#   bash bootstrap.sh test [ARGS...]   -> set up, then the whole test suite (pytest ARGS...)
#   bash bootstrap.sh setup            -> set up only
# Set-up is idempotent and fast when nothing changed: system libraries (libusb for open3d;
# mbpoll for the PLC stand-in tests, optional), a virtual environment in .venv, and the
# project installed into it in editable mode.
set -euo pipefail
cd "$(dirname "$0")"

say() { printf '[bootstrap] %s\n' "$*" >&2; }
die() { printf '[bootstrap] error: %s\n' "$*" >&2; exit 1; }

PY=${PYTHON:-python3}
command -v "$PY" >/dev/null || die "no python3 on PATH (need Python 3.10 to 3.13)"
"$PY" -c 'import sys; sys.exit(not ((3, 10) <= sys.version_info[:2] <= (3, 13)))' \
  || die "need Python 3.10 to 3.13, found $("$PY" --version 2>&1)"

is_root() { [ "$(id -u)" = "0" ]; }
apt_updated=0
apt_install() {  # apt_install PKG... ; returns non-zero when it cannot
  is_root && command -v apt-get >/dev/null || return 1
  if [ "$apt_updated" = 0 ]; then
    DEBIAN_FRONTEND=noninteractive apt-get update -qq >/dev/null 2>&1 || true
    apt_updated=1
  fi
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "$@" >/dev/null 2>&1
}

# open3d loads libusb-1.0 at import time.
if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
  say "installing the system library libusb-1.0-0 (open3d needs it)"
  apt_install libusb-1.0-0 || die "libusb-1.0-0 is missing and cannot be installed here: run 'sudo apt-get install libusb-1.0-0' (or your system's equivalent) and retry"
fi
# mbpoll: an independent Modbus client for the PLC tests; optional (those tests skip without it).
if ! command -v mbpoll >/dev/null; then
  apt_install mbpoll || say "mbpoll not available: the PLC stand-in tests will be skipped"
fi

if [ ! -x .venv/bin/python ]; then
  say "creating the virtual environment .venv"
  if ! "$PY" -m venv .venv >/dev/null 2>&1; then
    rm -rf .venv
    pyver=$("$PY" -c 'import sys; print(f"{sys.version_info[0]}.{sys.version_info[1]}")')
    apt_install "python${pyver}-venv" || apt_install python3-venv \
      || die "python3 -m venv failed: install the venv module (Debian: apt-get install python3-venv)"
    "$PY" -m venv .venv || die "python3 -m venv failed"
  fi
fi

stamp=.venv/.setup-stamp
want=$(cat pyproject.toml | sha256sum | cut -d' ' -f1)
if [ "$(cat "$stamp" 2>/dev/null || true)" != "$want" ]; then
  say "installing the project and its dependencies into .venv (first time: about a minute)"
  .venv/bin/python -m pip install -q --upgrade pip >/dev/null
  .venv/bin/python -m pip install -q -e ".[dev]" || die "pip install failed (see above)"
  echo "$want" > "$stamp"
fi

what=${1:-setup}
[ $# -gt 0 ] && shift
case "$what" in
  setup) say "ready: activate with 'source .venv/bin/activate', then run 'scanner --help'" ;;
  demo) exec .venv/bin/scanner demo "$@" ;;
  test) exec .venv/bin/python -m pytest "$@" ;;
  *) die "unknown action '$what' (expected setup, demo or test)" ;;
esac
