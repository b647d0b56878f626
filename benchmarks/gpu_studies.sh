#!/usr/bin/env bash
# The GPU session behind the studies (#15) and the architecture's before/after (#14), in one script.
#
#   bash benchmarks/gpu_studies.sh DATA OUT [COMMIT] [BEFORE_TREE]
#
# DATA holds the scene folders blocks/ and plant/ (`fastenerf synth --scene NAME --out DATA/NAME`);
# everything lands in OUT. BEFORE_TREE (optional) is a copy of the tree before the architecture
# change (`git archive 35d9aa7 | tar -x -C DIR`); its 60 s ngp curve on blocks runs first, then the
# same with this tree, one after the other on the same GPU (the before/after of #14).
# Then the three studies on both scenes: STUDY_JOBS processes side by side on the one GPU (the
# step is host-bound, so several processes use it better than one), every level trained for the
# same STUDY_STEPS steps (a step budget, so levels compare at equal work whatever the sharing).
# On the lent device machine: start it detached (setsid) and keep a call in flight until
# "all done" (the machine is handed back 30 s after the last call returns); OUT/partial.tgz holds
# the logs and JSONs so far after every stage.
set -u
DEVICE=${DEVICE:-cuda}; STUDY_STEPS=${STUDY_STEPS:-3000}; STUDY_JOBS=${STUDY_JOBS:-4}
EVT_S=${EVT_S:-60}; SCENES=${SCENES:-"blocks plant"}
DATA=$(realpath "$1"); OUT=$(realpath -m "$2"); COMMIT=${3:-unknown}; BEFORE=${4:-}
PY=${PY:-python3}
ROOT=$(cd "$(dirname "$0")/.." && pwd)
export PYTHONUNBUFFERED=1
link_package() {  # an uninstalled copy gets the links setup.py's package_dir would make
    [ -e "$1/fastenerf/kernels" ] || ln -s ../kernels "$1/fastenerf/kernels"
    [ -e "$1/fastenerf/viewer" ] || ln -s ../viewer "$1/fastenerf/viewer"
}
mkdir -p "$OUT"
T0=$(date +%s)
log() {
    echo "[$(date +%T) +$(($(date +%s) - T0))s] $*" | tee -a "$OUT/progress.log"
    (cd "$OUT" && tar czf partial.tgz.tmp ./*.log ./*/*.json ./*/*.md ./*/*.png 2>/dev/null
     mv -f partial.tgz.tmp partial.tgz)
}
log "start: $(nvidia-smi --query-gpu=name --format=csv,noheader 2>/dev/null | head -1), commit $COMMIT"

evt60() {  # TREE LABEL: a 60 s ngp error-vs-time curve on blocks with that tree's code
    link_package "$1"
    (cd "$1" && PYTHONPATH="$1:${PYTHONPATH:-}" $PY -m benchmarks.error_vs_time --scenes "$DATA/blocks" \
        --backends ngp --preset fast --budget-s "ngp=$EVT_S" --device "$DEVICE" --eval-views 10 \
        --out "$OUT/evt_$2" --commit "$2" --quiet) > "$OUT/evt_$2.log" 2>&1
    log "evt $2 done (rc $?)"
}
if [ -n "$BEFORE" ]; then
    evt60 "$(realpath "$BEFORE")" before
    evt60 "$ROOT" after
fi

link_package "$ROOT"
cd "$ROOT"
export PYTHONPATH=$ROOT:${PYTHONPATH:-}
jobs_list=()
for st in pose-error noise ablation pose-refine; do
    for s in $SCENES; do jobs_list+=("$s:$st"); done
done
run_study() {  # SCENE:STUDY; pose-refine is the pose study at 0, 1, 2 deg with --refine-poses
    local s=${1%%:*} st=${1##*:} extra=()
    if [ "$st" = pose-refine ]; then extra=(--levels 0 1 2 --set refine_poses=true); fi
    $PY -c "import sys; from fastenerf.cli import main; sys.exit(main())" bench study \
        "${st/pose-refine/pose-error}" "$DATA/$s" --out "$OUT/study_${s}_${st}" \
        --steps "$STUDY_STEPS" --device "$DEVICE" --commit "$COMMIT" --quiet "${extra[@]}" \
        > "$OUT/study_${s}_${st}.log" 2>&1
    log "study $s $st done (rc $?)"
}
for j in "${jobs_list[@]}"; do
    while [ "$(jobs -rp | wc -l)" -ge "$STUDY_JOBS" ]; do sleep 2; done
    run_study "$j" &
    sleep 5  # stagger the kernel compilations
done
wait
(cd "$OUT" && tar czf results.tar.gz --exclude='*.pt' progress.log ./*.log \
    study_*/*.json study_*/*.md study_*/*.png evt_*/error_vs_time.* 2>/dev/null)
log "all done"
