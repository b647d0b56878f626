#!/usr/bin/env bash
# Split ../shared/gpu/stage-warp.sh's first carry (.gpu-warp-a, ~41 MiB) in two, for a checkout
# whose tracked tree (~22 MiB) leaves no room beside it under the device's 64 MiB per call.
# Run from the repo root after stage-warp.sh; then three calls in a row (the machine stays
# warm ~30 s between them):
#   1. carry [".gpu-warp-a1"]  command: bash .gpu-warp-a1/stage.sh
#   2. carry [".gpu-warp-a2"]  command: bash .gpu-warp-a2/stage.sh
#   3. carry [".gpu-warp-b"]   command: source .gpu-warp-b/activate.sh && <your command>
set -euo pipefail
A=.gpu-warp-a/warp.so.xz.part00
[ -f "$A" ] || { echo "gpu_stage_thirds: $A missing: run ../shared/gpu/stage-warp.sh first" >&2; exit 2; }
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
for d in .gpu-warp-a1 .gpu-warp-a2; do
  grep -qxF "/$d/" .git/info/exclude || echo "/$d/" >> .git/info/exclude
done
echo "gpu_stage_thirds: .gpu-warp-a1 $(du -sh .gpu-warp-a1 | cut -f1), .gpu-warp-a2 $(du -sh .gpu-warp-a2 | cut -f1)"
