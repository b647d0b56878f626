"""What the x-gradient costs with coarse-to-fine holding levels off, now that `backward_x` skips
a level whose weights are all 0: the hash grid's forward and backward (table and x) on the
CPU, side by side in one process, the x-gradient weighted with every level on, with levels
1..K on, and with no x-gradient at all (x not requiring grad).

    PYTHONPATH=. python benchmarks/results/cpu_s40/scripts/level_skip.py OUT [N_POINTS]

The fast preset's grid (16 levels x 2 features, T = 2^19), N_POINTS points (default 2^16),
REPEATS rounds of each variant in turn (median of the rounds). Writes OUT/level_skip.json.
"""

import json
import os
import statistics
import sys
import time
from pathlib import Path

import torch

from fastenerf.kernels.hashgrid import HashGridConfig, hash_grid_encode, init_table

REPEATS = int(os.environ.get("REPEATS", "7"))
CFG = HashGridConfig(
    n_levels=16, n_features=2, log2_table_size=19, base_resolution=16, max_resolution=2048
)


def weights(levels_on: int | None) -> torch.Tensor | None:
    """(L*F,) weights with the first `levels_on` levels at 1 and the rest 0 (None: none)."""
    if levels_on is None:
        return None
    w = torch.zeros(CFG.n_levels, CFG.n_features)
    w[:levels_on] = 1.0
    return w.reshape(-1)


def step_ms(x: torch.Tensor, table: torch.Tensor, variant: tuple) -> float:
    grad_x, levels_on = variant
    xi = x.clone().requires_grad_(grad_x)
    t0 = time.perf_counter()
    enc = hash_grid_encode(xi, table, CFG, x_grad_weights=weights(levels_on))
    enc.sum().backward()
    return 1e3 * (time.perf_counter() - t0)


def main(argv: list[str]) -> int:
    ok = len(argv) in (1, 2) and not Path(argv[0]).exists()
    if ok and len(argv) == 2:
        ok = argv[1].isdigit() and int(argv[1]) > 0
    if not ok:
        print("level_skip.py: error: usage: OUT (new) [N_POINTS >= 1]", file=sys.stderr)
        return 2
    n = int(argv[1]) if len(argv) == 2 else 1 << 16
    gen = torch.Generator().manual_seed(0)
    x = torch.rand(n, 3, generator=gen)
    table = init_table(CFG, generator=gen).requires_grad_(True)
    variants = {
        "no x-gradient": (False, None),
        "x-gradient, 1 of 16 levels on": (True, 1),
        "x-gradient, 8 of 16 levels on": (True, 8),
        "x-gradient, 16 of 16 levels on": (True, 16),
    }
    times: dict[str, list[float]] = {k: [] for k in variants}
    for v in variants.values():
        step_ms(x, table, v)  # kernel build and first-touch, untimed
    for _ in range(REPEATS):
        for name, v in variants.items():
            times[name].append(step_ms(x, table, v))
    res = {
        "points": n,
        "repeats": REPEATS,
        "torch_threads": torch.get_num_threads(),
        "ms": {k: statistics.median(v) for k, v in times.items()},
    }
    for k, v in res["ms"].items():
        print(f"{k}: {v:.1f} ms", flush=True)
    out = Path(argv[0])
    out.mkdir(parents=True)
    (out / "level_skip.json").write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
