cd /work/main
O=/work/scratch/s37/cpu
A="--levels 2 --steps 3000 --device cpu --eval-views 10"
P="refine_poses=true smooth_poses=121 smooth_order=1 win_max=60"
FASTENERF_DETACH_DIRS=1 fastenerf bench study pose-error /work/scratch/cpu/shiny173 $A --out $O/shiny_dd --set $P > $O/shiny_dd.log 2>&1
FASTENERF_DETACH_DIRS=1 fastenerf bench study pose-error /work/scratch/cpu/lattice173 $A --out $O/lat_dd --set $P > $O/lat_dd.log 2>&1
echo done > $O/dd.done
