cd /work/main
O=/work/scratch/s34
for s in blocks plant lattice; do for v in "d:" "w60:win_max=60"; do n=${v%%:*}; extra=${v#*:}
  fastenerf bench study pose-error /work/scratch/cpu/${s}173 --levels 0 --steps 3000 --device cpu --quiet --eval-views 10 --out $O/${s}_0$n ${extra:+--set $extra} > $O/${s}_0$n.log 2>&1; echo "$s 0 $n rc $?" >> $O/progress.log
done; done
