#!/usr/bin/env bash
# The next lease's job (../next_gpu.txt), started detached once Warp is staged (copy this
# folder to .gpu-job with the tiny test scene in .gpu-job/tiny/scene and COMMIT set; `bash
# benchmarks/gpu_start.sh s55` starts it):
# 0. the CUDA-only tests of the graphed step, the kept graphs' (graph_keys, new) among them;
# 1. runs.txt: 60 s runs of graph_keys=4 beside the default, scene by scene (#17's step:
#    the mesh scene's 60 s run is 3.05 ms a step, and its capacity turned back 79 times);
# 2. benchmarks.fused_mlp_probe: both MLPs fully fused in Warp tiles against torch's GEMMs,
#    forward and forward+backward at 2^20 samples (new; at most 5 min, the cuBLASDx compile
#    included), whether a fused MLP is worth building (#17);
# 3. with what is left, settle1.txt: #20 at 1° with the windows lengthening at 1 px of
#    pose movement instead of 0.3 (refine_settle_px), and with the long windows from the
#    start (the pose gradient from short ones), scene by scene, cut off wherever the lease
#    ends.
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
timeout 300 $PY -m benchmarks.fused_mlp_probe --device "$DEVICE" --out "$RES/fused_mlp_probe.json" \
    > "$RES/fused_mlp_probe.log" 2>&1
note "fused_mlp_probe rc $?"
WAIT_READY=900 bash benchmarks/gpu_runs60.sh "$DATA" "$RES/settle1" "$HERE/settle1.txt" "$commit"
note "settle1 done"
touch "$RES/all.done"
