#!/usr/bin/env bash
# The pose study at 2° with and without refine_diffuse_until=0.4 (the colour held
# view-independent over the first 40 % of the steps; a CPU run has no settle to end it
# sooner), CPU, 3000 steps, lattice173 then shiny173 (`fastenerf synth --scene S --size
# 173x130 --frames 300`), the twenty-sixth session's pose-study options otherwise.
#   bash benchmarks/results/cpu_s53/scripts/diffuse.sh DATA OUT
set -u
[ $# -eq 2 ] && [ -d "$1" ] || { echo "diffuse.sh: error: usage: diffuse.sh DATA OUT" >&2; exit 2; }
[ ! -e "$2" ] || { echo "diffuse.sh: error: $2 exists (nothing written)" >&2; exit 2; }
mkdir -p "$2" 2>/dev/null || { echo "diffuse.sh: error: $2 cannot be made" >&2; exit 2; }
BASE="refine_poses=true smooth_poses=121 smooth_order=1"
for scene in lattice173 shiny173; do
  for v in default diffuse; do
    extra=""; [ "$v" = diffuse ] && extra="refine_diffuse_until=0.4"
    fastenerf bench study pose-error "$1/$scene" --levels 2 --steps 3000 --device cpu \
      --eval-views 10 --out "$2/$scene-$v" --set $BASE $extra > "$2/$scene-$v.log" 2>&1
    echo "$scene $v rc $? $(date +%T)"
  done
done
