"""Refinement's extra time per step, sorted into the brief's candidates (1)-(5), from the
full op lists of out/rfull (prof.py with all ops). python buckets.py [rays] [base] [refine]"""

import json
import re
import sys

S = "/work/scratch/s38prof/out/rfull"
rays = sys.argv[1] if len(sys.argv) > 1 else "2048"
a, b = (sys.argv[2], sys.argv[3]) if len(sys.argv) > 3 else ("base", "refine")
ra = json.load(open(f"{S}/rays{rays}/{a}/profile_step.json"))
rb = json.load(open(f"{S}/rays{rays}/{b}/profile_step.json"))
oa, ob = ra["top_cpu_ops_ms"], rb["top_cpu_ops_ms"]
BUCKETS = [
    ("(1) hash-grid grad_x kernel (backward_x)", r"backward_x$"),
    (
        "(1) hash-grid backward's Python + c2f g*w (_HashGridEncodeBackward self, aten::mul)",
        r"^_HashGridEncodeBackward$|^aten::mul$",
    ),
    (
        "(1') grad through _normalise (clamp/nan_to_num/div backward: ge/le/ne/eq/where/div/...)",
        r"^aten::(ge|le|ne|eq|where|div|logical_and|copy_|masked_fill|mul_|zeros_like|sub|add)$",
    ),
    ("(2) ray_points backward", r"_RayPointsBackward|_points_backward"),
    ("(3) view-direction gradient (SH backward)", r"_SHEncodeBackward|_sh_backward"),
    (
        "(4) pose rays + row Adam",
        r"PoseRays|_gather_rays|_ray_grads|_row_grads|_delta_grads|"
        r"_corrected_rows|_gauge_sums|_row_adam|_has_gradient|RowAdam|pose",
    ),
]
tot = {name: 0.0 for name, _ in BUCKETS}
rest = {}
for k in set(oa) | set(ob):
    d = ob.get(k, 0.0) - oa.get(k, 0.0)
    for name, pat in BUCKETS:
        if re.search(pat, k):
            tot[name] += d
            break
    else:
        rest[k] = d
sa, sb = sum(oa.values()), sum(ob.values())
print(f"rays/step {rays}: {a} -> {b} (one profiled run each, 20 steps), ms/step")
print(f"| | {a} | {b} | Δ |\n|---|---:|---:|---:|")
print(
    f"| step wall (unprofiled) | {ra['wall_ms_unprofiled']:.1f} | {rb['wall_ms_unprofiled']:.1f} "
    f"| {rb['wall_ms_unprofiled'] - ra['wall_ms_unprofiled']:+.1f} |"
)
print(
    f"| step wall (profiled) | {ra['wall_ms']:.1f} | {rb['wall_ms']:.1f} "
    f"| {rb['wall_ms'] - ra['wall_ms']:+.1f} |"
)
print(f"| sum of op self CPU | {sa:.1f} | {sb:.1f} | {sb - sa:+.1f} |")
print(
    f"| (5) host/Python outside ops (wall - ops) | {ra['wall_ms'] - sa:.1f} "
    f"| {rb['wall_ms'] - sb:.1f} "
    f"| {(rb['wall_ms'] - sb) - (ra['wall_ms'] - sa):+.1f} |"
)
for name, v in tot.items():
    print(f"| {name} | | | {v:+.2f} |")
other = sum(rest.values())
big = sorted(rest.items(), key=lambda kv: -abs(kv[1]))[:8]
print(
    f"| other ops (net; largest: {', '.join(f'{k} {v:+.2f}' for k, v in big)}) | | | {other:+.2f} |"
)
print("\nrefine run, top ops (self CPU ms/step):")
for k, v in list(ob.items())[:14]:
    print(f"  {k:60s} {v:7.2f}   (base {oa.get(k, 0):.2f})")
print("refine-only ops:", {k: round(v, 3) for k, v in ob.items() if k not in oa and v > 0.01})
