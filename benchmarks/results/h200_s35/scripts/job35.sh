# twenty-third session, second lease: 300 s runs with the new default windows (#17's 60 s vs
# 5 min), lattice 0° at 60 s kept for the pose-sensitivity diagnostic (#20)
cd /var/tmp/after && source /var/tmp/gpu-warp/activate.sh && source benchmarks/gpu_env.sh
export PYTHONPATH=/var/tmp/after:$PYTHONPATH
R=/var/tmp/res/${RNAME:-k}; D=/var/tmp/data; C=$(cat .gpu-job/COMMIT); mkdir -p $R; T0=$(date +%s)
log() { echo "[$(date +%T) +$(($(date +%s) - T0))s] $*" >> $R/progress.log; }
run() {  # NAME SCENE BUDGET
    while [ ! -e $D/$2.ready ]; do sleep 2; done
    $PY -m benchmarks.error_vs_time --scenes $D/$2 --backends ngp --budget-s ngp=$3 --device cuda \
        --quiet --commit $C --out $R/$2/$1 > $R/$2-$1.log 2>&1
    log "$2 $1 rc $?"
}
log "start: $(nvidia-smi --query-gpu=name --format=csv,noheader | head -1), commit $C"
run d60 blocks 60; find $R -name '*.pt' -delete
run d300 blocks 300; find $R -name '*.pt' -delete
run d60 shiny 60; find $R -name '*.pt' -delete
run d300 shiny 300; find $R -name '*.pt' -delete
run d60 lattice 60
$PY .gpu-job/pose_sensitivity.py $R/lattice/d60/runs/lattice-ngp $D/lattice > $R/lattice-sens.log 2>&1
log "lattice sensitivity rc $?"; find $R -name '*.pt' -delete
run d60 plant 60; find $R -name '*.pt' -delete
run d300 plant 300; find $R -name '*.pt' -delete
run d300 lattice 300; find $R -name '*.pt' -delete
log "all done"; touch $R/all.done
