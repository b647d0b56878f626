#!/usr/bin/env bash
# The CPU pose study at 1° with the default refinement and with refine_settle_smooth=31 (the
# corrected turns fitted to a smooth path once where the poses settle, over 31 of the 300 grid
# poses), 3000 steps, on one scene (`fastenerf synth --scene S --size 173x130 --frames 300`).
# The cpu_s55 options otherwise (the GPU default's settle, 0.3 px, which a CPU run does not set).
#   bash benchmarks/results/cpu_s56/scripts/settle_smooth.sh DATA OUT SCENE
set -u
[ $# -eq 3 ] && [ -d "$1/$3" ] || { echo "settle_smooth.sh: error: usage: settle_smooth.sh DATA OUT SCENE (DATA/SCENE a scene folder)" >&2; exit 2; }
[ ! -e "$2/$3-default" ] && [ ! -e "$2/$3-ss31" ] || { echo "settle_smooth.sh: error: $2/$3-* exists (nothing written)" >&2; exit 2; }
mkdir -p "$2" 2>/dev/null || { echo "settle_smooth.sh: error: $2 cannot be made" >&2; exit 2; }
BASE="refine_poses=true smooth_poses=121 smooth_order=1 refine_settle_px=0.3"
for v in default ss31; do
  extra=""; [ "$v" = ss31 ] && extra="refine_settle_smooth=31"
  fastenerf bench study pose-error "$1/$3" --levels 1 --steps 3000 --device cpu \
    --eval-views 10 --out "$2/$3-$v" --set $BASE $extra > "$2/$3-$v.log" 2>&1
  echo "$3 $v rc $? $(date +%T)"
done
