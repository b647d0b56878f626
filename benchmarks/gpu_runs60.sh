#!/usr/bin/env bash
# Budgeted error-vs-time runs on the lent GPU, one after another (each run's clock is its own:
# two at once would share the GPU and undercount nothing but halve each one's steps).
#
#   bash benchmarks/gpu_runs60.sh DATA OUT RUNS [COMMIT]
#
# RUNS is a file of lines "NAME SCENE [KEY=VALUE ...]" ('#' starts a comment); each line is
# `python -m benchmarks.error_vs_time --scenes DATA/SCENE --backends ngp --budget-s
# ngp=$BUDGET_S --set KEY=VALUE ...` into OUT/SCENE/NAME (BUDGET_S 60 unless set). A value
# with spaces or quotes goes in as one word, e.g. perturb={"pose_error_deg":1.0}. OUT/all.done
# appears at the end; OUT/partial.tgz holds every JSON and log so far (checkpoints deleted).
# On the lent machine: start it detached (setsid nohup ... &) and keep a call in flight
# (the machine goes back 30 s after a call returns, and the run with it); `gpu_poll.sh` is
# such a call. With WAIT_READY=S a run first waits up to S seconds for DATA/SCENE.ready (touch
# it once a later call has copied that scene in), so the list can start before every scene is
# carried; a scene still not ready is logged as skipped.
# Bad input (a missing DATA or RUNS, an OUT that exists or cannot be made) ends with one line
# on stderr and exit code 2 before anything is written; an existing OUT is left as it was.
set -u
fail() { echo "gpu_runs60.sh: error: $*" >&2; exit 2; }
[ $# -ge 3 ] || fail "usage: gpu_runs60.sh DATA OUT RUNS [COMMIT]"
[ -d "$1" ] || fail "DATA $1 is not a folder"
[ -f "$3" ] && [ -r "$3" ] || fail "RUNS $3 is not a readable file"
[[ "${WAIT_READY:-0}" =~ ^[0-9]+$ ]] || fail "WAIT_READY ${WAIT_READY} is not a whole number of seconds"
[ ! -e "$2" ] || fail "OUT $2 exists: give a new folder (nothing was written)"
mkdir -p "$2" 2>/dev/null || fail "OUT $2 cannot be made"
DATA=$(realpath "$1"); OUT=$(realpath "$2"); RUNS=$(realpath "$3"); COMMIT=${4:-unknown}
BUDGET_S=${BUDGET_S:-60}; DEVICE=${DEVICE:-cuda}
source "$(dirname "$0")/gpu_env.sh"
log() {
    echo "[$(date +%T) +$(($(date +%s) - T0))s] $*" >> "$OUT/progress.log"
    (cd "$OUT" && tar czf partial.tgz.tmp --exclude='*.pt' ./*.log ./*/*/*.json 2>/dev/null
     mv -f partial.tgz.tmp partial.tgz)
}
log "start: $(nvidia-smi --query-gpu=name --format=csv,noheader 2>/dev/null | head -1), commit $COMMIT"
while read -r name scene sets; do
    case "$name" in '' | '#'*) continue ;; esac
    read -r -a kv <<< "$sets"
    dir="$OUT/$scene/$name"
    if [ -n "${WAIT_READY:-}" ]; then
        end=$(( $(date +%s) + WAIT_READY ))
        while [ ! -e "$DATA/$scene.ready" ] && [ "$(date +%s)" -lt "$end" ]; do sleep 2; done
        [ -e "$DATA/$scene.ready" ] || { log "$scene $name skipped: $DATA/$scene.ready not there"; continue; }
    fi
    $PY -m benchmarks.error_vs_time --scenes "$DATA/$scene" --backends ngp \
        --budget-s "ngp=$BUDGET_S" --device "$DEVICE" --quiet --commit "$COMMIT" --out "$dir" \
        ${kv[@]:+--set "${kv[@]}"} > "$OUT/$scene-$name.log" 2>&1
    rc=$?
    find "$dir" -name '*.pt' -delete 2>/dev/null
    log "$scene $name rc $rc"
done < "$RUNS"
log "all done"
touch "$OUT/all.done"
