#!/usr/bin/env bash
# the pose-error study at 0° and 2° with the windows lengthening once the poses settle (W 15 -> 60)
cd /work/main
for tol in 0.3 0.1; do
  fastenerf bench study pose-error /work/scratch/cpu/lattice173 --levels 0 2 --steps 3000 --device cpu --eval-views 10 \
    --out /work/scratch/s36/cpu/lat_settle$tol --set refine_poses=true smooth_poses=121 smooth_order=1 refine_settle_px=$tol \
    > /work/scratch/s36/cpu/lat_settle$tol.log 2>&1
done
echo done > /work/scratch/s36/cpu/sw.done
