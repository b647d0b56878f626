#!/usr/bin/env bash
# The pose study at 0° and 2° with BARF's schedule on the field itself over the first 20 % of
# the steps (refine_c2f_mode=field, refine_c2f_start=0, refine_c2f_end=0.2), CPU, 3000 steps,
# shiny173 then lattice173; against hold.sh's `default` runs (same options otherwise).
#   bash benchmarks/results/cpu_s38/scripts/c2f_field.sh DATA OUT
set -u
[ $# -eq 2 ] && [ -d "$1" ] || { echo "c2f_field.sh: error: usage: c2f_field.sh DATA OUT" >&2; exit 2; }
[ ! -e "$2" ] || { echo "c2f_field.sh: error: $2 exists (nothing written)" >&2; exit 2; }
mkdir -p "$2" 2>/dev/null || { echo "c2f_field.sh: error: $2 cannot be made" >&2; exit 2; }
BASE="refine_poses=true smooth_poses=121 smooth_order=1"
C2F="refine_c2f_mode=field refine_c2f_start=0.0 refine_c2f_end=0.2"
for scene in shiny173 lattice173; do
  fastenerf bench study pose-error "$1/$scene" --levels 0 2 --steps 3000 --device cpu \
    --out "$2/$scene-c2f" --set $BASE $C2F > "$2.$scene.log" 2>&1
  echo "$scene rc $?"
done
