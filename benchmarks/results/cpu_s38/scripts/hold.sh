#!/usr/bin/env bash
# The pose study at 0° and 2° with and without the field held from 40 % to 70 % of the steps
# (refine_hold_start/end), CPU, 3000 steps, shiny173 then lattice173, one run at a time.
# The option exists only in tree ac91ed8 (removed after this measurement).
#   bash benchmarks/results/cpu_s38/scripts/hold.sh DATA OUT
set -u
[ $# -eq 2 ] && [ -d "$1" ] || { echo "hold.sh: error: usage: hold.sh DATA OUT" >&2; exit 2; }
[ ! -e "$2" ] || { echo "hold.sh: error: $2 exists (nothing written)" >&2; exit 2; }
mkdir -p "$2" 2>/dev/null || { echo "hold.sh: error: $2 cannot be made" >&2; exit 2; }
BASE="refine_poses=true smooth_poses=121 smooth_order=1"
for scene in shiny173 lattice173; do
  for v in default hold; do
    extra=""; [ $v = hold ] && extra="refine_hold_start=0.4 refine_hold_end=0.7"
    fastenerf bench study pose-error "$1/$scene" --levels 0 2 --steps 3000 --device cpu \
      --out "$2/$scene-$v" --set $BASE $extra > "$2.$scene-$v.log" 2>&1
    echo "$scene $v rc $?"
  done
done
