#!/usr/bin/env bash
# The next lease's job (../next_gpu.txt), started detached once Warp is staged (copy this
# folder to .gpu-job with the tiny test scene in .gpu-job/tiny/scene and COMMIT set; `bash
# benchmarks/gpu_start.sh s54` starts it):
# 0. the CUDA-only tests of relu_mask (cuBLASLt's RELU_AUX / DRELU epilogues through ctypes,
#    never run on a GPU before), its step eager and captured, and the fused layer's;
# 1. once every scene is on the machine, `profile_step --trace` of the default (the bf16 SH
#    a thread per four coefficients since gpu_s53) beside relu_mask on, every scene, each
#    trace read by trace_gaps;
# 2. runs.txt: 60 s runs with relu_mask on every scene, and the default on the mesh scene
#    beside it (#17's step);
# 3. runs_20.txt: #20 at 1° with the default refinement (no freeze), every scene, and at 2°
#    with the freeze and refine_diffuse_until (new) on lattice, the mesh scene and shiny.
# Everything lands in RES/s54 (poll it with benchmarks/gpu_poll.sh). DEVICE=cpu with small
# scenes, BUDGET_S and WARMUP set, and the paths below: a CPU dry run.
set -u
HERE=$(cd "$(dirname "$0")" && pwd)
AFTER=${AFTER:-/var/tmp/after}; DATA=${DATA:-/var/tmp/data}
RES=${RES:-/var/tmp/res}/s54
source "$AFTER/benchmarks/gpu_job_env.sh"  # note, ready, profiles, cuda_tests, $PY; cd there
cuda_tests tests/test_relu_mask.py tests/test_mlp_widths.py tests/test_graph_step.py \
    -k "relu_mask or (relu and not falls_back and not needs_a_captured)"
ready shiny  # the last scene staged: the profiles run on a quiet machine
profiles 'base={}' 'mask={"backend_options": {"relu_mask": true}}'
run_lists runs.txt runs_20.txt
