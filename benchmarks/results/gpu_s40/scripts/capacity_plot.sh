#!/usr/bin/env bash
# capacity.png, from the repository root: bash benchmarks/results/gpu_s40/scripts/capacity_plot.sh
set -eu
R=benchmarks/results/gpu_s40
args=()
for s in blocks plant toyset lattice; do
    args+=("$s (H100):default=$R/lease2_h100/$s/none0" "$s (H100):capacity=$R/lease2_h100/$s/cap_0")
    [ "$s" = lattice ] || args+=("$s (H100):capacity+refined=$R/lease2_h100/$s/capk_0")
done
for s in shiny lattice; do
    b=$([ "$s" = lattice ] && echo b || true)
    args+=("$s (H200):default=$R/lease3_h200/$s/none0$b" "$s (H200):capacity=$R/lease3_h200/$s/cap_0$b"
           "$s (H200):capacity+refined=$R/lease3_h200/$s/capk_0")
done
python -m benchmarks.compare_runs "${1:-$R/capacity.png}" "${args[@]}"
