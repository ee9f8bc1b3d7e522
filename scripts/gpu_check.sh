#!/usr/bin/env bash
# Check the paper's configuration on a CUDA machine (docs/gpu.md), in about 6 minutes on
# one H200 (budget: 8), also on a bare machine without network:
#
#   bash scripts/gpu_check.sh [--keep]
#
# 0. the environment: the project's .venv when there is one; else the machine's python3
#    with what scripts/gpu_prepare.sh put in .gpu/ (run that where there is network and
#    carry .gpu along): its wheels installed into a scratch folder, its GL loader debs
#    unpacked (as root); where open3d cannot be imported, scripts/gpu_shim/open3d stands
#    in for its three point-cloud calls (the report says so);
# 1. benchmarks/gpu_oracles.py --device cuda: the encoders on the GPU against the
#    official computations with the same random weights: DINOv2 (every family, the
#    official code from .gpu/dinov2-official or ../shared/reference/dinov2-official) in
#    fp32 (min token cosine >= 0.999) and bf16 (mean >= 0.99), GeDi (800 keypoints of a
#    model and a scene cloud) against torchgeometry's rotation and the transcribed
#    PointNet++ kernels (min cosine >= 0.999);
# 2. benchmarks/paper_run.py --dataset synthtiny --device cuda: the paper's configuration
#    (gedi + dinov2-vitg14, random full-size weights in the official layouts) through
#    every stage, timed per stage, s/image against the paper's 2.72 s, peak GPU memory;
# 3. benchmarks/icp_paths.py --device cuda --stages on that run's cache: refine's
#    hypothesis ICP on both paths (numpy one at a time on the CPU, torch batched on the
#    GPU), their times and how far their poses are apart, then refine and score again
#    with the numpy path for the comparison of choices and AR.
#
# Writes the report to $OUT/gpu_check.md (the device tool's output folder; else
# ./gpu_check_out/) and prints it. Without CUDA it prints one line and exits 0. Scratch
# goes to a fresh temporary folder, removed at the end unless --keep. A failed step
# stops the script with `gpu_check: FAILED: ...` and exit 1.
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT="$PWD"
KEEP=0
case "${1:-}" in
  --keep) KEEP=1 ;;
  -h|--help) sed -n '2,31p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
  "") ;;
  *) echo "gpu_check: FAILED: unknown option $1 (see --help)" >&2; exit 2 ;;
esac
fail() { echo "gpu_check: FAILED: $*" >&2; exit 1; }
step() { printf '[gpu_check %s] %s\n' "$(date +%H:%M:%S)" "$*"; }
REPORT_DIR="${OUT:-$ROOT/gpu_check_out}"
mkdir -p "$REPORT_DIR"
TMP="$(mktemp -d "${TMPDIR:-/tmp}/gpu_check.XXXXXX")"
cleanup() { if [ "$KEEP" = 1 ]; then echo "gpu_check: scratch kept in $TMP"; else rm -rf "$TMP"; fi; }
trap cleanup EXIT
export HF_HUB_OFFLINE=1 TRANSFORMERS_OFFLINE=1 PYOPENGL_PLATFORM=egl PYTHONUNBUFFERED=1
unset FREEZE_RUN_JSON
T_START=$(date +%s)

# --- 0. environment -------------------------------------------------------------------
ENV_NOTE="the project's .venv"
if [ -x "$ROOT/.venv/bin/python" ]; then
  PY="$ROOT/.venv/bin/python"
