#!/usr/bin/env bash
# Check the torch encoders on a CUDA machine (docs/gpu.md):
#
#   bash scripts/gpu_check.sh [--keep]
#
# 1. the encoder tests on cuda: FREEZE_TEST_DEVICE=cuda pytest tests/test_device.py
#    tests/test_encoders_dinov2.py tests/test_encoders_gedi.py;
# 2. benchmarks/gpu_agreement.py --device cuda: random GeDi and DINOv2 ViT-S/14 weights in
#    the official layouts in a temporary weights folder, time per call of each encoder on
#    cpu and cuda, and the CPU/GPU cosine agreement of their descriptors (>= 0.99 required);
# 3. the main job on synthtiny with gedi + dinov2-vits14 on cuda, on those weights, in a
#    temporary cache: snakemake --cores 2 bop_all --config datasets=synthtiny geometric=gedi
#    visual=dinov2-vits14 device=cuda weights_dir=$TMP/weights; then prints the device and
#    precision the model_features manifests recorded.
#
# Without CUDA (torch.cuda.is_available() false) it prints one line and exits 0. Scratch
# goes to a fresh temporary folder, removed at the end unless --keep. A failed step stops
# the script with `gpu_check: FAILED: ...` and exit 1.
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT="$PWD"
PY="$ROOT/.venv/bin/python"
KEEP=0
case "${1:-}" in
  --keep) KEEP=1 ;;
  -h|--help) sed -n '2,19p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
  "") ;;
  *) echo "gpu_check: FAILED: unknown option $1 (see --help)" >&2; exit 2 ;;
esac
[ -x "$PY" ] || { echo "gpu_check: FAILED: no .venv here: run scripts/install.sh first" >&2; exit 1; }

if ! "$PY" -c 'import sys, torch; sys.exit(0 if torch.cuda.is_available() else 1)' 2>/dev/null; then
  echo "gpu_check: no CUDA device visible to torch here (torch.cuda.is_available() is false): nothing to check"
  exit 0
fi

TMP="$(mktemp -d "${TMPDIR:-/tmp}/gpu_check.XXXXXX")"
cleanup() { if [ "$KEEP" = 1 ]; then echo "gpu_check: scratch kept in $TMP"; else rm -rf "$TMP"; fi; }
trap cleanup EXIT
step() { printf '[gpu_check %s] %s\n' "$(date +%H:%M:%S)" "$*"; }
fail() { echo "gpu_check: FAILED: $*" >&2; exit 1; }
export HF_HUB_OFFLINE=1 TRANSFORMERS_OFFLINE=1 PYOPENGL_PLATFORM=egl
unset FREEZE_RUN_JSON

step "GPU: $("$PY" -c 'import torch; print(torch.cuda.get_device_name(0), "| torch", torch.__version__, "| CUDA", torch.version.cuda)')"

step "1/3 encoder tests on cuda"
FREEZE_TEST_DEVICE=cuda "$PY" -m pytest -q -n 0 -rs tests/test_device.py tests/test_encoders_dinov2.py \
  tests/test_encoders_gedi.py || fail "encoder tests on cuda"

step "2/3 CPU/GPU agreement and time per call (random weights in $TMP/weights)"
"$PY" benchmarks/gpu_agreement.py --device cuda --weights "$TMP/weights" || fail "CPU/GPU agreement"

step "3/3 main job on synthtiny: gedi + dinov2-vits14, device=cuda (cache $TMP/cache)"
CONFIG=(datasets=synthtiny geometric=gedi visual=dinov2-vits14 device=cuda "weights_dir=$TMP/weights")
T0=$(date +%s)
FREEZE_CACHE="$TMP/cache" "$ROOT/.venv/bin/snakemake" -s "$ROOT/Snakefile" --directory "$TMP" --cores 2 bop_all \
  --config "${CONFIG[@]}" > "$TMP/snakemake.log" 2>&1 || { tail -n 40 "$TMP/snakemake.log" >&2; fail "main job (log: $TMP/snakemake.log; --keep keeps it)"; }
[ -f "$TMP/results/ar_table.md" ] && cat "$TMP/results/ar_table.md"  # random weights: the AR means nothing
step "main job: $(( $(date +%s) - T0 )) s; what the model_features manifests recorded:"
FREEZE_CACHE="$TMP/cache" "$PY" - "${CONFIG[@]}" <<'EOF' || fail "the manifests do not record cuda"
import json, sys
from pipeline.config import load_run
from pipeline.plan import RunPlan

overrides = dict(a.split("=", 1) for a in sys.argv[1:])
stage = RunPlan(load_run(overrides))["synthtiny"]["model_features"]
seen = {json.dumps(json.loads(m.read_text()).get("runtime"), sort_keys=True) for m in stage.dir.glob("*/_manifest.json")}
for s in sorted(seen):
    print("  ", s)
devices = {e["device"] for s in seen for e in json.loads(s).values()}
sys.exit(0 if seen and devices == {"cuda"} else 1)
EOF
echo "gpu_check: OK"
