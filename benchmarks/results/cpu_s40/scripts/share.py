"""Why a refined run's compaction stays off: the share of marched samples compositing uses
(what `compaction_auto` reads), over a run, with and without pose refinement. The fast preset
on the CPU, 2,048 rays per step, STEPS steps, compaction measured as on the GPU
(`early_stop_eps` 1e-4, `compaction_auto`), the refined runs with the GPU's settle default
(`refine_settle_px` 0.3: short windows until the poses settle) unless the variant says.

    PYTHONPATH=. python benchmarks/results/cpu_s40/scripts/share.py SCENE OUT [VARIANT ...]

VARIANT: plain | refined | refined_long (refinement with long windows from the start, no
settle). Writes OUT/share.json: per variant, per occupancy update (every 16 steps), the step,
the share read there, whether compaction was on, and the field's longest window.
"""

import json
import os
import sys
from pathlib import Path

from fastenerf.config import train_preset
from fastenerf.data.formats import load_scene_folder
from fastenerf.errors import InputError
from fastenerf.hooks import Hook
from fastenerf.train import Trainer

STEPS = int(os.environ.get("STEPS", "1500"))
COMPACTION = {"early_stop_eps": 1e-4, "compaction_auto": True}
VARIANTS = {
    "plain": {},
    "refined": {"refine_poses": True, "refine_settle_px": 0.3},
    "refined_long": {"refine_poses": True},
}


class Share(Hook):
    """The compaction switch's share at every occupancy update (16 steps)."""

    def __init__(self):
        self.rows: list[dict] = []

    def after_step(self, trainer: Trainer, stats: dict) -> None:
        sw = trainer.field.sampler.compaction
        if trainer.step_count % 16 == 1 and sw is not None and sw.share is not None:
            win = getattr(trainer.sampler.windows, "win_max", None)
            self.rows.append(
                {"step": trainer.step_count, "share": sw.share, "on": sw.on, "win_max": win}
            )


def main(argv: list[str]) -> int:
    names = argv[2:] or list(VARIANTS)
    if len(argv) < 2 or not Path(argv[0]).is_dir() or Path(argv[1]).exists():
        print("share.py: error: usage: SCENE (a folder) OUT (new) [VARIANT ...]", file=sys.stderr)
        return 2
    if bad := [n for n in names if n not in VARIANTS]:
        print(f"share.py: error: unknown variant(s) {bad} (known: {list(VARIANTS)})",
              file=sys.stderr)  # fmt: skip
        return 2
    out, res = Path(argv[1]), {"steps": STEPS}
    try:
        scene = load_scene_folder(argv[0])
        for name in names:
            cfg = train_preset(
                "fast", "ngp", device="cpu", steps=STEPS, rays_per_step=2048,
                backend_options=COMPACTION, **VARIANTS[name],
            )  # fmt: skip
            tr = Trainer(scene, cfg.validate(), out / name)
            hook = Share()
            tr.run(hooks=[hook], progress=False)
            res[name] = hook.rows
            tail = hook.rows[-5:]
            print(name, [(r["step"], round(r["share"], 3), r["on"], r["win_max"]) for r in tail],
                  flush=True)  # fmt: skip
        (out / "share.json").write_text(json.dumps(res, indent=1))
    except (InputError, OSError) as e:
        print(f"share.py: error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
