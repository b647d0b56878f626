#!/usr/bin/env bash
# The next lease's job (../next_gpu.txt), started detached once Warp is staged (copy this
# folder to .gpu-job with the tiny test scene in .gpu-job/tiny/scene and COMMIT set; `bash
# benchmarks/gpu_start.sh s57` starts it):
# 0. the CUDA-only tests of the graphed step (by name: the GPU machine's Warp compiles no
#    CPU kernels, so the file's CPU cases fail there), the capture after a restart included;
# 1. jitter.txt: #20 at 1°, 60 s: the default refinement against refine_settle_smooth on every
#    scene, refine_restart with and without it on plant, refine_resume on plant and lattice;
#    each run's pose error split by pose_jitter_deg;
# 2. with what is left, later_runs.txt (BUDGET_S=300): #17's 5-minute runs at the default.
# Everything lands in RES/s57 (poll it with benchmarks/gpu_poll.sh). DEVICE=cpu with small
# scenes, BUDGET_S, BUDGET300 and WARMUP set, and the paths below: a CPU dry run.
set -u
HERE=$(cd "$(dirname "$0")" && pwd)
AFTER=${AFTER:-/var/tmp/after}; DATA=${DATA:-/var/tmp/data}
RES=${RES:-/var/tmp/res}/s57
source "$AFTER/benchmarks/gpu_job_env.sh"  # note, ready, cuda_tests, run_lists, $PY; cd there
graph_cuda_tests  # the 12 CUDA cases of tests/test_graph_step.py, by name
commit=$(cat "$HERE/COMMIT" 2>/dev/null)
WAIT_READY=900 bash benchmarks/gpu_runs60.sh "$DATA" "$RES/jitter" "$HERE/jitter.txt" "$commit"
note "jitter done"
WAIT_READY=900 BUDGET_S=${BUDGET300:-300} bash benchmarks/gpu_runs60.sh "$DATA" "$RES/long" \
    "$HERE/later_runs.txt" "$commit"
note "long done"
touch "$RES/all.done"
