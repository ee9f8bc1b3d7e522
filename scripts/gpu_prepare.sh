#!/usr/bin/env bash
# Prepare what scripts/gpu_check.sh needs on a bare GPU machine without network, into
# .gpu/ (git-ignored; the device tool carries it: `carry: [".gpu"]`). Run it here, on a
# machine that reaches PyPI and Debian's archive, after scripts/install.sh:
#
#   bash scripts/gpu_prepare.sh [--python-version 3.12]
#
# .gpu/wheels   the project's Python dependencies that the GPU machine's image lacks
#               (its image has torch, transformers, numpy, scipy, pandas, pyarrow, typer,
#               rich, opencv, matplotlib, pytest...: the device entry's KINDS.md), as
#               wheels for its Python (3.12, manylinux x86-64), the versions of .venv;
# .gpu/debs     the GL loader libraries (libegl1, libglvnd0, libopengl0, libgl1,
#               libglx0, libgles2) that pyrender's EGL needs, for amd64;
# .gpu/dinov2-official
#               a copy of ../shared/reference/dinov2-official, the oracle of
#               benchmarks/gpu_oracles.py (it never enters the repository);
# .gpu/shared/realdata/lmo-rgb-scene2
#               a copy of the 40 real LM-O images and models semilmo is built from
#               (gpu_check.sh's steps 4 and 5; 32 MB).
#
# open3d is not carried: its wheel (100 MB) is over what reaches the machine (64 MiB in
# all); gpu_check.sh uses scripts/gpu_shim/open3d there instead (see its docstring).
# The whole of .gpu/ is about 52 MB (with the repository's 6 MB, under the 64 MiB that
# reaches the machine). A failed download stops the script with one line.
set -euo pipefail
cd "$(dirname "$0")/.."
PYV="3.12"
case "${1:-}" in
  --python-version) PYV="$2" ;;
  -h|--help) sed -n '2,24p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
  "") ;;
  *) echo "gpu_prepare: unknown option $1 (see --help)" >&2; exit 2 ;;
esac
[ -x .venv/bin/python ] || { echo "gpu_prepare: no .venv here: run scripts/install.sh first" >&2; exit 1; }
SHARED_REF="../shared/reference/dinov2-official"
LMO="../shared/realdata/lmo-rgb-scene2"
[ -f "$LMO/camera.json" ] || { echo "gpu_prepare: $LMO is missing (the LM-O sample of semilmo)" >&2; exit 1; }
[ -f "$SHARED_REF/dinov2/hub/backbones.py" ] || { echo "gpu_prepare: $SHARED_REF is missing (the official DINOv2 code)" >&2; exit 1; }

# The packages the GPU check imports that the machine's image does not have (found by
# importing the stages, benchmarks/paper_run.py and benchmarks/gpu_oracles.py here and
# removing what KINDS.md lists there).
PACKAGES="trimesh pyrender PyOpenGL pyglet freetype-py pykdtree rtree zarr numcodecs donfig google-crc32c
dask partd locket importlib_metadata zipp toolz pydantic pydantic_core annotated-types typing-inspection torchgeometry"
mkdir -p .gpu/wheels .gpu/debs
PINS=()
for p in $PACKAGES; do
  v=$(.venv/bin/python -c "import importlib.metadata as m, sys; print(m.version(sys.argv[1]))" "$p") \
    || { echo "gpu_prepare: $p is not installed in .venv" >&2; exit 1; }
  PINS+=("$p==$v")
done
rm -f .gpu/wheels/*.whl
# PyOpenGL 3.1.0 (pyrender's pin) is published as source only: a pure-Python wheel made here
SOURCE_ONLY="PyOpenGL"
for p in $SOURCE_ONLY; do
  for i in "${!PINS[@]}"; do
    if [ "${PINS[$i]%%==*}" = "$p" ]; then
      .venv/bin/python -m pip wheel -q --disable-pip-version-check --no-deps -w .gpu/wheels "${PINS[$i]}" 2>&1 | grep -v "^WARNING" || true
      unset 'PINS[$i]'
    fi
  done
done
PINS=("${PINS[@]}")
.venv/bin/python -m pip download -q --disable-pip-version-check --no-deps --only-binary=:all: \
  --python-version "$PYV" --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_24_x86_64 \
  --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 --platform manylinux1_x86_64 --platform any \
  -d .gpu/wheels "${PINS[@]}" 2>&1 | grep -v "^WARNING" || true
for p in "${PINS[@]}" PyOpenGL==; do
  name=$(echo "${p%%==*}" | tr 'A-Z-' 'a-z_')
  ls .gpu/wheels | tr 'A-Z-' 'a-z_' | grep -q "^${name}_[0-9]" || { echo "gpu_prepare: no wheel of $p for Python $PYV" >&2; exit 1; }
done

# GL loaders for EGL (the NVIDIA driver brings its own EGL vendor library)
L=/tmp/gpu_prepare_apt
mkdir -p "$L/partial"
O=(-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists="$L")
apt-get "${O[@]}" update -qq
rm -f .gpu/debs/*.deb
(cd .gpu/debs && apt-get "${O[@]}" download -qq libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2)

rm -rf .gpu/dinov2-official
cp -r "$SHARED_REF" .gpu/dinov2-official
rm -rf .gpu/shared
mkdir -p .gpu/shared/realdata
cp -r "$LMO" .gpu/shared/realdata/
echo "gpu_prepare: .gpu ready ($(du -sh .gpu | cut -f1)): $(ls .gpu/wheels | wc -l) wheels, $(ls .gpu/debs | wc -l) debs, the official DINOv2 code, the LM-O sample"
