# composite, eager and graph-replayed, at 64 and 192 samples per ray: bash .gpu-job/kr3.sh
set -u
cd "$(dirname "$0")/.." && export PYTHONPATH=$PWD:${PYTHONPATH:-} PYTHONUNBUFFERED=1
[ -e fastenerf/kernels ] || ln -s ../kernels fastenerf/kernels
[ -e fastenerf/viewer ] || ln -s ../viewer fastenerf/viewer
nvidia-smi --query-gpu=name --format=csv,noheader | tee $OUT/gpu.txt
echo "commit $(cat .gpu-job/COMMIT)" >> $OUT/gpu.txt
for m in 64 192; do
python3 -m benchmarks.kernels_render --device cuda --only composite --repeats 20 --mean-samples $m > $OUT/kr_comp_$m.json 2> $OUT/kr_comp_$m.err
python3 - $m <<'PY'
import json, os, sys
r = json.load(open(f"{os.environ['OUT']}/kr_comp_{sys.argv[1]}.json"))["composite"]
print(sys.argv[1], {k: round(v, 3) if isinstance(v, float) else v for k, v in r.items() if "ms" in k or "speedup" in k or "graph" in k})
PY
done
