#!/usr/bin/env bash
# Install everything on a fresh Debian machine with Python 3.11 (idempotent):
# the Debian packages headless pyrender needs (EGL/Mesa) and headless Chromium (the
# report's rendering test), a virtual environment in .venv, and the project with its
# pinned torch==2.13.0 (CPU wheel), installed by uv (pip where uv fails).
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
# The packages go in through uv (installed into the venv by pip, pinned): it resolves,
# fetches and unpacks in parallel, 11 s against pip's 85 s for the same 163 packages on
# this 2-core machine (CHANGELOG, issue 31). uv reads no pip configuration, so the
# machine's pip settings (wheel folders, mirrors, constraints) are handed to it; where
# uv cannot be had or fails, pip installs the same set. torch is pinned in
# pyproject.toml: an unpinned torch would pull a multi-GB CUDA build. uv, unlike pip,
# leaves the bytecode to the first import; where PYTHONDONTWRITEBYTECODE is set (CI
# machines, containers) that import never keeps it, every job compiles torch, scipy and
# open3d again, and the main job took 255 s instead of 197 s. --compile-bytecode
# compiles it here, as pip does.
PIP=(.venv/bin/python -m pip install -q --disable-pip-version-check)
uv_args=(--python .venv/bin/python --index-strategy unsafe-best-match --compile-bytecode)
while IFS= read -r line; do
  key="${line%%=*}"; value="${line#*=}"; value="${value#\'}"; value="${value%\'}"
  case "${key#*.}" in  # pip's multi-valued settings are space-separated
    find-links) for v in $value; do uv_args+=(--find-links "$v"); done ;;
    extra-index-url) for v in $value; do uv_args+=(--extra-index-url "$v"); done ;;
    index-url) uv_args+=(--index-url "$value") ;;
    constraint) for v in $value; do uv_args+=(--constraint "$v"); done ;;
    cert) export SSL_CERT_FILE="${SSL_CERT_FILE:-$value}" ;;
  esac
done < <(.venv/bin/python -m pip config list 2>/dev/null)
if "${PIP[@]}" uv==0.13.9 && .venv/bin/uv pip install -q "${uv_args[@]}" torch==2.13.0 -e '.[test]'; then
  :
else
  echo "uv could not install the packages; installing them with pip instead"
  "${PIP[@]}" torch==2.13.0
  "${PIP[@]}" -e '.[test]'
fi
.venv/bin/python -c 'import torch, open3d, pyrender, zarr, snakemake; print("environment ready: torch", torch.__version__)'
