#!/usr/bin/env bash
# The GPU benchmark session behind benchmarks/RESULTS.md (issues #5, #6), in one script.
#
#   bash benchmarks/gpu_run.sh DATA OUT [COMMIT] [TOTAL_S]
#
# DATA holds the scene folders blocks/ and plant/ (`fastenerf synth --scene NAME --out DATA/NAME`);
# everything lands in OUT. It needs a CUDA machine with torch and warp-lang; the project need
# not be installed (the repo root goes on PYTHONPATH). In order of importance, so that a cut
# session still has the main figures:
#   1. profile of one ngp training step (blocks)
#   2. error vs time: ngp on blocks (300 s), then the viewer's frame rate on that trained run
#      (render only and through EGL + GL when moderngl is importable) and a snapshot
#   3. error vs time: vanilla on blocks, ngp on plant, vanilla on plant; vanilla's budget is
#      read from OUT/vanilla_budget_s when present (default 240 s), so a caller can set it
#      while the script runs
#   4. if time is left, ngp on blocks with a 60 s budget (OUT/evt60)
#   5. the combined error-vs-time outputs, eval sheets of the ngp runs, results.tar.gz
# On the lent device machine: start it detached (setsid) in one call and keep a call in flight
# (`sleep 540; cp OUT/partial.tgz $OUT/; cat OUT/progress.log`) until "all done": the machine is
# handed back 30 s after the last call returns, and the detached run dies with it. After every
# stage OUT/partial.tgz holds the logs and curves so far, so each keep-alive call can bring them
# home (a session whose device time runs out mid-run keeps what was finished).
# Device time (H100, 2026-11-23): start + staging ~1 min, profile 45 s, ngp 300 s ~6 min,
# vanilla 200 s ~3.5 min per scene, collect + eval 40 s: ~23 min with VIEWER=0 and TOTAL_S 1230.
# TOTAL_S (default 1380) bounds the wall time of steps 1-3; each run gets what is left.
# DEVICE, NGP_S, VIEW_SIZE, VIEW_FRAMES, PROFILE_WARMUP (environment) shrink it for a CPU try;
# VIEWER=0 leaves out the viewer's measurements (step 2's second half).
set -u
DEVICE=${DEVICE:-cuda}; NGP_S=${NGP_S:-300}; VIEW_SIZE=${VIEW_SIZE:-800x600}
VIEW_FRAMES=${VIEW_FRAMES:-100}; PROFILE_WARMUP=${PROFILE_WARMUP:-300}; VIEWER=${VIEWER:-1}
DATA=$(realpath "$1"); OUT=$(realpath -m "$2"); COMMIT=${3:-unknown}; TOTAL=${4:-1380}
PY=${PY:-python3}
ROOT=$(cd "$(dirname "$0")/.." && pwd)
cd "$ROOT"
export PYTHONPATH=$ROOT:${PYTHONPATH:-} PYTHONUNBUFFERED=1
# setup.py maps kernels/ and viewer/ into the package; an uninstalled copy (the device machine)
# gets links instead — never a checkout that imports them already (the links are git-ignored)
if ! $PY -c "import fastenerf.kernels, fastenerf.viewer" 2>/dev/null; then
    [ -e fastenerf/kernels ] || ln -s ../kernels fastenerf/kernels
    [ -e fastenerf/viewer ] || ln -s ../viewer fastenerf/viewer
fi
mkdir -p "$OUT"
T0=$(date +%s)
left() { echo $((TOTAL - ($(date +%s) - T0))); }
log() {
    echo "[$(date +%T) +$(($(date +%s) - T0))s] $*" | tee -a "$OUT/progress.log"
    (cd "$OUT" && tar czf partial.tgz.tmp ./*.log profile/*.json profile/*.md \
        evt/runs/*/curve.json 2>/dev/null; mv -f partial.tgz.tmp partial.tgz)
}
fnerf() { $PY -c "import sys; from fastenerf.cli import main; sys.exit(main())" "$@"; }
EVT=(-m benchmarks.error_vs_time --device $DEVICE --eval-views 10 --out "$OUT/evt" --commit "$COMMIT"
     --quiet)
NGP=(--backends ngp --preset fast --budget-s "ngp=$NGP_S")
VAN=(--backends vanilla --preset eventnerf)

