#!/usr/bin/env bash
# The next lease's job (../next_gpu.txt), started detached once Warp is staged (copy this
# folder to .gpu-job with the tiny test scene in .gpu-job/tiny/scene and COMMIT set; `bash
# benchmarks/gpu_start.sh s55` starts it):
# 0. the CUDA-only tests of the graphed step, the kept graphs' (graph_keys, new) among them;
# 1. runs.txt: 60 s runs of graph_keys=4 beside the default, scene by scene (#17's step:
#    the mesh scene's 60 s run is 3.05 ms a step, and its capacity turned back 79 times);
# 2. with what is left, one 300 s run of the default on plant (#17's 5-minute target; the
#    first line of later_runs.txt), cut off wherever the lease ends.
# Everything lands in RES/s55 (poll it with benchmarks/gpu_poll.sh). DEVICE=cpu with small
# scenes, BUDGET_S and WARMUP set, and the paths below: a CPU dry run.
set -u
HERE=$(cd "$(dirname "$0")" && pwd)
AFTER=${AFTER:-/var/tmp/after}; DATA=${DATA:-/var/tmp/data}
RES=${RES:-/var/tmp/res}/s55
source "$AFTER/benchmarks/gpu_job_env.sh"  # note, ready, cuda_tests, run_lists, $PY; cd there
cuda_tests tests/test_graph_step.py
commit=$(cat "$HERE/COMMIT" 2>/dev/null)
WAIT_READY=900 bash benchmarks/gpu_runs60.sh "$DATA" "$RES/runs" "$HERE/runs.txt" "$commit"
note "runs done"
grep -E '^long0 plant' "$HERE/later_runs.txt" > "$RES/long_plant.txt"
BUDGET_S=${LONG_S:-300} WAIT_READY=900 bash benchmarks/gpu_runs60.sh "$DATA" "$RES/long" \
    "$RES/long_plant.txt" "$commit"
note "long done"
touch "$RES/all.done"
