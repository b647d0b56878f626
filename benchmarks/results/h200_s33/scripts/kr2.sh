# kernels_render (composite both layouts + march) and the composite A/B: bash .gpu-job/kr2.sh
set -u
cd "$(dirname "$0")/.." && export PYTHONPATH=$PWD:${PYTHONPATH:-} PYTHONUNBUFFERED=1
[ -e fastenerf/kernels ] || ln -s ../kernels fastenerf/kernels
[ -e fastenerf/viewer ] || ln -s ../viewer fastenerf/viewer
nvidia-smi --query-gpu=name --format=csv,noheader | tee $OUT/gpu.txt
echo "commit $(cat .gpu-job/COMMIT)" >> $OUT/gpu.txt
python3 .gpu-job/comp_ab.py 2> $OUT/comp_ab.err | cut -c1-600
python3 -m benchmarks.kernels_render --device cuda --repeats 20 > $OUT/kr_all.json 2> $OUT/kr_all.err
python3 - <<'PY'
import json, os
r = json.load(open(f"{os.environ['OUT']}/kr_all.json"))
for k, v in r.items():
    if isinstance(v, dict):
        print(k, {a: b for a, b in v.items() if any(w in a for w in ("ms", "speedup", "identical", "same"))})
PY
