cd /work/main
export PYTHONPATH=/work/main
O=/work/scratch/s34; S=/work/scratch/cpu/shiny173
for k in 8 16; do
fastenerf bench study pose-error $S --levels 2 --steps 3000 --device cpu --quiet --eval-views 10 --out $O/shiny_k$k --set win_max=60 refine_poses=true smooth_poses=121 smooth_order=1 refine_knots=$k > $O/shiny_k$k.log 2>&1; echo "k$k rc $?" >> $O/progress.log
done
