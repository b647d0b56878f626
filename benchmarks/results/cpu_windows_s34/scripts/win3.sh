cd /work/main
while ! grep -q iid /work/scratch/s34/progress.log 2>/dev/null; do sleep 5; done
S=/work/scratch/cpu/shiny173; O=/work/scratch/s34
fastenerf bench study pose-error $S --levels 0 --steps 3000 --device cpu --quiet --eval-views 10 --out $O/shiny_0w60 --set win_max=60 > $O/shiny_0w60.log 2>&1; echo "zero60 rc $?" >> $O/progress.log
