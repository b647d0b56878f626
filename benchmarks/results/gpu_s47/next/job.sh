#!/usr/bin/env bash
# The next lease's job (../next_gpu.txt), started detached once Warp is staged (copy this
# folder to .gpu-job, COMMIT set; `bash benchmarks/gpu_start.sh s48` starts it):
# 0. `profile_step` on plant, blocks and toyset with the default step: each device gap now
#    charged to the training thread's host events, another thread's counted apart, and the
#    kernel that ended it named (gpu_s47: the ~0.5 ms/step "at cudaDeviceSynchronize" had no
#    Python frame or op around it); then blocks and toyset with and without `carve_hidden`
#    side by side (the step at 1,000 steps, marched and trained samples); toyset plain, with
#    64 windows and refined (#20's +17.3 % step there);
#    blocks and toyset with CUDA's launch queues 4x (CUDA_SCALE_LAUNCH_QUEUES);
# 1. runs.txt: `carve_hidden` against the default in 60 s runs on every scene side by side;
#    runs_q4x.txt: blocks and toyset with the 4x queues; runs_ref.txt: #20 at 2 degrees on
#    plant and shiny (not re-run since the twenty-sixth session).
# Everything lands in RES/s48 (poll it with benchmarks/gpu_poll.sh). DEVICE=cpu with small
# scenes, BUDGET_S and WARMUP set, and the paths below: a CPU dry run.
set -u
HERE=$(cd "$(dirname "$0")" && pwd)
AFTER=${AFTER:-/var/tmp/after}; DATA=${DATA:-/var/tmp/data}
RES=${RES:-/var/tmp/res}/s48
source "$AFTER/benchmarks/gpu_job_env.sh"  # note, ready, profile, $PY, DEVICE; cd to the tree
for s in plant blocks toyset; do profile "prof_$s" "$s"; done
# compaction is the GPU default, so the variants differ in carve_hidden alone
for s in blocks toyset; do
    profile "prof_${s}_carve" "$s" \
        --variant 'base={"backend_options": {"carve_hidden": false}}' \
        --variant 'carve={"backend_options": {"carve_hidden": true}}'
done
# #20's refined step on the mesh scene (+17.3 % in gpu_s47's 60 s runs, target 15 %) beside
# the plain step with its batch (64 windows) and the default (16): where the extra time goes
profile prof_toyset_ref toyset --variant 'plain={"train": {}}' \
    --variant 'w64={"train": {"windows_per_step": 64}}' \
    --variant 'ref={"train": {"refine_poses": true}}'
# CUDA's launch queues 4x longer (read when CUDA starts, so per process): the host blocks in
# cudaGraphLaunch at "Command Buffer Full" while the device idles (gpu_s47: 0.38 ms/step on
# blocks, 0.47 on toyset); llama.cpp removed the same bubbles this way
for s in blocks toyset; do CUDA_SCALE_LAUNCH_QUEUES=4x profile "prof_${s}_q4x" "$s"; done
commit=$(cat "$HERE/COMMIT" 2>/dev/null)
WAIT_READY=900 bash benchmarks/gpu_runs60.sh "$DATA" "$RES/runs" "$HERE/runs.txt" "$commit"
CUDA_SCALE_LAUNCH_QUEUES=4x WAIT_READY=900 bash benchmarks/gpu_runs60.sh "$DATA" "$RES/runs_q4x" \
    "$HERE/runs_q4x.txt" "$commit"
WAIT_READY=900 bash benchmarks/gpu_runs60.sh "$DATA" "$RES/runs_ref" "$HERE/runs_ref.txt" "$commit"
note "runs done"
touch "$RES/all.done"
