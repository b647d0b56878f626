#!/usr/bin/env bash
# The GPU session behind issue #20 (pose refinement, threshold estimation), in one script.
#
#   bash benchmarks/gpu_refine.sh DATA OUT [COMMIT]
#
# DATA holds blocks/ and plant/ (`fastenerf synth --scene NAME --out DATA/NAME`, 346x260, 1000
# views) and the threshold study's scenes in DATA/threshold/ (made on a machine with moderngl,
# which the GPU machine lacks: `python -m fastenerf.cli bench study threshold blocks --data
# DATA/threshold --make-only`). Everything lands in OUT:
#   1. step time, each run alone on the GPU: `benchmarks.profile_step` on blocks (TIME_STEPS
#      steps after TIME_WARMUP) plain, with refine_poses, estimate_threshold, both (OUT/time_*)
#   2. STUDY_JOBS processes side by side (the step is host-bound): the pose study at 0, 1, 2°
#      on each scene without (OUT/study_SCENE_plain) and with refinement
#      (OUT/study_SCENE_refine), and the threshold study, one process per level, into
#      OUT/threshold; every run STUDY_STEPS steps (a step budget: equal work whatever the
#      sharing)
#   3. the threshold study's table over all levels, and OUT/refine_summary.{md,json,png}: every
#      target of the issue, met or not (`python -m benchmarks.study_refine OUT`)
# TINY_SET (KEY=VALUE for every study run), STUDY_STEPS, TIME_STEPS, TIME_WARMUP, EVAL_VIEWS, THR_ARGS (e.g.
# "--size 48x36 --frames 60") shrink it for a CPU try (DEVICE=cpu).
# REFINE_SET (extra KEY=VALUE for the refined runs) and EXTRA_VARIANTS (space-separated
# "name:KEY=VALUE,KEY=VALUE", each an additional refined pose study per scene,
# OUT/study_SCENE_NAME) compare options in one session. THR_LEVELS=none skips the threshold study.
# On the lent device machine: start it detached (setsid) and keep a call in flight until
# "all done"; OUT/partial.tgz holds the logs, JSONs and tables so far after every stage.
# Device time (H200, estimated from the last session's 3000-step studies, 4 side by side):
# ~1 min step times + ~7 min studies.
set -u
DEVICE=${DEVICE:-cuda}; STUDY_STEPS=${STUDY_STEPS:-3000}; STUDY_JOBS=${STUDY_JOBS:-4}
TIME_STEPS=${TIME_STEPS:-30}; TIME_WARMUP=${TIME_WARMUP:-400}; SCENES=${SCENES:-"blocks plant"}; REFINE_SET=${REFINE_SET:-}
EXTRA_VARIANTS=${EXTRA_VARIANTS:-}; EVAL_VIEWS=${EVAL_VIEWS:-10}; TINY_SET=${TINY_SET:-}
THR_SCENE=${THR_SCENE:-blocks}; THR_LEVELS=${THR_LEVELS:-"0.15 0.25 0.4"}; THR_ARGS=${THR_ARGS:-}
DATA=$(realpath "$1"); OUT=$(realpath -m "$2"); COMMIT=${3:-unknown}
source "$(dirname "$0")/gpu_env.sh"
log() {
    echo "[$(date +%T) +$(($(date +%s) - T0))s] $*" | tee -a "$OUT/progress.log"
    (cd "$OUT" && tar czf partial.tgz.tmp ./*.log ./*/*.json ./*/*.md ./*.md ./*.json 2>/dev/null
     mv -f partial.tgz.tmp partial.tgz)
}
bench() {  # the CLI without the console script (the device machine has the tree, not a package)
    $PY -c "import sys; from fastenerf.cli import main; sys.exit(main())" bench "$@"
}
common=(--steps "$STUDY_STEPS" --device "$DEVICE" --commit "$COMMIT" --quiet
        --eval-views "$EVAL_VIEWS")
log "start: $(nvidia-smi --query-gpu=name --format=csv,noheader 2>/dev/null | head -1), commit $COMMIT"

# 1. step time, alone: the steady-state step after TIME_WARMUP steps (benchmarks.profile_step;
# a short study's train seconds are dominated by start-up and compilation)
time_run() {  # NAME JSON-TRAIN-OPTIONS
    $PY -m benchmarks.profile_step --scene "$DATA/blocks" --device "$DEVICE" --quiet \
        --warmup "$TIME_WARMUP" --steps "$TIME_STEPS" --commit "$COMMIT" --out "$OUT/time_$1" \
        --variant "$1={\"train\":{$2}}" > "$OUT/time_$1.log" 2>&1
    log "time $1 done (rc $?)"
    rm -rf "$OUT/time_$1/run"
}
time_run plain ''
time_run refine '"refine_poses":true'
time_run threshold '"estimate_threshold":true'
time_run both '"refine_poses":true,"estimate_threshold":true'

# 2. the studies, STUDY_JOBS at a time
jobs_list=()
for s in $SCENES; do jobs_list+=("pose:$s:plain" "pose:$s:refine"); done
for v in $EXTRA_VARIANTS; do for s in $SCENES; do jobs_list+=("pose:$s:$v"); done; done
[ "$THR_LEVELS" = none ] || for lv in $THR_LEVELS; do jobs_list+=("thr:$lv"); done
run_job() {
    local kind=${1%%:*} rest=${1#*:}
    if [ "$kind" = thr ]; then
        bench study threshold "$THR_SCENE" --data "$DATA/threshold" --levels "$rest" \
            --out "$OUT/threshold" "${common[@]}" $THR_ARGS ${TINY_SET:+--set $TINY_SET} \
            > "$OUT/threshold_$rest.log" 2>&1
        log "threshold $rest done (rc $?)"
        return
    fi
    local s=${rest%%:*} v=${rest#*:} sets=()
    case $v in
        plain) sets=($TINY_SET) ;;
        refine) sets=(refine_poses=true $REFINE_SET $TINY_SET) ;;
        *) local extra=${v#*:}; sets=(refine_poses=true ${extra//,/ } $TINY_SET); v=${v%%:*} ;;
    esac
    bench study pose-error "$DATA/$s" --levels 0 1 2 --out "$OUT/study_${s}_$v" "${common[@]}" \
        ${sets[@]:+--set "${sets[@]}"} > "$OUT/study_${s}_$v.log" 2>&1
    log "pose study $s $v done (rc $?)"
}
for j in "${jobs_list[@]}"; do
    while [ "$(jobs -rp | wc -l)" -ge "$STUDY_JOBS" ]; do sleep 2; done
    run_job "$j" &
    sleep 5  # stagger the start-ups
done
wait

# 3. the tables
[ "$THR_LEVELS" = none ] || bench study threshold "$THR_SCENE" --data "$DATA/threshold" --levels $THR_LEVELS \
    --out "$OUT/threshold" --resume "${common[@]}" $THR_ARGS ${TINY_SET:+--set $TINY_SET} \
    > "$OUT/threshold_all.log" 2>&1
log "threshold table done (rc $?)"
$PY -m benchmarks.study_refine "$OUT" > "$OUT/summary.log" 2>&1
log "summary done (rc $?)"
(cd "$OUT" && tar czf results.tar.gz --exclude='*.pt' progress.log ./*.log ./*.md ./*.json ./*.png \
    study_*/*.json study_*/*.md study_*/*.png threshold/*.json threshold/*.md threshold/*.png \
    time_*/*.json 2>/dev/null)
log "all done"
