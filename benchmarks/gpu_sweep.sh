#!/usr/bin/env bash
# Options of a pose study compared level by level on the lent GPU, many runs side by side.
#
#   SWEEP="blocks:t0:0,1,2:refine_poses=true,refine_translation=false ..." \
#       bash benchmarks/gpu_sweep.sh DATA OUT [COMMIT]
#   STUDY=mount-error SWEEP="blocks:shared:0,2:refine_poses=true,refine_shared=true" ...
#
# Each SWEEP item is SCENE:NAME:LEVELS:SETS (LEVELS comma-separated degrees, SETS
# comma-separated KEY=VALUE for `bench study --set`, '-' for none); every (item, level) is its
# own process, JOBS at a time (the refined step is host-paced, so the GPU takes several),
# writing OUT/sweep_SCENE_NAME_L<level>/STUDY.json (STUDY: pose-error, the default, or
# mount-error, `bench study STUDY`). The table over all of them is
# OUT/sweep.md (`python -m benchmarks.study_sweep OUT`). STUDY_STEPS steps per run, as
# gpu_refine.sh's studies. On the lent device machine: start it detached (setsid) and keep a
# call in flight until "all done"; OUT/partial.tgz holds the logs and JSONs so far.
set -u
DEVICE=${DEVICE:-cuda}; STUDY_STEPS=${STUDY_STEPS:-3000}; JOBS=${JOBS:-8}
STUDY=${STUDY:-pose-error}
EVAL_VIEWS=${EVAL_VIEWS:-10}; SWEEP=${SWEEP:?SWEEP lists SCENE:NAME:LEVELS:SETS items}
DATA=$(realpath "$1"); OUT=$(realpath -m "$2"); COMMIT=${3:-unknown}
source "$(dirname "$0")/gpu_env.sh"
log() {
    echo "[$(date +%T) +$(($(date +%s) - T0))s] $*" | tee -a "$OUT/progress.log"
    (cd "$OUT" && tar czf partial.tgz.tmp ./*.log ./*/*.json 2>/dev/null
     mv -f partial.tgz.tmp partial.tgz)
}
log "start: $(nvidia-smi --query-gpu=name --format=csv,noheader 2>/dev/null | head -1), commit $COMMIT, $STUDY"
run_one() {  # SCENE NAME LEVEL SETS
    local sets=() dir="$OUT/sweep_$1_$2_L$3"
    [ "$4" = - ] || sets=(${4//,/ })
    $PY -c "import sys; from fastenerf.cli import main; sys.exit(main())" bench study "$STUDY" \
        "$DATA/$1" --levels "$3" --out "$dir" --steps "$STUDY_STEPS" --device "$DEVICE" \
        --commit "$COMMIT" --quiet --eval-views "$EVAL_VIEWS" ${sets[@]:+--set "${sets[@]}"} \
        > "$dir.log" 2>&1
    log "$STUDY $1 $2 ${3}deg done (rc $?)"
    rm -rf "$dir"/runs/*/checkpoint*
}
for item in $SWEEP; do
    IFS=: read -r scene name levels sets <<< "$item"
    for lv in ${levels//,/ }; do
        while [ "$(jobs -rp | wc -l)" -ge "$JOBS" ]; do sleep 2; done
        run_one "$scene" "$name" "$lv" "$sets" &
        sleep 3  # stagger the start-ups
    done
done
wait
$PY -m benchmarks.study_sweep "$OUT" > "$OUT/sweep.log" 2>&1
log "table done (rc $?)"
log "all done"
