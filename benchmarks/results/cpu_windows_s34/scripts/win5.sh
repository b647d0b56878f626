cd /work/main
O=/work/scratch/s34
for v in "d:" "w60:win_max=60"; do n=${v%%:*}; extra=${v#*:}
  fastenerf bench study pose-error /work/scratch/cpu/toyset173 --levels 0 --steps 3000 --device cpu --quiet --eval-views 10 --out $O/toyset_0$n ${extra:+--set $extra} > $O/toyset_0$n.log 2>&1; echo "toyset 0 $n rc $?" >> $O/progress.log
done
for s in shiny blocks; do
  fastenerf bench study pose-error /work/scratch/cpu/${s}173 --levels 0 --steps 3000 --device cpu --quiet --eval-views 10 --out $O/${s}_0w30 --set win_max=30 > $O/${s}_0w30.log 2>&1; echo "$s 0 w30 rc $?" >> $O/progress.log
done
