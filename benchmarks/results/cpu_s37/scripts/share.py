"""Does a field that starts on short windows keep more of its marched samples in use?

    python benchmarks/results/cpu_s37/scripts/share.py SCENE_DIR OUT.jsonl [KEY=VALUE ...]

A CPU run (3000 steps, ngp's fast preset) with the GPU's compaction switch on
(`early_stop_eps` 1e-4, `compaction_auto`), refinement at 0° (the pose study's settings) and
the windows given by KEY=VALUE (win_max=15, win_max=60, refine_settle_px=0.3). Every 100 steps:
the share of marched samples compositing used (`CompactionSwitch.share`, what switches
compaction on below 0.65), whether it compacts, samples per ray, the field's window length.
"""

import json
import os
import sys

from fastenerf.config import train_preset
from fastenerf.data.formats.native import load_scene
from fastenerf.errors import InputError
from fastenerf.hooks import Hook, default_hooks
from fastenerf.train import Trainer


class Share(Hook):
    def __init__(self, out):
        self.out = out

    def after_step(self, tr, stats):
        if tr.step_count % 100:
            return
        sampler = tr.field.sampler
        sw = sampler.compaction
        row = {"step": tr.step_count, "share": sw.share, "on": sw.on}
        row["samples_per_ray"] = stats.get("samples_per_ray")
        row["marched_per_ray"] = stats.get("marched_per_ray")
        row["win_max"] = tr.sampler.windows.win_max
        self.out.write(json.dumps(row) + "\n")
        self.out.flush()


def main(scene_dir: str, out: str, sets: list[str]) -> None:
    if os.path.exists(out) or os.path.exists(out + ".run"):
        raise InputError(f"{out}: exists (or its .run folder): give a new name")
    kv = {}
    for s in sets:
        k, _, v = s.partition("=")
        kv[k] = float(v) if "." in v else int(v)
    scene = load_scene(scene_dir)
    opts = {"early_stop_eps": 1e-4, "compaction_auto": True}
    cfg = train_preset(
        "fast", "ngp", steps=3000, device="cpu", refine_poses=True, smooth_poses=121,
        smooth_order=1, eval_every_s=0, checkpoint_every_s=0, backend_options=opts, **kv,
    )  # fmt: skip
    tr = Trainer(scene, cfg, out + ".run")
    with open(out, "w") as f:
        tr.run(hooks=[*default_hooks(tr, False), Share(f)], progress=False)


if __name__ == "__main__":
    if len(sys.argv) < 3:
        print(
            "share.py: error: usage: share.py SCENE_DIR OUT.jsonl [KEY=VALUE ...]", file=sys.stderr
        )
        sys.exit(2)
    try:
        main(sys.argv[1], sys.argv[2], sys.argv[3:])
    except (InputError, ValueError, OSError) as e:
        print(f"share.py: error: {e}", file=sys.stderr)
        sys.exit(2)
