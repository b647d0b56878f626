"""Training step time, one process: the tree's defaults ("new") against the march without
empty blocks and runs ("march_old") and HEAD's composite backward ("comp_old"), per scene,
order new, march_old, comp_old, new (again)."""

import gc
import json
import os
import sys
from pathlib import Path

import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import oldkernels.composite as oldcomp

import fastenerf.kernels.composite as comp
import fastenerf.kernels.occupancy as occ
import fastenerf.kernels.raymarch as rm
from benchmarks.cpu_preset import build
from benchmarks.curve import load_scene_dir
from benchmarks.step_time import measure

NEW = (comp._Composite, occ.block_factor, rm.RUNS)
MODES = {
    "new": NEW,
    "march_old": (NEW[0], lambda r, c: 1, False),
    "comp_old": (oldcomp._Composite, NEW[1], NEW[2]),
}
data, out = Path(sys.argv[1]), Path(sys.argv[2])
DEV, WARM, STEPS = (
    os.environ.get("DEV", "cuda"),
    int(os.environ.get("WARM", 1000)),
    int(os.environ.get("STEPS", 320)),
)
out.mkdir(parents=True, exist_ok=True)
rows = []
for name in sys.argv[3:]:
    scene = load_scene_dir(data / name)
    for mode in ("new", "march_old", "comp_old", "new"):
        comp._Composite, occ.block_factor, rm.RUNS = MODES[mode]
        tr = build(scene, f"run_{name}_{mode}", {}, 60.0, out, DEV)
        row = measure(tr, WARM, STEPS, True)
        row.update(
            scene=name, mode=mode, gpu=torch.cuda.get_device_name() if DEV == "cuda" else "cpu"
        )
        rows.append(row)
        print(
            json.dumps(
                {
                    k: row[k]
                    for k in (
                        "scene",
                        "mode",
                        "ms_per_step",
                        "samples_per_ray",
                        "step_mode",
                        "captures",
                    )
                }
            ),
            flush=True,
        )
        del tr
        gc.collect()
        if DEV == "cuda":
            torch.cuda.empty_cache()
        json.dump(rows, open(out / "st_ab.json", "w"), indent=1, default=str)
comp._Composite, occ.block_factor, rm.RUNS = NEW
print("done", flush=True)
