#!/usr/bin/env bash
# Check the paper's configuration on a CUDA machine (docs/gpu.md) within a budget of 8
# minutes (GPU_CHECK_BUDGET_S=480), also on a bare machine without network:
#
#   bash scripts/gpu_check.sh [--keep]
#
# 0. the environment: the project's .venv when there is one; else the machine's python3
#    with what scripts/gpu_prepare.sh put in .gpu/ (run that where there is network and
#    carry .gpu along): its wheels installed into a scratch folder, its GL loader debs
#    unpacked (as root); where open3d cannot be imported, scripts/gpu_shim/open3d stands
#    in for its point-cloud calls: normals, DBSCAN, outlier removal and FPFH (the
#    report says so);
# 1. benchmarks/gpu_oracles.py --device cuda: the encoders on the GPU against the
#    official computations with the same random weights: DINOv2 (every family, the
#    official code from .gpu/dinov2-official or ../shared/reference/dinov2-official) in
#    fp32 (min token cosine >= 0.999) and bf16 (mean >= 0.99), GeDi (800 keypoints of a
#    model and a scene cloud) against torchgeometry's rotation and the transcribed
#    PointNet++ kernels (min cosine >= 0.999);
# 2. benchmarks/paper_run.py --dataset synthtiny --device cuda: the paper's configuration
#    (gedi + dinov2-vitg14, random full-size weights in the official layouts) through
#    every stage, timed per stage, s/image against the paper's 2.72 s, peak GPU memory;
# 3. benchmarks/scene_paths.py --device cuda --stages on that run's cache: register's
#    RANSAC and refine's hypothesis ICP on both paths (numpy on the CPU, torch on the
#    GPU), their times and how far their results are apart, then register, refine and
#    score again on the numpy paths: the choices, the AR and the time per image (by stage)
#    of both paths;
# 4. semilmo (40 real LM-O images) with the CPU encoders' stand-ins (fpfh + colortex) and
#    the scene side on the GPU (paper_run.py --device cuda), then again on the numpy paths
#    (scene_paths.py --stages --stages-only): s/image of both against the goal of 0.3 s;
# 5. semilmo with the paper's configuration on cuda (paper_run.py): s/image against the
#    paper's 2.72 s and the goal of 1.0 s.
# Steps 4 and 5 run only in what is left of the budget (each stopped at its end, and the
# report says so), and need the LM-O sample: ../shared/realdata/lmo-rgb-scene2, or the
# copy scripts/gpu_prepare.sh puts in .gpu/shared.
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
  -h|--help) sed -n '2,38p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
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
BUDGET_S="${GPU_CHECK_BUDGET_S:-480}"
left() { echo $((BUDGET_S - ($(date +%s) - T_START))); }

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
  ENV_NOTE="$ENV_NOTE; open3d absent: scripts/gpu_shim/open3d stands in for its normals, DBSCAN, outlier removal and FPFH (CPU; its FPFH about 3-4x slower than open3d's)"
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
step "1/5 the encoders on cuda against the official computations"
T1=$(date +%s)
"$PY" benchmarks/gpu_oracles.py --device cuda --official "$OFFICIAL" --out "$TMP/oracles.md" \
  > "$TMP/oracles.log" 2>&1 || { tail -n 40 "$TMP/oracles.log" >&2; cp "$TMP/oracles.log" "$REPORT_DIR/" || true; fail "oracle comparisons (log: $REPORT_DIR/oracles.log)"; }
T2=$(date +%s)

# --- 2. the paper's configuration on synthtiny ----------------------------------------------
step "2/5 the paper's configuration (gedi + dinov2-vitg14) on synthtiny, device=cuda"
"$PY" benchmarks/paper_run.py --dataset synthtiny --geometric gedi --visual dinov2-vitg14 --device cuda \
  --weights "$TMP/weights" --cache "$TMP/cache" --out "$TMP/paper_run.md" --json "$REPORT_DIR/paper_run.json" \
  > "$TMP/paper_run.log" 2>&1 || { tail -n 40 "$TMP/paper_run.log" >&2; cp "$TMP/paper_run.log" "$REPORT_DIR/" || true; fail "paper run (log: $REPORT_DIR/paper_run.log)"; }
T3=$(date +%s)

