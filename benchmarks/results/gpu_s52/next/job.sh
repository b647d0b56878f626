#!/usr/bin/env bash
# The next lease's job (../next_gpu.txt), started detached once Warp is staged (copy this
# folder to .gpu-job with the tiny test scene in .gpu-job/tiny/scene and COMMIT set; `bash
# benchmarks/gpu_start.sh s53` starts it):
# 0. the CUDA-only tests (the three gpu_s52 saw fail from their helper's trainer order, and
#    the fused layer's and the captured step's), on a tiny scene made before the lease; the
#    two that build Warp's CPU kernels are left out (the staged Warp has no CPU compiler);
# 1. benchmarks.kernels_encoding: the hash grid and the SH, float32 and bf16 (the bf16 SH
#    rewritten a thread a coefficient since gpu_s52);
# 2. once every scene is on the machine, `profile_step --trace` of the new defaults (block
#    distortion, bf16 features, density_logit) beside both options off, every scene, each
#    trace read by trace_gaps;
# 3. runs.txt: 60 s runs of the default, scene by scene (#17's step at the new defaults);
# 4. runs_frz.txt: #20 at 1° with refine_freeze on every scene, as far as the budget goes.
# Everything lands in RES/s53 (poll it with benchmarks/gpu_poll.sh). DEVICE=cpu with small
# scenes, BUDGET_S and WARMUP set, and the paths below: a CPU dry run.
set -u
HERE=$(cd "$(dirname "$0")" && pwd)
AFTER=${AFTER:-/var/tmp/after}; DATA=${DATA:-/var/tmp/data}
RES=${RES:-/var/tmp/res}/s53
source "$AFTER/benchmarks/gpu_job_env.sh"  # note, ready, profile, gaps, cuda_tests, $PY; cd there
cuda_tests tests/test_mlp_widths.py tests/test_graph_step.py \
    -k "(relu or captured or capture_copy) and not falls_back and not needs_a_captured"
$PY -m benchmarks.kernels_encoding --device "$DEVICE" --json "$RES/kernels_encoding.json" \
    > "$RES/kernels_encoding.log" 2>&1
note "kernels_encoding rc $?"
ready shiny  # the last scene staged: the profiles run on a quiet machine
for s in toyset shiny blocks plant lattice; do
    profile "prof_$s" "$s" --trace --variant 'base={}' \
        --variant 'off={"backend_options": {"distortion_layout": "ray", "bf16_features": false}}'
    for v in base off; do gaps "prof_$s" $v; done
done
run_lists runs.txt runs_frz.txt
