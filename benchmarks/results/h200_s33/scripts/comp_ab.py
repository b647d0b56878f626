# ruff: noqa: B023  (each closure is called within its own loop iteration)
"""Composite block layout: HEAD's kernels (.gpu-job/oldkernels, backward rescans) against the
tree's (backward reads forward's transmittance), same inputs, interleaved, 65,536 rays."""

import json
import os
import sys

import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import oldkernels.composite as old

import fastenerf.kernels.composite as new
from benchmarks import kernels_render as kr
from benchmarks.timing import time_ms

out = {"gpu": torch.cuda.get_device_name()}
for spr in (64, 192):
    sig, rgbs, t_s, t_e, packed = kr._packed_case(65536, spr, "cuda")
    bg = torch.tensor([0.3, 0.5, 0.7], device="cuda")
    g_rgb = torch.randn(65536, 3, device="cuda")

    def run(mod, backward):
        s = sig.clone().requires_grad_(backward)
        c = rgbs.clone().requires_grad_(backward)
        if mod is None:
            o = kr.torch_composite(s, c, t_s, t_e, packed, bg)
        else:
            o = mod.composite(s, c, t_s, t_e, packed, background=bg, layout="block")
        if backward:
            return o, torch.autograd.grad((o["rgb"] * g_rgb).sum() + o["depth"].sum(), (s, c))
        return o, None

    a, ga = run(old, True)
    b, gb = run(new, True)
    same = all(torch.equal(a[k], b[k]) for k in a) and all(
        torch.equal(x, y) for x, y in zip(ga, gb, strict=False)
    )
    r = {"n_samples": int(sig.numel()), "bit_identical": same}
    for _rep in range(3):
        for name, mod in (("old", old), ("new", new), ("torch", None)):
            with torch.no_grad():
                f = time_ms(lambda: run(mod, False), "cuda", 20)
            fb = time_ms(lambda: run(mod, True), "cuda", 20)
            r.setdefault(f"{name}_fwd_ms", []).append(f)
            r.setdefault(f"{name}_fwdbwd_ms", []).append(fb)
    out[str(spr)] = r
    print(spr, json.dumps(r), flush=True)
json.dump(out, open(os.path.join(os.environ["OUT"], "comp_ab.json"), "w"), indent=1)
