# Sourced first by a lease's job.sh (`.gpu-job/job.sh`, started by gpu_start.sh) once it has
# set RES (its results folder), AFTER (the tree's copy) and DATA (the scenes):
#   RES=${RES:-/var/tmp/res}/NAME; AFTER=...; DATA=...; source "$AFTER/benchmarks/gpu_job_env.sh"
# Makes RES, activates the staged Warp where there is one, sources gpu_env.sh (the links,
# PYTHONPATH, $PY; the working folder becomes the tree) and gives the job
#   note TEXT      a timestamped line in RES/progress.log (what gpu_poll.sh prints)
#   ready SCENE    waits up to 900 s for DATA/SCENE.ready (a later call copies the scene in)
#   profile NAME SCENE [ARGS]   `benchmarks.profile_step` of DATA/SCENE at WARMUP (1000) steps,
#                  50 profiled, into RES/NAME (its log RES/NAME.log), then a progress note
#   profiles NAME=JSON...   `profile --trace` of every scene in $SCENES (the five built-in
#                  and mesh scenes unless set) with these variants in one process each, into
#                  RES/prof_SCENE, then each variant's trace read by `gaps`
#   gaps NAME VARIANT   RES/NAME/VARIANT's trace (a `profile --trace`) read by
#                  `benchmarks.trace_gaps` into RES/gaps_NAME_VARIANT.md, then a progress note
#   cuda_tests TEST_ARGS...   pytest on the tiny test scene HERE/tiny/scene (made before the
#                  lease: the machine cannot draw one) into RES/tests_cuda.log, then a note
#   graph_cuda_tests   cuda_tests of tests/test_graph_step.py's CUDA cases by name (the GPU
#                  machine's staged Warp compiles no CPU kernels: the file's CPU cases fail there)
#   run_lists LIST...   each HERE/LIST (a gpu_runs60.sh list, NAME.txt) in turn into RES/NAME
#                  (the job's HERE/COMMIT recorded), then "runs done" and RES/all.done
# DEVICE (cuda unless set) is exported for the job's commands.
mkdir -p "$RES"
[ -f /var/tmp/gpu-warp/activate.sh ] && source /var/tmp/gpu-warp/activate.sh
OUT=$RES source "$AFTER/benchmarks/gpu_env.sh"
DEVICE=${DEVICE:-cuda}; export DEVICE
note() { echo "[$(date +%T)] $*" >> "$RES/progress.log"; }
ready() { local n=0; while [ ! -e "$DATA/$1.ready" ] && [ $n -lt 450 ]; do sleep 2; n=$((n + 1)); done; }
profile() {
    local name=$1 scene=$2; shift 2
    ready "$scene"
    $PY -m benchmarks.profile_step --scene "$DATA/$scene" --device "$DEVICE" \
        --warmup "${WARMUP:-1000}" --steps 50 --quiet --out "$RES/$name" "$@" > "$RES/$name.log" 2>&1
    note "profile $name rc $?"
}
profiles() {
    local s spec args=()
    for spec in "$@"; do args+=(--variant "$spec"); done
    for s in ${SCENES:-toyset shiny blocks plant lattice}; do
        profile "prof_$s" "$s" --trace "${args[@]}"
        for spec in "$@"; do gaps "prof_$s" "${spec%%=*}"; done
    done
}
gaps() {
    $PY -m benchmarks.trace_gaps "$RES/$1/$2/trace.json.gz" --out "$RES/gaps_$1_$2.md" \
        > "$RES/gaps_$1_$2.log" 2>&1
    note "trace_gaps $1 $2 rc $?"
}
cuda_tests() {
    FASTENERF_TINY_SCENE=$HERE/tiny/scene timeout 600 $PY -m pytest -q -p no:cacheprovider \
        "$@" > "$RES/tests_cuda.log" 2>&1
    note "CUDA tests rc $?"
}
graph_cuda_tests() {
    local t=tests/test_graph_step.py
    cuda_tests "$t::test_captured_step_matches_the_device_step" \
        "$t::test_fused_relu_steps_are_the_plain_mlps_steps_captured_or_not" \
        "$t::test_gpu_options_train_as_without_them_captured_or_not" \
        "$t::test_graph_step_flags_an_overflowing_sample_buffer[cuda]" \
        "$t::test_a_failed_capture_leaves_an_eager_step_that_draws_random_numbers" \
        "$t::test_capture_copy_is_a_second_graph_of_the_same_step" \
        "$t::test_a_kept_graph_replays_when_its_capacity_returns" \
        "$t::test_kept_graphs_let_go_when_the_device_is_short_of_memory" \
        "$t::test_a_field_restart_captures_the_new_fields_step"
}
run_lists() {
    local commit list
    commit=$(cat "$HERE/COMMIT" 2>/dev/null)
    for list in "$@"; do
        WAIT_READY=900 bash benchmarks/gpu_runs60.sh "$DATA" "$RES/${list%.txt}" "$HERE/$list" "$commit"
    done
    note "runs done"
    touch "$RES/all.done"
}
note "start $(nvidia-smi --query-gpu=name --format=csv,noheader 2>/dev/null | head -1)"
