#!/usr/bin/env bash
# Run the test suite (headless rendering over EGL, no model-hub access), printing the 15
# slowest tests. Extra arguments go to pytest: the quick loop is `bash scripts/test.sh -m "not slow"`
# (tests marked slow take more than about 3 s each); a later --durations=N overrides 15.
set -euo pipefail
cd "$(dirname "$0")/.."
export PYOPENGL_PLATFORM=egl HF_HUB_OFFLINE=1
exec .venv/bin/python -m pytest -q --durations=15 "$@"
