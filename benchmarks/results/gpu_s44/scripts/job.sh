#!/usr/bin/env bash
# The thirty-second session's lease, started detached once Warp is staged:
#   setsid nohup bash /var/tmp/after/benchmarks/results/gpu_s44/scripts/job.sh > /dev/null 2>&1 &
# 1. the table backward's run lengths on ray-ordered and uniform points (benchmarks.hashgrid_runs);
#    R = the fastest on ray order;
# 2. profile_step on every scene, backward_run 1 against R (the same step otherwise);
# 3. list1.txt before (/var/tmp/before, a3a7d02: unpadded colour MLP, a thread per point)
#    and after (this tree with backward_run=R) through benchmarks/gpu_ab.sh;
# 4. list3.txt (#20 at 0 degrees, a second seed) through benchmarks/gpu_runs60.sh.
# Everything lands in /var/tmp/res/s44 (poll it with benchmarks/gpu_poll.sh).
set -u
HERE=$(cd "$(dirname "$0")" && pwd)
AFTER=${AFTER:-/var/tmp/after}; DATA=${DATA:-/var/tmp/data}; RES=${RES:-/var/tmp/res}/s44
DEVICE=${DEVICE:-cuda}; export DEVICE  # (DEVICE=cpu, the paths and BUDGET_S set: a CPU dry run)
mkdir -p "$RES"
[ -f /var/tmp/gpu-warp/activate.sh ] && source /var/tmp/gpu-warp/activate.sh
OUT=$RES source "$AFTER/benchmarks/gpu_env.sh"  # links, PYTHONPATH, $PY; cd to the tree
note() { echo "[$(date +%T)] $*" >> "$RES/progress.log"; }
ready() { local n=0; while [ ! -e "$DATA/$1.ready" ] && [ $n -lt 450 ]; do sleep 2; n=$((n + 1)); done; }
note "start $(nvidia-smi --query-gpu=name --format=csv,noheader 2>/dev/null | head -1)"
$PY -m benchmarks.hashgrid_runs --device "$DEVICE" --json "$RES/runs_micro.json" > "$RES/runs_micro.md" 2>&1
R=$($PY -c "import json; r = json.load(open('$RES/runs_micro.json'))['sets']['ray_order']; print(min(r, key=lambda x: x['bwd_ms'])['run'])" 2>/dev/null || echo 4)
RV=$R; [ "$R" = 1 ] && RV=4  # the profiles compare a run length with 1 either way
note "micro done: R=$R"
for s in toyset plant lattice shiny blocks; do
    ready $s
    $PY -m benchmarks.profile_step --scene "$DATA/$s" --device "$DEVICE" --warmup "${WARMUP:-1000}" --steps 50 \
        --quiet --out "$RES/prof_$s" --variant 'r1={"backend_options": {"backward_run": 1}}' \
        --variant "r$RV={\"backend_options\": {\"backward_run\": $RV}}" > "$RES/prof_$s.log" 2>&1
    note "profile $s rc $?"
done
RES=$(dirname "$RES") AFTER=$AFTER DATA=$DATA AFTER_SET="backward_run=$R" bash benchmarks/gpu_ab.sh "$HERE/list1.txt" s44/ab
note "list 1 done"
WAIT_READY=900 bash benchmarks/gpu_runs60.sh "$DATA" "$RES/l3" "$HERE/list3.txt" "$(cat "$HERE/COMMIT" 2>/dev/null)"
note "list 3 done"
touch "$RES/all.done"
