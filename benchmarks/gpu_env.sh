# Sourced by the GPU session scripts (gpu_refine.sh, gpu_sweep.sh) after they set DATA and OUT:
# the tree importable without installing it (the device machine has a copy, not a package), the
# links a checkout keeps git-ignored, OUT made, T0 the start for the progress log's offsets.
PY=${PY:-python3}
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
export PYTHONUNBUFFERED=1 PYTHONPATH=$ROOT:${PYTHONPATH:-}
cd "$ROOT" || exit 2
[ -e fastenerf/kernels ] || ln -s ../kernels fastenerf/kernels
[ -e fastenerf/viewer ] || ln -s ../viewer fastenerf/viewer
mkdir -p "$OUT"
T0=$(date +%s)
