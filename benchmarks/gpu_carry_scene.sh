#!/usr/bin/env bash
# Cut a scene folder into carries that fit beside the tree under the device's 64 MiB per call,
# each with a stage.sh that lands it on the machine; whichever part completes the set (any
# order) joins them into DATA/NAME and touches DATA/NAME.ready (what `WAIT_READY` in
# gpu_runs60.sh waits for).
#
#   bash benchmarks/gpu_carry_scene.sh SCENE_DIR OUT_PREFIX [PART_MB]
#
# Writes OUT_PREFIX.p0, OUT_PREFIX.p1, ... (PART_MB MiB each, default 14). Carry one per call,
# in any order, each with the command `bash OUT_PREFIX.pK/stage.sh` (DATA: /var/tmp/data
# unless set on the machine). The scene's folder name is the name it gets there.
# Bad input (no SCENE_DIR, a PART_MB that is no whole number, an OUT_PREFIX.p* that exists,
# a folder for them that cannot be made) ends with one line on stderr and exit code 2 before
# anything is written.
set -u
fail() { echo "gpu_carry_scene.sh: error: $*" >&2; exit 2; }
[ $# -ge 2 ] && [ $# -le 3 ] || fail "usage: gpu_carry_scene.sh SCENE_DIR OUT_PREFIX [PART_MB]"
[ -d "$1" ] || fail "SCENE_DIR $1 is not a folder"
MB=${3:-14}
[[ "$MB" =~ ^[1-9][0-9]*$ ]] || fail "PART_MB $MB is not a whole number of MiB >= 1"
! compgen -G "$2.p[0-9]*" > /dev/null \
    || fail "$2.p* exists: remove the old parts or give a new prefix (nothing written)"
mkdir -p "$(dirname "$2")" 2>/dev/null && [ -w "$(dirname "$2")" ] \
    || fail "$(dirname "$2") cannot be made or written (nothing written)"
SRC=$(cd "$(dirname "$1")" && pwd); NAME=$(basename "$1"); OUT=$2
TMP=$(mktemp -d) || fail "no temporary folder"
trap 'rm -rf "$TMP"' EXIT
(cd "$SRC" && tar cf - "$NAME") | split -b "${MB}M" -d -a 3 - "$TMP/part." \
    || fail "could not pack $1"
parts=("$TMP"/part.*)
n=${#parts[@]}
for k in "${!parts[@]}"; do
    d="$OUT.p$k"
    mkdir -p "$d" 2>/dev/null || fail "$d cannot be made"
    mv "${parts[$k]}" "$d/"
    cat > "$d/stage.sh" <<SH
# part $((k + 1)) of $n of scene $NAME (benchmarks/gpu_carry_scene.sh)
set -e; DATA=\${DATA:-/var/tmp/data}; P="\$DATA/.parts-$NAME"; mkdir -p "\$P"
cp "\$(dirname "\$0")"/part.* "\$P/"
here=\$(ls "\$P" | wc -l)
if [ "\$here" = $n ]; then
  cat "\$P"/part.* | (cd "\$DATA" && tar xf -) && rm -rf "\$P" && touch "\$DATA/$NAME.ready"
  echo "scene $NAME staged"
else
  echo "scene $NAME: part $((k + 1)) of $n (\$here of $n here)"
fi
SH
done
echo "$n part(s): $(printf '%s ' "$OUT".p*)"
