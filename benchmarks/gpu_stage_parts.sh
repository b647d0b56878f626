#!/usr/bin/env bash
# Cut the Warp that ../shared/gpu/stage-warp.sh caches into carries of PART_MB MiB each (15
# unless set), for a checkout whose tracked tree leaves less room beside each call than
# gpu_stage_thirds.sh's ~20 MiB pieces need (the device carries 64 MiB a call, tree included).
#
#   bash ../shared/gpu/stage-warp.sh && PART_MB=15 bash benchmarks/gpu_stage_parts.sh
#
# Makes .gpu-wp-00, .gpu-wp-01, ... (ignored by git). On the lent machine, calls in a row (the
# machine goes back 30 s after a call returns), one folder carried per call:
#   carry [".gpu-wp-NN"]  command: bash .gpu-wp-NN/stage.sh        (every folder but the last)
#   carry [the last one]  command: source .gpu-wp-LAST/activate.sh && <your command>
# Later calls on the warm machine: source /var/tmp/gpu-warp/activate.sh && <your command>.
# (GPU_WARP_DIR and GPU_WARP_SITE on the machine move /var/tmp/gpu-warp and /tmp/gpu-warp-site.)
# Bad input (a PART_MB that is no whole number >= 2, no staged Warp in the cache) is one line
# on stderr and exit code 2, and the old pieces are left as they were.
set -euo pipefail
fail() { echo "gpu_stage_parts.sh: error: $*" >&2; exit 2; }
PART_MB=${PART_MB:-15}
[[ "$PART_MB" =~ ^[0-9]+$ ]] && [ "$PART_MB" -ge 2 ] || fail "PART_MB $PART_MB is not a whole number >= 2"
CACHE="${XDG_CACHE_HOME:-$HOME/.cache}/gpu-warp-${WARP_VERSION:-1.19.0}"
[ -f "$CACHE/done" ] || fail "$CACHE has no staged Warp: run ../shared/gpu/stage-warp.sh first"
[ -f "$CACHE/warp_rest.zip" ] || fail "$CACHE/warp_rest.zip missing: run ../shared/gpu/stage-warp.sh again"
tmp=$(mktemp -d .gpu-wp-tmp.XXXX 2>/dev/null) || fail "cannot make a folder in $(pwd)"
trap 'rm -rf "$tmp"' EXIT
# every piece is made in $tmp first: the old pieces go only once the new ones are whole
cat "$CACHE"/warp.so.xz.part* | split -b "$((PART_MB - 1))M" -d -a 2 - "$tmp/xz."
pieces=("$tmp"/xz.*); last=$(( ${#pieces[@]} - 1 ))
for i in "${!pieces[@]}"; do
    d=$(printf "$tmp/.gpu-wp-%02d" "$i"); mkdir "$d"; mv "${pieces[$i]}" "$d/"
    cat > "$d/stage.sh" <<'SH'
set -e; G=${GPU_WARP_DIR:-/var/tmp/gpu-warp}; mkdir -p "$G"; cp "$(dirname "$0")"/xz.* "$G/"; echo "$(basename "$(dirname "$0")") staged"
SH
done
d=$(printf "$tmp/.gpu-wp-%02d" "$last"); cp "$CACHE/warp_rest.zip" "$d/"
cat > "$d/activate.sh" <<SH
# source me on the lent machine after every earlier .gpu-wp-NN/stage.sh: joins the pieces once
_gw_site=${GPU_WARP_SITE:-/tmp/gpu-warp-site}; _gw_dir=${GPU_WARP_DIR:-/var/tmp/gpu-warp}
if [ ! -f "\$_gw_site/warp/bin/warp.so" ]; then
  _gw_here="\$(cd "\$(dirname "\${BASH_SOURCE[0]}")" && pwd)"
  bash "\$_gw_here/stage.sh" > /dev/null
  if [ "\$(ls "\$_gw_dir"/xz.* | wc -l)" -ne $((last + 1)) ]; then
    echo "gpu-warp: pieces missing in \$_gw_dir: stage every .gpu-wp-NN first" >&2
    return 1 2>/dev/null || exit 1
  fi
  mkdir -p "\$_gw_site/warp/bin"
  python3 -c "import zipfile,sys; zipfile.ZipFile(sys.argv[1]).extractall(sys.argv[2])" "\$_gw_here/warp_rest.zip" "\$_gw_site"
  cat "\$_gw_dir"/xz.* | xz -d -T4 > "\$_gw_site/warp/bin/warp.so.tmp" && mv "\$_gw_site/warp/bin/warp.so.tmp" "\$_gw_site/warp/bin/warp.so"
  printf 'export PYTHONPATH="%s\${PYTHONPATH:+:\$PYTHONPATH}" PYTHONUNBUFFERED=1\n' "\$_gw_site" > "\$_gw_dir/activate.sh"
fi
export PYTHONPATH="\$_gw_site\${PYTHONPATH:+:\$PYTHONPATH}"
export PYTHONUNBUFFERED=1
SH
rm -rf .gpu-wp-[0-9][0-9] && mv "$tmp"/.gpu-wp-[0-9][0-9] .
du -sh .gpu-wp-[0-9][0-9] | tr '\n' ' '; echo
