# detached: the 60 s list, then the threshold study (3 scenes x 2 levels side by side, 3000 steps)
cd /var/tmp/after && source /var/tmp/gpu-warp/activate.sh
C=$(cat .gpu-job/COMMIT); R=/var/tmp/res/g; mkdir -p $R
WAIT_READY=600 bash benchmarks/gpu_runs60.sh /var/tmp/data $R/runs .gpu-job/runs_g.txt $C > $R/runs60.log 2>&1
export PYTHONPATH=$PWD:${PYTHONPATH:-} PYTHONUNBUFFERED=1
[ -e fastenerf/kernels ] || ln -s ../kernels fastenerf/kernels; [ -e fastenerf/viewer ] || ln -s ../viewer fastenerf/viewer
T=$R/thr; mkdir -p $T
bench() { python3 -c "import sys; from fastenerf.cli import main; sys.exit(main())" bench "$@"; }
common=(--steps 3000 --device cuda --commit $C --quiet --eval-views 10)
echo "[$(date +%T)] threshold start $(nvidia-smi --query-gpu=name --format=csv,noheader)" >> $T/progress.log
for lv in 0.15 0.4; do for s in blocks shiny lattice; do
  ( end=$(( $(date +%s) + 900 ))
    while [ ! -e /var/tmp/thrdata/$s-pos$lv.ready ] && [ "$(date +%s)" -lt "$end" ]; do sleep 2; done
    bench study threshold $s --data /var/tmp/thrdata --levels $lv --out $T/$s "${common[@]}" > $T/$s-$lv.log 2>&1
    echo "[$(date +%T)] $s $lv rc $?" >> $T/progress.log ) &
  sleep 4
done; done
wait
for s in blocks shiny lattice; do
  bench study threshold $s --data /var/tmp/thrdata --levels 0.15 0.4 --out $T/$s --resume "${common[@]}" > $T/$s-all.log 2>&1
  echo "[$(date +%T)] $s table rc $?" >> $T/progress.log
done
find $T -name '*.pt' -delete
(cd $R && tar czf /var/tmp/res/g_png.tgz $(find . -name '*.png' | grep -v study_view))
touch $T/all.done