# --- 3. the scene side's two paths on synthtiny ---------------------------------------
step "3/5 register's RANSAC and refine's ICP: numpy on the CPU against torch on cuda, on the paper run's cache"
"$PY" benchmarks/scene_paths.py --dataset synthtiny --geometric gedi --visual dinov2-vitg14 --device cuda \
  --weights "$TMP/weights" --cache "$TMP/cache" --stages --out "$TMP/scene_paths.md" \
  > "$TMP/scene_paths.log" 2>&1 || { tail -n 40 "$TMP/scene_paths.log" >&2; cp "$TMP/scene_paths.log" "$REPORT_DIR/" || true; fail "scene paths (log: $REPORT_DIR/scene_paths.log)"; }
T4=$(date +%s)

# --- 4 and 5. semilmo, in what is left of the budget -----------------------------------------
SEMI_NOTE=""
if [ -z "${FREEZE_SHARED:-}" ] && [ ! -d "$ROOT/../shared/realdata/lmo-rgb-scene2" ] && [ -d "$ROOT/.gpu/shared/realdata/lmo-rgb-scene2" ]; then
  export FREEZE_SHARED="$ROOT/.gpu/shared"
fi
# semilmo_step NAME SECONDS_MIN COMMAND...: run COMMAND under what is left of the budget
semilmo_step() {
  local name="$1" need="$2"; shift 2
  local budget; budget=$(left)
  if [ "$budget" -lt "$need" ]; then
    SEMI_NOTE="$SEMI_NOTE- $name: not run ($budget s of the budget left, it needs at least $need s)."$'\n'
    return 0
  fi
  local rc=0
  timeout "$budget" "$@" > "$TMP/$name.log" 2>&1 || rc=$?
  if [ "$rc" -eq 124 ]; then
    SEMI_NOTE="$SEMI_NOTE- $name: stopped at the end of the budget ($budget s)."$'\n'
  elif [ "$rc" -ne 0 ]; then
    tail -n 40 "$TMP/$name.log" >&2; cp "$TMP/$name.log" "$REPORT_DIR/" || true; fail "$name (log: $REPORT_DIR/$name.log)"
  else
    cat "$TMP/$name.md" >> "$TMP/semilmo.md"; echo >> "$TMP/semilmo.md"
  fi
}
: > "$TMP/semilmo.md"
if [ -d "${FREEZE_SHARED:-$ROOT/../shared}/realdata/lmo-rgb-scene2" ]; then
  step "4/5 semilmo: the CPU encoders' stand-ins (fpfh + colortex), the scene side on cuda, then on numpy"
  semilmo_step semilmo_standins 60 "$PY" benchmarks/paper_run.py --dataset semilmo --geometric fpfh --visual colortex \
    --device cuda --weights "$TMP/weights" --cache "$TMP/cache" --out "$TMP/semilmo_standins.md"
  if [ -f "$TMP/semilmo_standins.md" ]; then
    semilmo_step semilmo_standins_numpy 60 "$PY" benchmarks/scene_paths.py --dataset semilmo --geometric fpfh \
      --visual colortex --device cuda --weights "$TMP/weights" --cache "$TMP/cache" --stages --stages-only \
      --out "$TMP/semilmo_standins_numpy.md"
  fi
  step "5/5 semilmo: the paper's configuration (gedi + dinov2-vitg14), device=cuda"
  semilmo_step semilmo_paper 120 "$PY" benchmarks/paper_run.py --dataset semilmo --geometric gedi \
    --visual dinov2-vitg14 --device cuda --weights "$TMP/weights" --cache "$TMP/cache" --out "$TMP/semilmo_paper.md"
else
  SEMI_NOTE="- semilmo: not run (no realdata/lmo-rgb-scene2 in ../shared or .gpu/shared: run scripts/gpu_prepare.sh and carry .gpu)."$'\n'
fi
T5=$(date +%s)

{
  echo "# scripts/gpu_check.sh, $(date -u +%Y-%m-%dT%H:%MZ)"
  echo
  echo "GPU: $GPU. Environment: $ENV_NOTE. Steps: oracles $((T2 - T1)) s, paper run $((T3 - T2)) s, scene paths $((T4 - T3)) s, semilmo $((T5 - T4)) s, total $((T5 - T_START)) s (budget $BUDGET_S s)."
  echo
  cat "$TMP/oracles.md"
  echo
  cat "$TMP/paper_run.md"
  echo
  cat "$TMP/scene_paths.md"
  echo
  echo "## semilmo"
  echo
  cat "$TMP/semilmo.md"
  printf '%s' "$SEMI_NOTE"
} > "$REPORT_DIR/gpu_check.md"
cp "$TMP/paper_run.log" "$REPORT_DIR/paper_run.log"
cat "$REPORT_DIR/gpu_check.md"
echo "gpu_check: OK ($((T5 - T_START)) s; report $REPORT_DIR/gpu_check.md)"
