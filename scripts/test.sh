#!/usr/bin/env bash
# Run the test suite (headless rendering over EGL, no model-hub access) on two worker
# processes (pytest-xdist; the tests sharing a pipeline run or a module stay on one
# worker, tests/conftest.py), printing the 15 slowest tests. Extra arguments go to
# pytest: the quick loop is `bash scripts/test.sh -m "not slow"` (tests marked slow take
# more than about 3 s each); a later --durations=N overrides 15. FREEZE_TEST_WORKERS=0
# runs everything in this one process (e.g. for pdb).
set -euo pipefail
cd "$(dirname "$0")/.."
export PYOPENGL_PLATFORM=egl HF_HUB_OFFLINE=1
exec .venv/bin/python -m pytest -q -n "${FREEZE_TEST_WORKERS:-2}" --dist loadgroup --durations=15 "$@"
