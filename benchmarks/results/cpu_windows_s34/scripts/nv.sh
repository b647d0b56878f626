cd /work/main
while ! grep -q "^rc" /tmp/fresh34_demo.log 2>/dev/null; do sleep 5; done
O=/work/scratch/s34; S=/work/scratch/cpu/shiny173; P=benchmarks/results/cpu_windows_s34/scripts/no_view.py
python $P bench study pose-error $S --levels 0 --steps 3000 --device cpu --quiet --eval-views 10 --out $O/shiny_nv_0 --set win_max=60 > $O/shiny_nv_0.log 2>&1; echo "nv0 rc $?" >> $O/progress.log
python $P bench study pose-error $S --levels 2 --steps 3000 --device cpu --quiet --eval-views 10 --out $O/shiny_nv_2 --set win_max=60 refine_poses=true smooth_poses=121 smooth_order=1 > $O/shiny_nv_2.log 2>&1; echo "nv2 rc $?" >> $O/progress.log
