#!/usr/bin/env bash
# The GPU session behind the GPU-bound step (#17), in one script.
#
#   bash benchmarks/gpu_speed.sh DATA OUT COMMIT BEFORE_TREE
#
# DATA holds scene folders (`fastenerf synth --scene NAME --out DATA/NAME`); BEFORE_TREE is a copy
# of the tree before the change (`git archive 898716e fastenerf kernels benchmarks | tar -x -C DIR`).
# Everything lands in OUT; after every stage OUT/partial.tgz holds the logs and JSONs so far.
# Stages (STAGES, in this order; each can be left out):
#   kernels   marching/compositing vs PyTorch, the fixed-capacity march (eager, graph, syncs)
#   profile   one step's profile after (PROFILE_SCENES) and before (BEFORE_SCENES, default
#             blocks): ms/step, the GPU's
#             busy share, samples per ray, host syncs per step. With PROFILE_VARIANTS
#             ("NAME=JSON ...", benchmarks.cpu_preset variants), each variant of the after tree
#             on each scene instead (and BEFORE_TREE may be '-')
#   evt       60 s error-vs-time curves, before then after, on each of SCENES (side by side)
#   variants  the after tree with each VARIANT ("NAME:SETS", SETS a comma-separated --set list,
#             empty for the defaults) on each of SCENES
# On the lent device machine: start it detached (setsid) and keep a call in flight until
# "all done" (the machine is handed back 30 s after the last call returns).
set -u
DEVICE=${DEVICE:-cuda}; BUDGET=${BUDGET:-60}; SCENES=${SCENES:-"blocks plant shiny"}
PROFILE_SCENES=${PROFILE_SCENES:-"blocks plant shiny lattice meshobj"}
STAGES=${STAGES:-"kernels profile evt variants"}; WARMUP=${WARMUP:-1500}
VARIANTS=${VARIANTS:-"cone0:ngp:cone_angle=0 early:ngp:cone_angle=0,ngp:early_cone_angle=0.015625,ngp:early_steps=256"}
PROFILE_VARIANTS=${PROFILE_VARIANTS:-}
DATA=$(realpath "$1"); OUT=$(realpath -m "$2"); COMMIT=${3:-unknown}
BEFORE=$4; [ "$BEFORE" = - ] || BEFORE=$(realpath "$4")
PY=${PY:-python3}
ROOT=$(cd "$(dirname "$0")/.." && pwd)
export PYTHONUNBUFFERED=1
link_package() {  # an uninstalled copy gets the links setup.py's package_dir would make
    [ -e "$1/fastenerf/kernels" ] || ln -s ../kernels "$1/fastenerf/kernels"
    [ -e "$1/fastenerf/viewer" ] || ln -s ../viewer "$1/fastenerf/viewer"
}
link_package "$ROOT"; [ "$BEFORE" = - ] || link_package "$BEFORE"
mkdir -p "$OUT"
T0=$(date +%s)
log() {
    echo "[$(date +%T) +$(($(date +%s) - T0))s] $*" | tee -a "$OUT/progress.log"
    (cd "$OUT" && tar czf partial.tgz.tmp ./*.log ./*/*.json ./*/*.md 2>/dev/null
     mv -f partial.tgz.tmp partial.tgz)
}
want() { [[ " $STAGES " == *" $1 "* ]]; }
in_tree() {  # TREE CMD...: run a python module with that tree's code
    local tree=$1; shift
    (cd "$tree" && PYTHONPATH="$tree:${PYTHONPATH:-}" $PY "$@")
}
log "start: $(nvidia-smi --query-gpu=name --format=csv,noheader 2>/dev/null | head -1), commit $COMMIT"

if want kernels; then
    in_tree "$ROOT" -m benchmarks.kernels_render --device "$DEVICE" > "$OUT/kernels.log" 2>&1
    log "kernels done (rc $?)"
fi
profile() {  # TREE LABEL SCENE [--variant NAME=JSON]
    local tree=$1 label=$2 s=$3; shift 3
    mkdir -p "$OUT/profile_${label}_$s"
    in_tree "$tree" -m benchmarks.profile_step --scene "$DATA/$s" --device "$DEVICE" \
        --warmup "$WARMUP" --steps 30 --out "$OUT/profile_${label}_$s" --commit "$label" \
        --quiet "$@" > "$OUT/profile_${label}_$s.log" 2>&1
    log "profile $label $s done (rc $?)"
}
if want profile && [ -n "$PROFILE_VARIANTS" ]; then
    for s in $PROFILE_SCENES; do
        [ -d "$DATA/$s" ] || continue
        for v in $PROFILE_VARIANTS; do profile "$ROOT" "${v%%=*}" "$s" --variant "$v"; done
    done
elif want profile; then
    if [ "$BEFORE" != - ]; then
        for s in ${BEFORE_SCENES:-blocks}; do [ -d "$DATA/$s" ] && profile "$BEFORE" before "$s"; done
    fi
    for s in $PROFILE_SCENES; do [ -d "$DATA/$s" ] && profile "$ROOT" after "$s"; done
fi
evt() {  # TREE LABEL SCENE [--set ...]
    local tree=$1 label=$2 s=$3; shift 3
    in_tree "$tree" -m benchmarks.error_vs_time --scenes "$DATA/$s" --backends ngp --preset fast \
        --budget-s "ngp=$BUDGET" --device "$DEVICE" --eval-views 10 --warmup-steps 100 \
        --out "$OUT/evt_${label}_$s" --commit "$label" --quiet "$@" > "$OUT/evt_${label}_$s.log" 2>&1
    log "evt $label $s done (rc $?)"
}
if want evt; then
    for s in $SCENES; do
        evt "$BEFORE" before "$s"
        evt "$ROOT" after "$s"
    done
fi
if want variants; then
    for s in $SCENES; do  # scene by scene: a cut-short session still has whole pairs
        for v in $VARIANTS; do
            name=${v%%:*}; sets=${v#*:}
            if [ -n "$sets" ]; then evt "$ROOT" "$name" "$s" --set ${sets//,/ }
            else evt "$ROOT" "$name" "$s"; fi  # "NAME:": the defaults
        done
    done
fi
(cd "$OUT" && tar czf results.tar.gz --exclude='*.pt' progress.log ./*.log ./*/*.json ./*/*.md \
    ./*/*.png 2>/dev/null)
log "all done"
