#!/usr/bin/env bash
# The next lease's job (../next_gpu.txt), started detached once Warp is staged (copy this
# folder to .gpu-job, COMMIT set; `bash benchmarks/gpu_start.sh s49` starts it):
# 0. `profile_step` on blocks: the default step with each sync gap's lead-in (the host events
#    before the call; gpu_s48: ~0.5 ms/step idle "at cudaDeviceSynchronize" on the training
#    thread with no graph captured), then 8 steps with --stacks --trace (a Chrome trace of
#    the replayed steps) and benchmarks.trace_syncs on it: the sync calls by caller;
# 1. runs.txt: 60 s runs, the default and 4,096 rays a step side by side on every scene
#    (#17: the kernels alone are 3.0-4.4 ms a step at 8,192 rays, 0.7-1.3 M samples);
# 2. runs_frz.txt: #20 at 0 degrees, refined with and without refine_freeze on the mesh
#    scene (its step +17.3 %, target 15 %), refine_freeze on blocks and plant (their 0° cost).
# Everything lands in RES/s49 (poll it with benchmarks/gpu_poll.sh). DEVICE=cpu with small
# scenes, BUDGET_S and WARMUP set, and the paths below: a CPU dry run.
set -u
HERE=$(cd "$(dirname "$0")" && pwd)
AFTER=${AFTER:-/var/tmp/after}; DATA=${DATA:-/var/tmp/data}
RES=${RES:-/var/tmp/res}/s49
source "$AFTER/benchmarks/gpu_job_env.sh"  # note, ready, profile, $PY, DEVICE; cd to the tree
profile prof_blocks blocks
profile prof_blocks_trace blocks --steps 8 --stacks --trace
for call in cudaDeviceSynchronize cudaStreamSynchronize; do  # who asks the device to drain
    $PY -m benchmarks.trace_syncs "$RES/prof_blocks_trace/run/trace.json.gz" --name "$call" \
        --out "$RES/trace_$call.md" > "$RES/trace_$call.log" 2>&1
    note "trace_syncs $call rc $?"
done
commit=$(cat "$HERE/COMMIT" 2>/dev/null)
WAIT_READY=900 bash benchmarks/gpu_runs60.sh "$DATA" "$RES/runs" "$HERE/runs.txt" "$commit"
WAIT_READY=900 bash benchmarks/gpu_runs60.sh "$DATA" "$RES/runs_frz" "$HERE/runs_frz.txt" "$commit"
note "runs done"
touch "$RES/all.done"
