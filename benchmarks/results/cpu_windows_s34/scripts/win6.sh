cd /work/main
while ! grep -q "blocks 0 w30" /work/scratch/s34/progress.log 2>/dev/null; do sleep 5; done
O=/work/scratch/s34
for v in "d:" "w60:win_max=60"; do n=${v%%:*}; extra=${v#*:}
  python -m benchmarks.error_vs_time --scenes /work/scratch/cpu/blocks173 --backends ngp --budget-s ngp=300 --device cpu --quiet --out $O/blocks_300_$n ${extra:+--set $extra} > $O/blocks_300_$n.log 2>&1; echo "blocks 300 $n rc $?" >> $O/progress.log
done
