#!/usr/bin/env bash
# pose-settle observation on the CPU: how far the corrections move per 5 % of the budget
cd /work/main
for deg in 0 2; do
  fastenerf train /work/scratch/cpu/lattice173 --out /work/scratch/s36/cpu/obs_$deg --steps 3000 --device cpu \
    --pose-error-deg $deg --refine-poses --smooth-poses 121 --smooth-order 1 --refine-settle-px 1e-6 \
    --log-every 25 --eval-every-s 0 > /work/scratch/s36/cpu/obs_$deg.log 2>&1
done
echo done > /work/scratch/s36/cpu/obs.done
