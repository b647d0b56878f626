cd /work/main
O=/work/scratch/s34
for s in shiny lattice; do
fastenerf bench study pose-error /work/scratch/cpu/${s}173 --levels 0 1 2 --steps 3000 --device cpu --quiet --eval-views 10 --out $O/${s}_aligned_study --set refine_poses=true smooth_poses=121 smooth_order=1 > $O/${s}_al.log 2>&1; echo "$s aligned rc $?" >> $O/progress.log
done
