#!/usr/bin/env bash
# The next lease's job (../next_gpu.txt), started detached once Warp is staged (copy this
# folder to .gpu-job, COMMIT set; `bash benchmarks/gpu_start.sh s50` starts it):
# 0. `profile_step --trace` (no --stacks: the host as fast as it trains) on blocks, the mesh
#    scene and plant at the new default (4,096 pixels a step), each trace read by
#    benchmarks.trace_gaps: the device's idle by cause (host late, queued, in graph) and the
#    host op a late launch waited on (gpu_s49: no per-step sync; ~1 ms a step of idle);
# 1. runs.txt: 60 s runs, the new default and 2,048 pixels a step on every scene;
# 2. runs_frz.txt: #20 at 0° at the new default, refined with refine_freeze on the mesh
#    scene, blocks and plant, then without it on the mesh scene (the step target, 15 %).
# Everything lands in RES/s50 (poll it with benchmarks/gpu_poll.sh). DEVICE=cpu with small
# scenes, BUDGET_S and WARMUP set, and the paths below: a CPU dry run.
set -u
HERE=$(cd "$(dirname "$0")" && pwd)
AFTER=${AFTER:-/var/tmp/after}; DATA=${DATA:-/var/tmp/data}
RES=${RES:-/var/tmp/res}/s50
source "$AFTER/benchmarks/gpu_job_env.sh"  # note, ready, profile, $PY, DEVICE; cd to the tree
for s in blocks toyset plant; do
    profile "prof_$s" "$s" --trace
    $PY -m benchmarks.trace_gaps "$RES/prof_$s/run/trace.json.gz" --out "$RES/gaps_$s.md" \
        > "$RES/gaps_$s.log" 2>&1
    note "trace_gaps $s rc $?"
done
commit=$(cat "$HERE/COMMIT" 2>/dev/null)
WAIT_READY=900 bash benchmarks/gpu_runs60.sh "$DATA" "$RES/runs" "$HERE/runs.txt" "$commit"
WAIT_READY=900 bash benchmarks/gpu_runs60.sh "$DATA" "$RES/runs_frz" "$HERE/runs_frz.txt" "$commit"
note "runs done"
touch "$RES/all.done"
