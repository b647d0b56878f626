#!/usr/bin/env bash
# The pose study at 0° and 1° with the default refinement and with refine_restart (a new
# field once the poses settle), CPU, 3000 steps, on one scene (`fastenerf synth --scene S
# --size 173x130 --frames 300`). A CPU run sets no settle tolerance: both variants take the
# GPU default's 0.3 px, so the windows lengthen (and the restart happens) where a GPU run's
# would; the twenty-sixth session's pose-study options otherwise.
#   bash benchmarks/results/cpu_s55/scripts/restart.sh DATA OUT SCENE
set -u
[ $# -eq 3 ] && [ -d "$1/$3" ] || { echo "restart.sh: error: usage: restart.sh DATA OUT SCENE (DATA/SCENE a scene folder)" >&2; exit 2; }
[ ! -e "$2/$3-default" ] && [ ! -e "$2/$3-restart" ] || { echo "restart.sh: error: $2/$3-* exists (nothing written)" >&2; exit 2; }
mkdir -p "$2" 2>/dev/null || { echo "restart.sh: error: $2 cannot be made" >&2; exit 2; }
BASE="refine_poses=true smooth_poses=121 smooth_order=1 refine_settle_px=0.3"
for v in default restart; do
  extra=""; [ "$v" = restart ] && extra="refine_restart=true"
  fastenerf bench study pose-error "$1/$3" --levels 0 1 --steps 3000 --device cpu \
    --eval-views 10 --out "$2/$3-$v" --set $BASE $extra > "$2/$3-$v.log" 2>&1
  echo "$3 $v rc $? $(date +%T)"
done
