cd /work/main
while ! grep -q w120 /work/scratch/s34/progress.log 2>/dev/null; do sleep 5; done
S=/work/scratch/cpu/shiny173; O=/work/scratch/s34
fastenerf bench study pose-error $S --levels 0 --steps 3000 --device cpu --quiet --eval-views 10 --out $O/shiny_0 > $O/shiny_0.log 2>&1; echo "zero rc $?" >> $O/progress.log
fastenerf bench study pose-error $S --levels 0.276 --steps 3000 --device cpu --quiet --eval-views 10 --out $O/shiny_iid --set refine_poses=true > $O/shiny_iid.log 2>&1; echo "iid rc $?" >> $O/progress.log
