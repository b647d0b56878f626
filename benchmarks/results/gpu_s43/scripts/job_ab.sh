# Before/after side by side in one lease (next_gpu.txt, list 1): every line of LIST is run
# from the BEFORE tree, then from the AFTER tree, back to back, each through
# benchmarks/gpu_runs60.sh into RES/OUTNAME/{before,after}-K as NAME_before and NAME_after;
# RES/OUTNAME/all.done at the end
# (what gpu_poll.sh waits for). Start it detached (setsid nohup ... &) after Warp is staged:
#   bash job_ab.sh LIST OUTNAME
# BEFORE (/var/tmp/before: `git archive a3a7d02 fastenerf kernels viewer setup.py
# 'benchmarks/*.py' 'benchmarks/*.sh'` unpacked), AFTER (/var/tmp/after: start.sh's copy),
# DATA (/var/tmp/data) and RES (/var/tmp/res) may be set.
set -u
BEFORE=${BEFORE:-/var/tmp/before}; AFTER=${AFTER:-/var/tmp/after}
DATA=${DATA:-/var/tmp/data}; RES=${RES:-/var/tmp/res}
[ $# -eq 2 ] && [ -f "$1" ] || { echo "job_ab.sh: error: usage: job_ab.sh LIST OUTNAME" >&2; exit 2; }
for tree in "$BEFORE" "$AFTER"; do
    [ -f "$tree/benchmarks/gpu_runs60.sh" ] || { echo "job_ab.sh: error: $tree is no tree" >&2; exit 2; }
done
LIST=$(realpath "$1"); OUT=$RES/$2
[ ! -e "$OUT" ] || { echo "job_ab.sh: error: $OUT exists" >&2; exit 2; }
mkdir -p "$OUT"
[ -f /var/tmp/gpu-warp/activate.sh ] && source /var/tmp/gpu-warp/activate.sh
k=0
while read -r line; do
    case "$line" in '' | '#'*) continue ;; esac
    k=$((k + 1))
    for t in before after; do
        tree=$BEFORE; [ $t = after ] && tree=$AFTER
        read -r name rest <<< "$line"
        echo "${name}_$t $rest" > "$OUT/line-$k.txt"  # run_table's rows: SCENE/NAME_before|after
        (cd "$tree" && WAIT_READY=${WAIT_READY:-900} bash benchmarks/gpu_runs60.sh "$DATA" \
            "$OUT/$t-$k" "$OUT/line-$k.txt" "$t") >> "$OUT/job.log" 2>&1
        echo "[$(date +%T)] $t $k: $line" >> "$OUT/progress.log"
    done
done < "$LIST"
touch "$OUT/all.done"
