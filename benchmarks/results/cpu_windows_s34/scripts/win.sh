cd /work/main
S=/work/scratch/cpu/shiny173; O=/work/scratch/s34
base="refine_poses=true smooth_poses=121 smooth_order=1"
for v in "w15:" "w60:win_max=60" "w120:win_max=120"; do
  n=${v%%:*}; extra=${v#*:}
  fastenerf bench study pose-error $S --levels 2 --steps 3000 --device cpu --quiet --eval-views 10 --out $O/shiny_$n --set $base $extra > $O/shiny_$n.log 2>&1
  echo "$n rc $?" >> $O/progress.log
done
