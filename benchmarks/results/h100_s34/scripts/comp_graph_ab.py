"""Composite block layout, replayed from CUDA graphs: the tree's kernels (backward rescans the
optical depths) against 41770eb's (.gpu-job/stkernels: forward keeps each sample's outgoing
transmittance), same inputs, interleaved, 65,536 rays, 64 and 192 samples per ray."""

import json
import os
import sys

import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import stkernels.composite as stored

import fastenerf.kernels.composite as tree
from benchmarks import kernels_render as kr

out = {"gpu": torch.cuda.get_device_name()}
for spr in (64, 192):
    sig, rgbs, t_s, t_e, packed = kr._packed_case(65536, spr, "cuda")
    bg = torch.tensor([0.3, 0.5, 0.7], device="cuda")
    g_rgb = torch.randn(65536, 3, device="cuda")
    graphs, res = {}, {}
    for name, mod in (("tree", tree), ("stored", stored)):
        s, c = sig.clone().requires_grad_(), rgbs.clone().requires_grad_()

        def step(mod=mod, s=s, c=c, t_s=t_s, t_e=t_e, packed=packed, bg=bg, g_rgb=g_rgb):
            o = mod.composite(s, c, t_s, t_e, packed, background=bg, layout="block")
            return (o["rgb"], o["depth"]) + torch.autograd.grad(
                (o["rgb"] * g_rgb).sum() + o["depth"].sum(), (s, c)
            )

        graphs[name], res[name] = kr._captured(step)
        graphs[name].replay()
    torch.cuda.synchronize()
    r = {
        "n_samples": int(sig.numel()),
        "bit_identical": all(
            torch.equal(a, b) for a, b in zip(res["tree"], res["stored"], strict=True)
        ),
    }
    for _rep in range(6):
        for name in ("tree", "stored"):
            r.setdefault(f"{name}_fwdbwd_graph_ms", []).append(
                kr._time_ms(graphs[name].replay, "cuda", 50)
            )
    out[str(spr)] = r
    print(spr, json.dumps(r), flush=True)
json.dump(out, open(os.path.join(os.environ["OUT"], "comp_graph_ab.json"), "w"), indent=1)
