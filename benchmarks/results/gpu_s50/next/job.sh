#!/usr/bin/env bash
# The next lease's job (../next_gpu.txt), started detached once Warp is staged (copy this
# folder to .gpu-job, COMMIT set; `bash benchmarks/gpu_start.sh s51` starts it):
# 0. once every scene is on the machine (gpu_s50's first profile ran during the copies),
#    `profile_step --trace` of the default and of `fused_relu` side by side in one process
#    on every scene, each trace read by benchmarks.trace_gaps (the device's busy share and
#    its kernel time by kind, every kernel counted since 3b621b6);
# 1. runs.txt: 60 s runs, the default and fused_relu on every scene, scene by scene;
# 2. runs_frz.txt: #20 at 2° with refine_freeze at 4,096 pixels on blocks and shiny;
# 3. the CUDA-only tests of the fused layer and the captured step (skipped on the CPU CI).
# Everything lands in RES/s51 (poll it with benchmarks/gpu_poll.sh). DEVICE=cpu with small
# scenes, BUDGET_S and WARMUP set, and the paths below: a CPU dry run.
set -u
HERE=$(cd "$(dirname "$0")" && pwd)
AFTER=${AFTER:-/var/tmp/after}; DATA=${DATA:-/var/tmp/data}
RES=${RES:-/var/tmp/res}/s51
source "$AFTER/benchmarks/gpu_job_env.sh"  # note, ready, profile, $PY, DEVICE; cd to the tree
gaps() {  # NAME VARIANT: RES/NAME/VARIANT's trace read into RES/gaps_NAME_VARIANT.md
    $PY -m benchmarks.trace_gaps "$RES/$1/$2/trace.json.gz" --out "$RES/gaps_$1_$2.md" \
        > "$RES/gaps_$1_$2.log" 2>&1
    note "trace_gaps $1 $2 rc $?"
}
ready shiny  # the last scene staged: the profiles run on a quiet machine
for s in blocks toyset plant lattice shiny; do
    profile "prof_$s" "$s" --trace --variant 'base={}' \
        --variant 'fr={"backend_options": {"fused_relu": true}}'
    gaps "prof_$s" base
    gaps "prof_$s" fr
done
run_lists runs.txt runs_frz.txt
rm -f "$RES/all.done"  # the tests come after the runs: done once they are
timeout 600 $PY -m pytest -q -p no:cacheprovider tests/test_mlp_widths.py \
    tests/test_graph_step.py -k "relu or captured or capture_copy" > "$RES/tests_cuda.log" 2>&1
note "CUDA tests rc $?"
touch "$RES/all.done"
