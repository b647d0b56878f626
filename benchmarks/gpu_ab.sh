#!/usr/bin/env bash
# Before/after 60 s runs side by side in one lease: every line of LIST ("NAME SCENE
# [KEY=VALUE ...]", as for gpu_runs60.sh) is run from the BEFORE tree, then from the AFTER
# tree, back to back, each through benchmarks/gpu_runs60.sh into RES/OUTNAME/{before,after}-K
# as NAME_before and NAME_after (rows SCENE/NAME_before|after for `benchmarks.run_table
# RES/OUTNAME/*/*/* --base NAME_before`); RES/OUTNAME/all.done at the end (what gpu_poll.sh
# waits for). Start it detached (setsid nohup ... &) once Warp is staged:
#
#   [AFTER_SET="KEY=VALUE ..."] bash benchmarks/gpu_ab.sh LIST OUTNAME
#
# BEFORE (/var/tmp/before: e.g. `git archive COMMIT fastenerf kernels viewer setup.py
# 'benchmarks/*.py' 'benchmarks/*.sh'` unpacked), AFTER (/var/tmp/after: the current tree),
# DATA (/var/tmp/data) and RES (/var/tmp/res) may be set. AFTER_SET adds settings to every
# after run only (an option the before tree does not know). Bad input (no LIST, a tree
# without gpu_runs60.sh, an existing RES/OUTNAME) is one line on stderr and exit code 2.
set -u
fail() { echo "gpu_ab.sh: error: $*" >&2; exit 2; }
BEFORE=${BEFORE:-/var/tmp/before}; AFTER=${AFTER:-/var/tmp/after}
DATA=${DATA:-/var/tmp/data}; RES=${RES:-/var/tmp/res}
[ $# -eq 2 ] && [ -f "$1" ] || fail "usage: gpu_ab.sh LIST OUTNAME (LIST a file)"
for tree in "$BEFORE" "$AFTER"; do
    [ -f "$tree/benchmarks/gpu_runs60.sh" ] || fail "$tree is no tree (no benchmarks/gpu_runs60.sh)"
done
LIST=$(realpath "$1"); OUT=$RES/$2
[ ! -e "$OUT" ] || fail "$OUT exists (nothing was run)"
mkdir -p "$OUT" || fail "$OUT cannot be made"
[ -f /var/tmp/gpu-warp/activate.sh ] && source /var/tmp/gpu-warp/activate.sh
k=0
while read -r line; do
    case "$line" in '' | '#'*) continue ;; esac
    k=$((k + 1))
    for t in before after; do
        tree=$BEFORE; extra=""
        [ $t = after ] && tree=$AFTER && extra=${AFTER_SET:-}
        read -r name rest <<< "$line"
        echo "${name}_$t $rest $extra" > "$OUT/line-$k-$t.txt"
        (cd "$tree" && WAIT_READY=${WAIT_READY:-900} bash benchmarks/gpu_runs60.sh "$DATA" \
            "$OUT/$t-$k" "$OUT/line-$k-$t.txt" "$t") >> "$OUT/job.log" 2>&1
        echo "[$(date +%T)] $t $k: ${name}_$t $rest $extra" >> "$OUT/progress.log"
    done
done < "$LIST"
touch "$OUT/all.done"
