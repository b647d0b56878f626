#!/usr/bin/env bash
# The call that keeps a lent machine busy while a detached list runs, and brings its results back.
#
#   bash benchmarks/gpu_poll.sh RESULTS SECONDS
#
# Waits up to SECONDS for RESULTS/all.done (or, in a folder of lists with no job's
# progress.log of its own, every RESULTS/*/all.done: a job's lists finish one by one before
# the job does), prints the end of the
# progress logs, then packs RESULTS' JSON, JSON lines (the runs' metrics.jsonl: samples marched
# and used, per logged step), gzipped traces (profile_step --trace), Markdown and logs (no
# checkpoints, no partial.tgz)
# into $OUT/res.tgz, the device tool's return folder. Run it back to back, each call within
# 30 s of the last, until the list is done.
set -u
[ $# -eq 2 ] || { echo "gpu_poll.sh: error: usage: gpu_poll.sh RESULTS SECONDS" >&2; exit 2; }
[ -d "$1" ] || { echo "gpu_poll.sh: error: RESULTS $1 is not a folder" >&2; exit 2; }
[[ "$2" =~ ^[0-9]+$ ]] || { echo "gpu_poll.sh: error: SECONDS $2 is not a whole number" >&2; exit 2; }
[ -n "${OUT:-}" ] && [ -d "$OUT" ] || { echo "gpu_poll.sh: error: \$OUT is not a folder" >&2; exit 2; }
RESULTS=$(realpath "$1"); end=$(( $(date +%s) + $2 ))
done_yet() {
    [ -e "$RESULTS/all.done" ] && return 0
    [ -e "$RESULTS/progress.log" ] && return 1
    local d n=0
    for d in "$RESULTS"/*/; do [ -e "$d/all.done" ] || return 1; n=$((n + 1)); done
    [ "$n" -gt 0 ]
}
while ! done_yet && [ "$(date +%s)" -lt "$end" ]; do sleep 5; done
tail -n 6 "$RESULTS"/progress.log "$RESULTS"/*/progress.log 2>/dev/null
(cd "$(dirname "$RESULTS")" && find "$(basename "$RESULTS")" -type f \( -name '*.json' \
    -o -name '*.jsonl' -o -name '*.json.gz' -o -name '*.md' -o -name '*.log' -o -name '*.txt' -o -name all.done \) -print0 |
    tar czf "$OUT/res.tgz" --null -T -)
done_yet && echo "gpu_poll: all done" || echo "gpu_poll: still running"
