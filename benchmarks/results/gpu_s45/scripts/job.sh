#!/usr/bin/env bash
# The gpu_s45 lease's job (gpu_s44/next_gpu.txt's lists 0, 1 and 4, the runs reordered to
# fit one lease), started detached once Warp is staged (copy this folder to .gpu-job; `bash benchmarks/gpu_start.sh s45` starts it)
# 0. `benchmarks.mlp_widths` (padded against padded_cat) and `profile_step` on toyset and plant
#    from the BEFORE tree (29e5ae3: the segment cap and the colour input before c35496d and
#    85e6ee1) and from this tree, one scene after the other;
# 1. runs.txt: diagonal_steps 768 on every scene beside its plain run, then #20's cost at
#    0 degrees split (plant, blocks), then diagonal_steps 512 where the budget allows.
# Everything lands in RES/s45 (poll it with benchmarks/gpu_poll.sh). DEVICE=cpu with small
# scenes, BUDGET_S and WARMUP set, and the paths below: a CPU dry run.
set -u
HERE=$(cd "$(dirname "$0")" && pwd)
AFTER=${AFTER:-/var/tmp/after}; BEFORE=${BEFORE:-/var/tmp/before}; DATA=${DATA:-/var/tmp/data}
RES=${RES:-/var/tmp/res}/s45
source "$AFTER/benchmarks/gpu_job_env.sh"  # note, ready, $PY, DEVICE; cd to the tree
$PY -m benchmarks.mlp_widths --n "${MLP_N:-1900000}" --device "$DEVICE" --out "$RES/mlp_widths.json" \
    > "$RES/mlp_widths.log" 2>&1
note "mlp_widths rc $?"
for s in toyset plant; do
    ready $s
    for t in before after; do
        tree=$AFTER; [ $t = before ] && tree=$BEFORE
        [ -e "$tree/fastenerf/kernels" ] || ln -s ../kernels "$tree/fastenerf/kernels"
        (cd "$tree" && PYTHONPATH=$tree${PYTHONPATH:+:$PYTHONPATH} $PY -m benchmarks.profile_step --scene "$DATA/$s" \
            --device "$DEVICE" --warmup "${WARMUP:-1000}" --steps 50 --quiet \
            --out "$RES/prof_${s}_$t") > "$RES/prof_${s}_$t.log" 2>&1
        note "profile $s $t rc $?"
    done
done
WAIT_READY=900 bash benchmarks/gpu_runs60.sh "$DATA" "$RES/runs" "$HERE/runs.txt" \
    "$(cat "$HERE/COMMIT" 2>/dev/null)"
note "runs done"
touch "$RES/all.done"
