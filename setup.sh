#!/usr/bin/env bash
# One command that sets up a fresh machine: the system libraries the wheels need, a virtual
# environment in .venv, the project in editable mode and its test tools.
set -euo pipefail
cd "$(dirname "$0")"

# Open3D's wheel links against libusb and libgomp, which a minimal Debian lacks; chromium is the
# browser the web view's tests drive through Playwright (`playwright install` needs the internet);
# telnet is the real program tests/clients/test_telnet_program.py types at the text server through.
SYSTEM_PACKAGES="libusb-1.0-0 libgomp1 chromium telnet"
missing=""
for pkg in $SYSTEM_PACKAGES; do
    dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || missing="$missing $pkg"
done
if [ -n "$missing" ]; then
    if [ "$(id -u)" -eq 0 ]; then SUDO=""; else SUDO="sudo"; fi
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq $missing
fi

PYTHON="${PYTHON:-python3.11}"
[ -x .venv/bin/python ] || "$PYTHON" -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q -e '.[test]'
.venv/bin/python -c "import open3d, cv2, zmq, serial, pydantic; print('rvs: environment ready')"
