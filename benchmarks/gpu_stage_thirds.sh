#!/usr/bin/env bash
# Split ../shared/gpu/stage-warp.sh's two carries (.gpu-warp-a ~41 MiB, .gpu-warp-b ~39 MiB) in
# four of about 20 MiB, for a checkout whose tracked tree (~29 MiB) leaves no room beside either
# under the device's 64 MiB per call. Run from the repo root after stage-warp.sh; then four
# calls in a row (the machine goes back 30 s after a call returns: chain them, and the first
# poll, with nothing in between):
#   1. carry [".gpu-warp-a1", <a scene folder or two>]  command: bash .gpu-warp-a1/stage.sh
#   2. carry [".gpu-warp-a2", <your job files>]         command: bash .gpu-warp-a2/stage.sh
#   3. carry [".gpu-warp-b0"]                           command: bash .gpu-warp-b0/stage.sh
#   4. carry [".gpu-warp-b"]   command: source .gpu-warp-b/activate.sh && <your command>
# Later calls on that warm machine: source /var/tmp/gpu-warp/activate.sh && <your command>.
# A scene too large to go beside the tree in one call: benchmarks/gpu_carry_scene.sh.
set -euo pipefail
A=.gpu-warp-a/warp.so.xz.part00
B=.gpu-warp-b/warp.so.xz.part01
fail() { echo "gpu_stage_thirds: $* missing: run ../shared/gpu/stage-warp.sh first" >&2; exit 2; }
[ -f "$A" ] || fail "$A"
[ -f "$B" ] || [ -f .gpu-warp-b/bq.01 ] || fail "$B"
rm -rf .gpu-warp-a1 .gpu-warp-a2 && mkdir -p .gpu-warp-a1 .gpu-warp-a2
split -b 21M -d "$A" .gpu-warp-a1/p00.
mv .gpu-warp-a1/p00.01 .gpu-warp-a2/
cat > .gpu-warp-a1/stage.sh <<'SH'
set -e; mkdir -p /var/tmp/gpu-warp; cp "$(dirname "$0")"/p00.00 /var/tmp/gpu-warp/; echo "a1 staged"
SH
cat > .gpu-warp-a2/stage.sh <<'SH'
set -e; G=/var/tmp/gpu-warp; cp "$(dirname "$0")"/p00.01 $G/
cat $G/p00.00 $G/p00.01 > $G/warp.so.xz.part00 && rm $G/p00.0*; echo "a staged"
SH
if [ -f "$B" ]; then  # b's half goes in two: bq.00 ahead in b0, bq.01 stays, joined on activation
  rm -rf .gpu-warp-b0 && mkdir -p .gpu-warp-b0
  split -b 19M -d "$B" .gpu-warp-b/bq. && rm "$B" && mv .gpu-warp-b/bq.00 .gpu-warp-b0/
  cat > .gpu-warp-b0/stage.sh <<'SH'
set -e; mkdir -p /var/tmp/gpu-warp; cp "$(dirname "$0")"/bq.00 /var/tmp/gpu-warp/; echo "b0 staged"
SH
  mv .gpu-warp-b/activate.sh .gpu-warp-b/activate-whole.sh
  cat > .gpu-warp-b/activate.sh <<'SH'
# source me: joins b's two pieces, then stage-warp.sh's own activation
_gw_b="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
if [ -f /tmp/gpu-warp-site/warp/bin/warp.so ]; then
  export PYTHONPATH="/tmp/gpu-warp-site${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
else
  [ -f "$_gw_b/warp.so.xz.part01" ] || cat /var/tmp/gpu-warp/bq.00 "$_gw_b/bq.01" > "$_gw_b/warp.so.xz.part01"
  source "$_gw_b/activate-whole.sh"
fi
SH
fi
for d in .gpu-warp-a1 .gpu-warp-a2 .gpu-warp-b0; do
  grep -qxF "/$d/" .git/info/exclude 2>/dev/null || echo "/$d/" >> .git/info/exclude
done
du -sh .gpu-warp-a1 .gpu-warp-a2 .gpu-warp-b0 .gpu-warp-b | tr '\n' ' '; echo
