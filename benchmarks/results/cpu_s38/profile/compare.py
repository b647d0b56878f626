"""Per-op self CPU time (ms/step), mean of rounds, refinement vs none; from out/r*/rays*/NAME.
python /work/scratch/s38prof/compare.py [rays] [base] [refine]"""

import glob
import json
import sys
from collections import defaultdict

S = "/work/scratch/s38prof/out"
rays = sys.argv[1] if len(sys.argv) > 1 else "2048"
a, b = (sys.argv[2], sys.argv[3]) if len(sys.argv) > 3 else ("base", "refine")


def load(name):
    runs = [
        json.load(open(p)) for p in sorted(glob.glob(f"{S}/r*/rays{rays}/{name}/profile_step.json"))
    ]
    ops = defaultdict(float)
    for r in runs:
        for k, v in r["top_cpu_ops_ms"].items():
            ops[k] += v / len(runs)
    mean = lambda key: sum(r[key] for r in runs) / len(runs)  # noqa: E731
    stages = {k: sum(r["host_ms"][k] for r in runs) / len(runs) for k in runs[0]["host_ms"]}
    return (
        ops,
        mean("wall_ms_unprofiled"),
        mean("wall_ms"),
        mean("samples_per_step"),
        stages,
        len(runs),
    )


oa, pa, wa, sa, ha, n = load(a)
ob, pb, wb, sb, hb, _ = load(b)
print(f"rays/step {rays}: {a} vs {b}, mean of {n} rounds")
print(f"| | {a} | {b} | Δ |\n|---|---:|---:|---:|")
print(f"| wall ms/step (unprofiled) | {pa:.1f} | {pb:.1f} | {pb - pa:+.1f} |")
print(f"| wall ms/step (profiled) | {wa:.1f} | {wb:.1f} | {wb - wa:+.1f} |")
print(f"| samples/step | {sa:,.0f} | {sb:,.0f} | |")
for k in ha:
    print(f"| stage {k} (incl.) | {ha[k]:.2f} | {hb[k]:.2f} | {hb[k] - ha[k]:+.2f} |")
keys = sorted(set(oa) | set(ob), key=lambda k: -(ob.get(k, 0) - oa.get(k, 0)))
print("| op (self CPU) | | | |")
tot = 0.0
for k in keys:
    d = ob.get(k, 0) - oa.get(k, 0)
    tot += d
    if abs(d) >= 0.05 or k.startswith("wp::_kernels"):
        print(f"| {k} | {oa.get(k, 0):.2f} | {ob.get(k, 0):.2f} | {d:+.2f} |")
print(f"| sum of listed-op Δ (top-40 lists) | | | {tot:+.2f} |")
