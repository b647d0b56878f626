#!/usr/bin/env bash
# shiny173: the windows lengthening once the poses settle, against W 15 and W 60 throughout
cd /work/main
S=/work/scratch/cpu/shiny173; O=/work/scratch/s36/cpu
A="--levels 0 2 --steps 3000 --device cpu --eval-views 10"
P="refine_poses=true smooth_poses=121 smooth_order=1"
fastenerf bench study pose-error $S $A --out $O/shiny_settle0.3 --set $P refine_settle_px=0.3 > $O/shiny_settle0.3.log 2>&1
fastenerf bench study pose-error $S $A --out $O/shiny_w15 --set $P win_max=15 > $O/shiny_w15.log 2>&1
fastenerf bench study pose-error $S $A --out $O/shiny_w60 --set $P win_max=60 > $O/shiny_w60.log 2>&1
echo done > $O/sh.done