else
  PY="$(command -v python3)" || fail "no .venv and no python3"
  [ -d "$ROOT/.gpu/wheels" ] || fail "no .venv here and no .gpu/: run scripts/gpu_prepare.sh on a machine with network and carry .gpu"
  if ! "$PY" -c 'import torch' 2>/dev/null; then fail "$PY has no torch"; fi
  if [ "$(id -u)" -eq 0 ] && ls "$ROOT"/.gpu/debs/*.deb >/dev/null 2>&1; then
    for f in "$ROOT"/.gpu/debs/*.deb; do dpkg -x "$f" /; done
    ldconfig
  fi
  "$PY" -m pip install -q --disable-pip-version-check --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target "$TMP/site" "$ROOT"/.gpu/wheels/*.whl || fail "installing .gpu/wheels"
  export PYTHONPATH="$TMP/site:$ROOT${PYTHONPATH:+:$PYTHONPATH}"
  ENV_NOTE="$PY with .gpu/wheels ($(ls "$ROOT"/.gpu/wheels | wc -l) wheels)"
fi
if ! "$PY" -c 'import open3d' 2>/dev/null; then
  export PYTHONPATH="$ROOT/scripts/gpu_shim:${PYTHONPATH:-$ROOT}"
  ENV_NOTE="$ENV_NOTE; open3d absent: scripts/gpu_shim/open3d stands in for its normals, DBSCAN and outlier removal (CPU)"
fi
NV_EGL=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
if [ -f "$NV_EGL" ] && [ -z "${__EGL_VENDOR_LIBRARY_FILENAMES:-}" ]; then export __EGL_VENDOR_LIBRARY_FILENAMES="$NV_EGL"; fi

if ! "$PY" -c 'import sys, torch; sys.exit(0 if torch.cuda.is_available() else 1)' 2>/dev/null; then
  echo "gpu_check: no CUDA device visible to torch here (torch.cuda.is_available() is false): nothing to check"
  exit 0
fi
OFFICIAL="$ROOT/.gpu/dinov2-official"
[ -f "$OFFICIAL/dinov2/hub/backbones.py" ] || OFFICIAL="$ROOT/../shared/reference/dinov2-official"
[ -f "$OFFICIAL/dinov2/hub/backbones.py" ] || fail "no official DINOv2 code in .gpu/dinov2-official or ../shared/reference"
GPU="$("$PY" -c 'import torch; print(torch.cuda.get_device_name(0), "| torch", torch.__version__, "| CUDA", torch.version.cuda)')"
step "GPU: $GPU; environment: $ENV_NOTE"

# --- 1. oracles -------------------------------------------------------------------------
step "1/3 the encoders on cuda against the official computations"
T1=$(date +%s)
"$PY" benchmarks/gpu_oracles.py --device cuda --official "$OFFICIAL" --out "$TMP/oracles.md" \
  > "$TMP/oracles.log" 2>&1 || { tail -n 40 "$TMP/oracles.log" >&2; cp "$TMP/oracles.log" "$REPORT_DIR/" || true; fail "oracle comparisons (log: $REPORT_DIR/oracles.log)"; }
T2=$(date +%s)

# --- 2. the paper's configuration on synthtiny ----------------------------------------------
step "2/3 the paper's configuration (gedi + dinov2-vitg14) on synthtiny, device=cuda"
"$PY" benchmarks/paper_run.py --dataset synthtiny --geometric gedi --visual dinov2-vitg14 --device cuda \
  --weights "$TMP/weights" --cache "$TMP/cache" --out "$TMP/paper_run.md" --json "$REPORT_DIR/paper_run.json" \
  > "$TMP/paper_run.log" 2>&1 || { tail -n 40 "$TMP/paper_run.log" >&2; cp "$TMP/paper_run.log" "$REPORT_DIR/" || true; fail "paper run (log: $REPORT_DIR/paper_run.log)"; }
T3=$(date +%s)

# --- 3. refine's ICP on both paths --------------------------------------------------------
step "3/3 refine's hypothesis ICP: numpy on the CPU against torch on cuda, on the paper run's hypotheses"
"$PY" benchmarks/icp_paths.py --dataset synthtiny --geometric gedi --visual dinov2-vitg14 --device cuda \
  --weights "$TMP/weights" --cache "$TMP/cache" --stages --out "$TMP/icp_paths.md" \
  > "$TMP/icp_paths.log" 2>&1 || { tail -n 40 "$TMP/icp_paths.log" >&2; cp "$TMP/icp_paths.log" "$REPORT_DIR/" || true; fail "ICP paths (log: $REPORT_DIR/icp_paths.log)"; }
T4=$(date +%s)

{
  echo "# scripts/gpu_check.sh, $(date -u +%Y-%m-%dT%H:%MZ)"
  echo
  echo "GPU: $GPU. Environment: $ENV_NOTE. Steps: oracles $((T2 - T1)) s, paper run $((T3 - T2)) s, ICP paths $((T4 - T3)) s, total $((T4 - T_START)) s."
  echo
  cat "$TMP/oracles.md"
  echo
  cat "$TMP/paper_run.md"
  echo
  cat "$TMP/icp_paths.md"
} > "$REPORT_DIR/gpu_check.md"
cp "$TMP/paper_run.log" "$REPORT_DIR/paper_run.log"
cat "$REPORT_DIR/gpu_check.md"
echo "gpu_check: OK ($((T4 - T_START)) s; report $REPORT_DIR/gpu_check.md)"
