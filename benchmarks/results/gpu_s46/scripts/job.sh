#!/usr/bin/env bash
# The next lease's job (../next_gpu.txt), started detached once Warp is staged (copy this
# folder to .gpu-job, COMMIT set; `bash benchmarks/gpu_start.sh s46` starts it):
# 0. `benchmarks.mlp_widths` (SH in the kernel's layout now), `benchmarks.kernels_render`
#    (march and composite against PyTorch, the single pass beside the two), `profile_step` on
#    toyset and plant from the BEFORE tree (4328e9b: the colour input still on torch's 2-byte
#    cat), and on every scene from this tree with the march's two passes against one;
# 1. runs.txt: 64 windows per step against 16 (shiny; second seeds elsewhere), then the
#    refined run at 0 degrees beside a plain run on its own 64-window batch.
# Everything lands in RES/s46 (poll it with benchmarks/gpu_poll.sh). DEVICE=cpu with small
# scenes, BUDGET_S and WARMUP set, and the paths below: a CPU dry run.
set -u
HERE=$(cd "$(dirname "$0")" && pwd)
AFTER=${AFTER:-/var/tmp/after}; BEFORE=${BEFORE:-/var/tmp/before}; DATA=${DATA:-/var/tmp/data}
RES=${RES:-/var/tmp/res}/s46
source "$AFTER/benchmarks/gpu_job_env.sh"  # note, ready, $PY, DEVICE; cd to the tree
$PY -m benchmarks.mlp_widths --n "${MLP_N:-1900000}" --device "$DEVICE" --out "$RES/mlp_widths.json" \
    > "$RES/mlp_widths.log" 2>&1
note "mlp_widths rc $?"
# #17's march and composite ratios against plain PyTorch since the march's cap became one kernel
$PY -m benchmarks.kernels_render --device "$DEVICE" --repeats "${KR_REPEATS:-20}" \
    > "$RES/kernels_render.json" 2> "$RES/kernels_render.log"
note "kernels_render rc $?"
# the colour input's cat: the BEFORE tree on toyset and plant (the "two" variant below is after)
for s in toyset plant; do
    ready $s
    [ -e "$BEFORE/fastenerf/kernels" ] || ln -s ../kernels "$BEFORE/fastenerf/kernels"
    (cd "$BEFORE" && PYTHONPATH=$BEFORE${PYTHONPATH:+:$PYTHONPATH} $PY -m benchmarks.profile_step \
        --scene "$DATA/$s" --device "$DEVICE" --warmup "${WARMUP:-1000}" --steps 50 --quiet \
        --out "$RES/prof_${s}_before") > "$RES/prof_${s}_before.log" 2>&1
    note "profile $s before rc $?"
done
# the single-pass march against the two passes in the step, every scene (same samples: the
# step time decides the default)
for s in toyset plant lattice shiny blocks; do
    ready $s
    $PY -m benchmarks.profile_step --scene "$DATA/$s" --device "$DEVICE" \
        --warmup "${WARMUP:-1000}" --steps 50 --quiet --out "$RES/prof_${s}_sp" \
        --variant 'two={"backend_options": {"single_pass": false}}' \
        --variant 'one={"backend_options": {"single_pass": true}}' > "$RES/prof_${s}_sp.log" 2>&1
    note "profile $s single pass rc $?"
done
WAIT_READY=900 bash benchmarks/gpu_runs60.sh "$DATA" "$RES/runs" "$HERE/runs.txt" \
    "$(cat "$HERE/COMMIT" 2>/dev/null)"
note "runs done"
touch "$RES/all.done"
