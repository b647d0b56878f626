#!/usr/bin/env bash
# A lease's start, in the call that carries the last Warp piece and `.gpu-job` (a folder with
# the session's job.sh, its lists and COMMIT):
#
#   source .gpu-wp-LAST/activate.sh && bash benchmarks/gpu_start.sh NAME
#
# copies the tree to AFTER (/var/tmp/after; not the Warp pieces, scenes, before tree or
# results) and starts AFTER/.gpu-job/job.sh detached (its output in RES/NAME-job.log, RES
# /var/tmp/res), then prints RES/NAME/progress.log. Poll with `bash benchmarks/gpu_poll.sh
# RES/NAME 560`. Bad input (no NAME, one that is no plain name, no .gpu-job/job.sh) is one
# line on stderr and exit code 2, before anything is copied.
set -u
fail() { echo "gpu_start.sh: error: $*" >&2; exit 2; }
[ $# -eq 1 ] || fail "usage: gpu_start.sh NAME (the results folder under RES)"
[[ "$1" =~ ^[A-Za-z0-9_.-]+$ ]] || fail "NAME $1 is not a plain name (letters, digits, _ . -)"
[ -f .gpu-job/job.sh ] || fail "no .gpu-job/job.sh here ($(pwd)): carry .gpu-job in this call"
AFTER=${AFTER:-/var/tmp/after}; RES=${RES:-/var/tmp/res}
mkdir -p "$AFTER" "$RES/$1" || fail "cannot make $AFTER or $RES/$1"
tar cf - --exclude='./.gpu-wp-*' --exclude='./.gpu-data' --exclude='./.gpu-before' \
    --exclude=./benchmarks/results . | (cd "$AFTER" && tar xf -) || fail "could not copy the tree"
RES=$RES setsid nohup bash "$AFTER/.gpu-job/job.sh" > "$RES/$1-job.log" 2>&1 < /dev/null &
sleep 5; cat "$RES/$1/progress.log" 2>/dev/null
nvidia-smi --query-gpu=name --format=csv,noheader 2>/dev/null || true