log "start: $(nvidia-smi --query-gpu=name --format=csv,noheader 2>/dev/null | head -1), commit $COMMIT"
$PY -m benchmarks.profile_step --scene "$DATA/blocks" --device "$DEVICE" --warmup "$PROFILE_WARMUP" --steps 50 \
    --out "$OUT/profile" --commit "$COMMIT" --quiet > "$OUT/profile.log" 2>&1
log "profile done (rc $?)"

$PY "${EVT[@]}" --scenes "$DATA/blocks" "${NGP[@]}" \
    --max-wall-s "$(left)" > "$OUT/evt_blocks_ngp.log" 2>&1
log "ngp blocks done (rc $?)"

RUN="$OUT/evt/runs/blocks-ngp"
if [ "$VIEWER" = 1 ]; then
    $PY -m fastenerf.viewer.bench "$RUN" --size "$VIEW_SIZE" --frames "$VIEW_FRAMES" --no-gl \
        --chunk 65536 262144 1048576 --out "$OUT/viewer_render.json" > "$OUT/viewer.log" 2>&1
    log "viewer render-only done (rc $?)"
    if $PY -c "import moderngl" 2>/dev/null; then
        $PY -m fastenerf.viewer.bench "$RUN" --size "$VIEW_SIZE" --frames "$VIEW_FRAMES" \
            --out "$OUT/viewer_gl.json" >> "$OUT/viewer.log" 2>&1
        log "viewer GL done (rc $?)"
        fnerf view "$RUN" --snapshot "$OUT/viewer_snapshot.png" --size "$VIEW_SIZE" \
            --view-index 0 >> "$OUT/viewer.log" 2>&1
        log "snapshot done (rc $?)"
    fi
fi

vbudget() { cat "$OUT/vanilla_budget_s" 2>/dev/null || echo 240; }
$PY "${EVT[@]}" --scenes "$DATA/blocks" "${VAN[@]}" --budget-s "vanilla=$(vbudget)" \
    --max-wall-s "$(left)" > "$OUT/evt_blocks_vanilla.log" 2>&1
log "vanilla blocks done (rc $?)"
$PY "${EVT[@]}" --scenes "$DATA/plant" "${NGP[@]}" \
    --max-wall-s "$(left)" > "$OUT/evt_plant_ngp.log" 2>&1
log "ngp plant done (rc $?)"
$PY "${EVT[@]}" --scenes "$DATA/plant" "${VAN[@]}" --budget-s "vanilla=$(vbudget)" \
    --max-wall-s "$(( $(left) > 30 ? $(left) : 30 ))" > "$OUT/evt_plant_vanilla.log" 2>&1
log "vanilla plant done (rc $?)"

# If time is left: ngp on blocks with a 60 s budget (the budget rule then marches with cone
# 1/256), the fair ngp point for the time-to-PSNR ratio against vanilla's best above.
if [ "$(left)" -gt 100 ]; then
    $PY "${EVT[@]}" --out "$OUT/evt60" --scenes "$DATA/blocks" --backends ngp --preset fast \
        --budget-s ngp=60 --max-wall-s "$(left)" > "$OUT/evt_blocks_ngp60.log" 2>&1
    log "ngp blocks 60 s done (rc $?)"
fi

# Collect: every run of OUT/evt (finished or cut) into one json/png/md; no training happens
# (finished runs return at once; cut ones get a zero wall budget).
$PY "${EVT[@]}" --scenes "$DATA/blocks" "$DATA/plant" --backends ngp vanilla \
    --preset ngp=fast vanilla=eventnerf --budget-s "ngp=$NGP_S" "vanilla=$(vbudget)" --resume --max-wall-s 0 \
    > "$OUT/evt_collect.log" 2>&1
log "collected (rc $?)"
for s in blocks plant; do
    fnerf eval "$OUT/evt/runs/$s-ngp" --views 8 --out "$OUT/eval_$s" --no-progress \
        > "$OUT/eval_$s.log" 2>&1
    log "eval $s done (rc $?)"
done
(cd "$OUT" && tar czf results.tar.gz --exclude='evt/runs/*/checkpoint*' --exclude='*.pt' \
    progress.log ./*.log ./*.json ./*.png profile evt/error_vs_time.* evt/runs/*/curve.json \
    evt60/error_vs_time.json \
    eval_*/sheet.png evt/runs/*/metrics.json 2>/dev/null)
log "all done"
