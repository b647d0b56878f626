# ruff: noqa: E401, E731, B007, E501  (the script as it ran: python train_blocks_ab.py SCENE, blocks at 173x130, 300 frames)
"""CPU training steps with the march's empty blocks (default) and without (block_factor -> 1)."""

import shutil
import sys

import fastenerf.kernels.occupancy as occ
from fastenerf.config import train_preset
from fastenerf.data.formats import load_scene_folder
from fastenerf.train import Trainer

scene = load_scene_folder(sys.argv[1])
orig = occ.block_factor
res = {"blocks": [], "cellwise": []}
for rep in range(3):
    for name in ("blocks", "cellwise"):
        occ.block_factor = orig if name == "blocks" else (lambda r, c: 1)
        out = f"/tmp/cpuab/run_{name}_{rep}"
        shutil.rmtree(out, ignore_errors=True)
        cfg = train_preset("fast", "ngp", device="cpu", steps=400, eval_every_s=1e9)
        tr = Trainer(scene, cfg, out)
        assert tr.field.grid.block == (8 if name == "blocks" else 1) or name == "cellwise", (
            tr.field.grid.block
        )
        t0 = tr.train_seconds
        s = tr.run(hooks=[], progress=False)
        h = tr.history
        late = [x for x in h if x["step"] > 100]
        spr = sum(x.get("samples_per_ray", 0) for x in late) / max(1, len(late))
        ms = (
            (late[-1]["elapsed_s"] - late[0]["elapsed_s"])
            / (late[-1]["step"] - late[0]["step"])
            * 1e3
        )
        res[name].append(ms)
        print(
            rep,
            name,
            "block",
            tr.field.grid.block,
            f"{ms:.1f} ms/step after step 100, samples/ray {spr:.1f}, loss {s['loss']:.4f}",
            flush=True,
        )
print({k: sorted(v)[1] for k, v in res.items()})
