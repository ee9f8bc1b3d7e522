#!/usr/bin/env bash
# Install everything on a fresh Debian machine with Python 3.11 (idempotent):
# the Debian packages headless pyrender needs (EGL/Mesa) and headless Chromium (the
# report's rendering test), a virtual environment in .venv, and the project with its
# pinned torch==2.13.0 (CPU wheel).
set -euo pipefail
cd "$(dirname "$0")/.."

SUDO=""
if [ "$(id -u)" -ne 0 ]; then SUDO="sudo"; fi
DEB_PACKAGES="libusb-1.0-0 libegl1 libegl-mesa0 libgl1-mesa-dri libgbm1 chromium"
missing=""
for p in $DEB_PACKAGES; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing="$missing $p"
done
if [ -n "$missing" ]; then
  echo "installing Debian packages:$missing"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq $missing
fi

PY="${PYTHON:-python3}"
"$PY" -c 'import sys; assert sys.version_info >= (3, 11), f"Python >= 3.11 needed, found {sys.version}"'
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
# torch first and pinned: an unpinned torch would pull a multi-GB CUDA build.
.venv/bin/python -m pip install -q --disable-pip-version-check torch==2.13.0
.venv/bin/python -m pip install -q --disable-pip-version-check -e '.[test]'
.venv/bin/python -c 'import torch, open3d, pyrender, zarr, snakemake; print("environment ready: torch", torch.__version__)'
