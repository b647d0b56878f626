#!/usr/bin/env bash
# The next lease's job (../next_gpu.txt), started detached once Warp is staged (copy this
# folder to .gpu-job, COMMIT set; `bash benchmarks/gpu_start.sh s47` starts it):
# 0. `kernels_render` (the single pass with slot-major scratch against the two passes);
#    `profile_step` on plant, blocks and toyset with the default step: each device gap's
#    containing host events and the explicit synchronisations by caller (what the
#    0.07-0.83 ms/step the H200 idled at `cudaDeviceSynchronize` comes from), and plant once
#    more with `--stacks` (Python calls in the profile: the path names the line);
# 1. runs.txt: the single-pass march against the two passes, 60 s runs on every scene side by
#    side; then the refined run at 0 degrees on toyset beside its plain runs.
# Everything lands in RES/s47 (poll it with benchmarks/gpu_poll.sh). DEVICE=cpu with small
# scenes, BUDGET_S and WARMUP set, and the paths below: a CPU dry run.
set -u
HERE=$(cd "$(dirname "$0")" && pwd)
AFTER=${AFTER:-/var/tmp/after}; DATA=${DATA:-/var/tmp/data}
RES=${RES:-/var/tmp/res}/s47
source "$AFTER/benchmarks/gpu_job_env.sh"  # note, ready, $PY, DEVICE; cd to the tree
# the allocator's and CUDA's settings the machine starts with (an expandable-segments allocator
# synchronises the device when it unmaps memory)
env | grep -E '^(PYTORCH|CUDA|TORCH|NVIDIA|WARP)' | sort > "$RES/env.txt"
$PY -c "import torch; print(torch.cuda.get_allocator_backend())" >> "$RES/env.txt" 2>&1
# the single pass against the two at 65,536 and 16,384 rays, its scratch slot-major now
# (gpu_s46: 0.88x and 1.06x with rows side by side); the march and composite ratios again
$PY -m benchmarks.kernels_render --device "$DEVICE" --repeats "${KR_REPEATS:-20}" \
    > "$RES/kernels_render.json" 2> "$RES/kernels_render.log"
note "kernels_render rc $?"
for s in plant blocks toyset; do
    ready $s
    $PY -m benchmarks.profile_step --scene "$DATA/$s" --device "$DEVICE" \
        --warmup "${WARMUP:-1000}" --steps 50 --quiet --out "$RES/prof_$s" \
        > "$RES/prof_$s.log" 2>&1
    note "profile $s rc $?"
done
# the same on plant with Python calls recorded: each gap's path names the line it began in
$PY -m benchmarks.profile_step --scene "$DATA/plant" --device "$DEVICE" \
    --warmup "${WARMUP:-1000}" --steps 50 --quiet --stacks --out "$RES/prof_plant_stacks" \
    > "$RES/prof_plant_stacks.log" 2>&1
note "profile plant stacks rc $?"
WAIT_READY=900 bash benchmarks/gpu_runs60.sh "$DATA" "$RES/runs" "$HERE/runs.txt" \
    "$(cat "$HERE/COMMIT" 2>/dev/null)"
note "runs done"
touch "$RES/all.done"
