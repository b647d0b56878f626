#!/usr/bin/env bash
# The next lease's job (../next_gpu.txt), started detached once Warp is staged (copy this
# folder to .gpu-job with the tiny test scene in .gpu-job/tiny/scene and COMMIT set; `bash
# benchmarks/gpu_start.sh s57` starts it):
# 0. the CUDA-only tests of the graphed step (by name: the GPU machine's Warp compiles no
#    CPU kernels, so the file's CPU cases fail there), the capture after a restart included;
# 1. jitter.txt: #20 at 1°, the default refinement and refine_restart interleaved on every
#    scene, each run's pose error now split by pose_jitter_deg (60 s);
# 2. with what is left, later_runs.txt (BUDGET_S=300): #17's 5-minute runs at the default.
# Everything lands in RES/s57 (poll it with benchmarks/gpu_poll.sh). DEVICE=cpu with small
# scenes, BUDGET_S, BUDGET300 and WARMUP set, and the paths below: a CPU dry run.
set -u
HERE=$(cd "$(dirname "$0")" && pwd)
AFTER=${AFTER:-/var/tmp/after}; DATA=${DATA:-/var/tmp/data}
RES=${RES:-/var/tmp/res}/s57
source "$AFTER/benchmarks/gpu_job_env.sh"  # note, ready, cuda_tests, run_lists, $PY; cd there
T=tests/test_graph_step.py
cuda_tests "$T::test_captured_step_matches_the_device_step" \
    "$T::test_fused_relu_steps_are_the_plain_mlps_steps_captured_or_not" \
    "$T::test_gpu_options_train_as_without_them_captured_or_not" \
    "$T::test_graph_step_flags_an_overflowing_sample_buffer[cuda]" \
    "$T::test_a_failed_capture_leaves_an_eager_step_that_draws_random_numbers" \
    "$T::test_capture_copy_is_a_second_graph_of_the_same_step" \
    "$T::test_a_kept_graph_replays_when_its_capacity_returns" \
    "$T::test_kept_graphs_let_go_when_the_device_is_short_of_memory" \
    "$T::test_a_field_restart_captures_the_new_fields_step"
commit=$(cat "$HERE/COMMIT" 2>/dev/null)
WAIT_READY=900 bash benchmarks/gpu_runs60.sh "$DATA" "$RES/jitter" "$HERE/jitter.txt" "$commit"
note "jitter done"
WAIT_READY=900 BUDGET_S=${BUDGET300:-300} bash benchmarks/gpu_runs60.sh "$DATA" "$RES/long" \
    "$HERE/later_runs.txt" "$commit"
note "long done"
touch "$RES/all.done"
