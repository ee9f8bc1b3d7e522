#!/usr/bin/env bash
# Run the test suite (headless rendering over EGL, no model-hub access).
set -euo pipefail
cd "$(dirname "$0")/.."
export PYOPENGL_PLATFORM=egl HF_HUB_OFFLINE=1
exec .venv/bin/python -m pytest -q "$@"
