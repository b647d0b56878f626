#!/usr/bin/env bash
# The next lease's job (../next_gpu.txt), started detached once Warp is staged (copy this
# folder to .gpu-job, COMMIT set; `bash benchmarks/gpu_start.sh s50` starts it):
# 0. `profile_step --trace` (no --stacks: the host as fast as it trains) on blocks, the mesh
#    scene and plant at the new default (4,096 pixels a step), each trace read by
#    benchmarks.trace_gaps: the device's idle by cause (host late, queued, in graph) and the
#    host op a late launch waited on (gpu_s49: no per-step sync; ~1 ms a step of idle);
#    then blocks with the grid update 8 steps away from the sampler's block draw
#    (`update_offset=8`: the two host-heavy jobs of every 16 steps no longer in one step);
#    then blocks with the step captured twice, the copies replayed in turn (graph_copies=2),
#    and benchmarks.graph_relaunch on blocks and the mesh scene: the step's graph replayed
#    alone, back to back, and alternating with a second capture of it;
# 1. runs.txt: 60 s runs, the new default and 2,048 pixels a step on every scene;
# 2. runs_frz.txt: #20 at 0° at the new default, refined with refine_freeze on the mesh
#    scene, blocks and plant, then without it on the mesh scene (the step target, 15 %).
# Everything lands in RES/s50 (poll it with benchmarks/gpu_poll.sh). DEVICE=cpu with small
# scenes, BUDGET_S and WARMUP set, and the paths below: a CPU dry run.
set -u
HERE=$(cd "$(dirname "$0")" && pwd)
AFTER=${AFTER:-/var/tmp/after}; DATA=${DATA:-/var/tmp/data}
RES=${RES:-/var/tmp/res}/s50
source "$AFTER/benchmarks/gpu_job_env.sh"  # note, ready, profile, $PY, DEVICE; cd to the tree
gaps() {  # NAME: the device idle of RES/NAME's trace by cause, into RES/gaps_NAME.md
    $PY -m benchmarks.trace_gaps "$RES/$1/run/trace.json.gz" --out "$RES/gaps_$1.md" \
        > "$RES/gaps_$1.log" 2>&1
    note "trace_gaps $1 rc $?"
}
for s in blocks toyset plant; do
    profile "prof_$s" "$s" --trace
    gaps "prof_$s"
done
# the grid update 8 steps off the sampler's block draw (update_offset, off by default)
profile prof_blocks_off8 blocks --trace --variant 'off8={"backend_options": {"update_offset": 8}}'
gaps prof_blocks_off8
# the step captured twice and the copies replayed in turn (graph_copies, 1 by default)
profile prof_blocks_gc2 blocks --trace --variant 'gc2={"train": {"graph_copies": 2}}'
gaps prof_blocks_gc2
for s in blocks toyset; do  # one graph relaunched back to back, against two in turn
    $PY -m benchmarks.graph_relaunch --scene "$DATA/$s" --device "$DEVICE" --quiet \
        --out "$RES/relaunch_$s" > "$RES/relaunch_$s.log" 2>&1
    note "graph_relaunch $s rc $?"
done
run_lists runs.txt runs_frz.txt
