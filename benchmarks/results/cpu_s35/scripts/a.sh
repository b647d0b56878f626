cd /work/main
for w in 15 60; do
  fastenerf bench study pose-error /work/scratch/cpu/lattice173 --levels 0 2 --steps 3000 --device cpu --eval-views 10 --out /work/scratch/s35/cpu/lat_w$w --set win_max=$w refine_poses=true smooth_poses=121 smooth_order=1 > /work/scratch/s35/cpu/lat_w$w.log 2>&1
done
PYTHONPATH=. python benchmarks/results/cpu_windows_s34/scripts/restart_field.py /work/scratch/s34/lattice_aligned_study/runs/pose-2deg /work/scratch/cpu/lattice173 /work/scratch/s35/cpu/lat_restart 3000 > /work/scratch/s35/cpu/lat_restart.log 2>&1
