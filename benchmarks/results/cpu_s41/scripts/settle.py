"""When does a refined run's field get its long windows, with the settle check's looks from
the pose lr's warm-up end (the default) or from refine_settle_from, at 0° and at 2°? The fast
preset on the CPU, 2,048 rays per step, a STEPS-step budget, compaction as on the GPU, the
GPU's settle tolerance (`refine_settle_px` 0.3, which the CPU leaves off unless set).

    PYTHONPATH=. python benchmarks/results/cpu_s41/scripts/settle.py SCENE OUT [VARIANT ...]

VARIANT: ref0 | ref0_from | ref2 | ref2_from (0° or 2° of pose error; `_from`:
refine_settle_from 0.02, the pose lr's start). Writes OUT/settle.json: per variant, where the
windows lengthened (budget fraction), the pose error left at the end (degrees: mean, and with
the common rotation taken out), and the marched and trained samples per ray every 16 steps
(`samples.py`'s hook).
"""

import json
import os
import sys
from pathlib import Path

from samples import COMPACTION, Samples

from fastenerf.config import train_preset
from fastenerf.data.formats import load_scene_folder
from fastenerf.errors import InputError
from fastenerf.perturb_config import PerturbConfig
from fastenerf.train import Trainer

STEPS = int(os.environ.get("STEPS", "1500"))
SETTLE = {"refine_poses": True, "refine_settle_px": 0.3}
VARIANTS = {
    "ref0": {},
    "ref0_from": {"refine_settle_from": 0.02},
    "ref2": {"perturb": PerturbConfig(pose_error_deg=2.0)},
    "ref2_from": {"perturb": PerturbConfig(pose_error_deg=2.0), "refine_settle_from": 0.02},
}


def run(scene, out: Path, name: str) -> dict:
    cfg = train_preset(
        "fast", "ngp", device="cpu", steps=STEPS, rays_per_step=2048,
        backend_options=COMPACTION, **SETTLE, **VARIANTS[name],
    )  # fmt: skip
    tr = Trainer(scene, cfg.validate(), out / name)
    hook = Samples()
    tr.run(hooks=[hook], progress=False)
    stats = tr.selfcal.stats()
    keys = ("pose_error_deg", "pose_error_aligned_deg", "pose_correction_deg")
    return {
        "settled_at": tr.selfcal.pose_cal.settle.settled_at,
        **{k: float(stats[k]) for k in keys if k in stats},
        "samples": hook.rows,
    }


def main(argv: list[str]) -> int:
    names = argv[2:] or list(VARIANTS)
    if len(argv) < 2 or not Path(argv[0]).is_dir() or Path(argv[1]).exists():
        print("settle.py: error: usage: SCENE (a folder) OUT (new) [VARIANT ...]", file=sys.stderr)
        return 2
    if bad := [n for n in names if n not in VARIANTS]:
        print(f"settle.py: error: unknown variant(s) {bad} (known: {list(VARIANTS)})",
              file=sys.stderr)  # fmt: skip
        return 2
    out, res = Path(argv[1]), {"steps": STEPS}
    try:
        scene = load_scene_folder(argv[0])
        for name in names:
            res[name] = run(scene, out, name)
            r = {k: v for k, v in res[name].items() if k != "samples"}
            print(name, r, res[name]["samples"][-1], flush=True)
        (out / "settle.json").write_text(json.dumps(res, indent=1))
    except (InputError, OSError) as e:
        print(f"settle.py: error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
