cd /work/scratch/s37/cpu
while pgrep -f "share.py /work/scratch/cpu/shiny173 test.jsonl" > /dev/null; do sleep 5; done
mv test.jsonl shiny_w15.jsonl
for kv in win_max=60 refine_settle_px=0.3; do
  python /work/main/benchmarks/results/cpu_s37/scripts/share.py /work/scratch/cpu/shiny173 shiny_${kv%%=*}.jsonl $kv > shiny_${kv%%=*}.log 2>&1
done
for kv in win_max=15 win_max=60; do
  python /work/main/benchmarks/results/cpu_s37/scripts/share.py /work/scratch/cpu/lattice173 lat_${kv/=/}.jsonl $kv > lat_${kv/=/}.log 2>&1
done
touch share.done
