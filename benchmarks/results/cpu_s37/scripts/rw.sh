cd /work/main
O=/work/scratch/s37/cpu
A="--levels 2 --steps 3000 --device cpu --eval-views 10"
P="refine_poses=true smooth_poses=121 smooth_order=1 refine_settle_px=0.3 refine_win_max=60"
fastenerf bench study pose-error /work/scratch/cpu/shiny173 $A --out $O/shiny_s03_rw60 --set $P > $O/shiny_s03_rw60.log 2>&1
fastenerf bench study pose-error /work/scratch/cpu/lattice173 $A --out $O/lat_s03_rw60 --set $P > $O/lat_s03_rw60.log 2>&1
touch $O/rw.done
