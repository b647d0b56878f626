#!/bin/bash
# All step profiles: 4 configs x 2 batch sizes, two rounds (alternating, for noise). CPU only.
cd /work/main
S=/work/scratch/s38prof
CMP='"early_stop_eps":0.0001,"compaction_auto":false'
for round in 1 2; do
for rays in 256 2048; do
  R="\"rays_per_step\":$rays"
  declare -A V=(
    [base]="{\"train\":{$R}}"
    [refine]="{\"train\":{$R,\"refine_poses\":true,\"refine_start\":0.0}}"
    [base_cmp]="{\"train\":{$R},\"backend_options\":{$CMP}}"
    [refine_cmp]="{\"train\":{$R,\"refine_poses\":true,\"refine_start\":0.0},\"backend_options\":{$CMP}}"
  )
  for name in base refine base_cmp refine_cmp; do
    out=$S/out/r$round/rays$rays/$name
    python $S/prof.py --scene $S/shiny --device cpu --warmup 100 --steps 20 --quiet \
      --variant "$name=${V[$name]}" --out $out > $out.log 2>&1 || echo "FAIL $out"
    python - "$out" <<'PY'
import json,sys; r=json.load(open(sys.argv[1]+"/profile_step.json"))
print(sys.argv[1], f"plain {r['wall_ms_unprofiled']:.1f} prof {r['wall_ms']:.1f} samples {r['samples_per_step']:.0f} spr {r['samples_per_ray']:.1f} mpr {r['marched_per_ray']}", flush=True)
PY
  done
done
done
