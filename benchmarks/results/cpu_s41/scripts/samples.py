"""Does a refined run march and train more samples than a plain one once its poses settle?
On the GPU the mesh scene's refined run at 0° marched 2.05 M samples per step against 1.89 M
and trained 1.38 M against 1.20 M at 60 s (gpu_s41). The fast preset on the CPU, 2,048 rays
per step, a STEPS-step budget, compaction as on the GPU (`early_stop_eps` 1e-4,
`compaction_auto`), the refined run with the GPU's settle default (`refine_settle_px` 0.3).

    PYTHONPATH=. python benchmarks/results/cpu_s41/scripts/samples.py SCENE OUT [VARIANT ...]

VARIANT: plain | refined | refined_long (long field windows from the start). Writes
OUT/samples.json: per variant, per 16 steps, the mean marched and trained samples per ray, the
compaction switch's share and state, the field's longest window (views).
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
    "refined_long": {"refine_poses": True},  # no settle: long field windows from the start
}


class Samples(Hook):
    """Mean marched and trained samples per ray over every 16 steps."""

    def __init__(self):
        self.rows: list[dict] = []
        self._sum = [0.0, 0.0, 0]

    def after_step(self, trainer: Trainer, stats: dict) -> None:
        trained = float(stats.get("samples_per_ray", 0.0))
        s = self._sum
        s[0] += float(stats.get("marched_per_ray", trained))
        s[1] += trained
        s[2] += 1
        if trainer.step_count % 16:
            return
        sw = trainer.field.sampler.compaction
        self.rows.append(
            {
                "step": trainer.step_count,
                "marched_per_ray": s[0] / s[2],
                "trained_per_ray": s[1] / s[2],
                "share": None if sw is None else sw.share,
                "on": None if sw is None else sw.on,
                "win_max": getattr(trainer.sampler.windows, "win_max", None),
            }
        )
        self._sum = [0.0, 0.0, 0]


def main(argv: list[str]) -> int:
    names = argv[2:] or list(VARIANTS)
    if len(argv) < 2 or not Path(argv[0]).is_dir() or Path(argv[1]).exists():
        print("samples.py: error: usage: SCENE (a folder) OUT (new) [VARIANT ...]", file=sys.stderr)
        return 2
    if bad := [n for n in names if n not in VARIANTS]:
        print(f"samples.py: error: unknown variant(s) {bad} (known: {list(VARIANTS)})",
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
            hook = Samples()
            tr.run(hooks=[hook], progress=False)
            res[name] = hook.rows
            for r in hook.rows[-3:]:
                print(name, {k: (round(v, 3) if isinstance(v, float) else v) for k, v in r.items()},
                      flush=True)  # fmt: skip
        (out / "samples.json").write_text(json.dumps(res, indent=1))
    except (InputError, OSError) as e:
        print(f"samples.py: error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
