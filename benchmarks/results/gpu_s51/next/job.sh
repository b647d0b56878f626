#!/usr/bin/env bash
# The next lease's job (../next_gpu.txt), started detached once Warp is staged (copy this
# folder to .gpu-job with the tiny test scene in .gpu-job/tiny/scene and COMMIT set; `bash
# benchmarks/gpu_start.sh s52` starts it):
# 0. the CUDA-only tests of the fused layer and the captured step, on a tiny scene made
#    before the lease (the machine cannot draw one: no trimesh, no EGL); the two tests that
#    build Warp's CPU kernels are left out (the staged Warp has no CPU compiler);
# 1. the distortion loss's two layouts timed side by side (benchmarks.kernels_render);
# 2. once every scene is on the machine, `profile_step --trace` of the default, of
#    distortion_layout=block and of bf16_features side by side on every scene, each trace
#    read by trace_gaps;
# 3. runs.txt: 60 s runs, the default and both options together, scene by scene;
# 4. runs_frz.txt: #20 at 2° with refine_freeze at the default on plant, the mesh scene and
#    lattice, as far as the budget goes.
# Everything lands in RES/s52 (poll it with benchmarks/gpu_poll.sh). DEVICE=cpu with small
# scenes, BUDGET_S and WARMUP set, and the paths below: a CPU dry run.
set -u
HERE=$(cd "$(dirname "$0")" && pwd)
AFTER=${AFTER:-/var/tmp/after}; DATA=${DATA:-/var/tmp/data}
RES=${RES:-/var/tmp/res}/s52
source "$AFTER/benchmarks/gpu_job_env.sh"  # note, ready, profile, gaps, $PY, DEVICE; cd there
FASTENERF_TINY_SCENE=$HERE/tiny/scene timeout 600 $PY -m pytest -q -p no:cacheprovider \
    tests/test_mlp_widths.py tests/test_graph_step.py \
    -k "(relu or captured or capture_copy) and not falls_back and not needs_a_captured" \
    > "$RES/tests_cuda.log" 2>&1
note "CUDA tests rc $?"
$PY -m benchmarks.kernels_render --device "$DEVICE" --only distortion \
    > "$RES/kernels_distortion.json" 2> "$RES/kernels_distortion.log"
note "kernels_render distortion rc $?"
ready shiny  # the last scene staged: the profiles run on a quiet machine
for s in toyset shiny blocks plant lattice; do
    profile "prof_$s" "$s" --trace --variant 'base={}' \
        --variant 'db={"backend_options": {"distortion_layout": "block"}}' \
        --variant 'bf={"backend_options": {"bf16_features": true}}'
    for v in base db bf; do gaps "prof_$s" $v; done
done
run_lists runs.txt runs_frz.txt
