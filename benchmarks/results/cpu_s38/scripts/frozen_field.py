"""Does pose refinement stall because the field absorbs the slow error? The pose study's 2°
run (with the motion prior) three ways on one scene, CPU:

- joint: the default, field and poses learnt together from a new field;
- frozen: the field of a clean run (0°, no refinement, same steps) loaded and held fixed
  (lr 0), the poses alone learnt against it;
- warm: that clean field loaded, then field and poses learnt together;
- half: joint from a new field, the field held fixed (lr 0) over the second half;
- pause: joint from a new field, the field held fixed from 40 % to 70 % of the steps.
(The runs in results/cpu_s38/frozen/ were made before this line was fixed: their half and
pause runs, like warm, started from the clean field.)
- slow03 / slow01: joint from a new field, the field's lr x 0.3 over the first 40 % / x 0.1
  over the first 20 % of the steps (the poses' lr as always).
MODES (environment, comma-separated) picks some of joint, frozen, warm, half, pause, slow03,
slow01.

    PYTHONPATH=. python benchmarks/results/cpu_s38/scripts/frozen_field.py SCENE OUT [STEPS]

Writes OUT/{clean,MODE...}/ (runs) and OUT/frozen_field.json (the rotation error
left at each logged step, and each run's PSNR from `fastenerf eval`'s rule).
"""

import json
import os
import subprocess
import sys
from pathlib import Path

from fastenerf.config import train_preset
from fastenerf.data.formats import load_scene_folder
from fastenerf.errors import InputError
from fastenerf.train import Trainer

PRIOR = {"smooth_poses": 121, "smooth_order": 1}  # the CPU pose study's (300 views)
PAUSES = {"half": (0.5, 1.0), "pause": (0.4, 0.7)}  # the field held fixed over these fractions
SLOWS = {"slow03": (0.3, 0.4), "slow01": (0.1, 0.2)}  # (field lr factor, until this fraction)
MODES = os.environ.get("MODES", "joint,frozen,warm,half").split(",")


def config(steps: int, refine: bool):
    extra = {"refine_poses": True, **PRIOR} if refine else {}
    cfg = train_preset("fast", "ngp", device="cpu", steps=steps, log_every=50, **extra)
    if refine:
        cfg.perturb.pose_error_deg = 2.0
    return cfg.validate()


def curve(run: Path) -> list[list[float]]:
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    return [[r["step"], r["pose_error_deg"]] for r in rows if "pose_error_deg" in r]


def main(argv: list[str]) -> int:
    if len(argv) not in (2, 3) or not Path(argv[0]).is_dir() or Path(argv[1]).exists():
        print("frozen_field.py: error: usage: SCENE (a folder) OUT (new) [STEPS]", file=sys.stderr)
        return 2
    scene_dir, out = argv[0], Path(argv[1])
    steps = int(argv[2]) if len(argv) == 3 else 3000
    scene = load_scene_folder(scene_dir)
    res = {}
    try:
        clean = Trainer(scene, config(steps, False), out / "clean")
        clean.run(progress=False)
        state = clean.field.state_dict()
        for mode in MODES:
            tr = Trainer(load_scene_folder(scene_dir), config(steps, True), out / mode)
            if mode in ("frozen", "warm"):
                tr.field.load_state_dict(state)
            if mode == "frozen":
                tr.lr_at = lambda step: 0.0
            if mode in PAUSES:
                lo, hi = (int(f * steps) for f in PAUSES[mode])
                tr.lr_at = lambda s, f=tr.lr_at, lo=lo, hi=hi: 0.0 if lo <= s < hi else f(s)
            if mode in SLOWS:
                k, end = SLOWS[mode][0], int(SLOWS[mode][1] * steps)
                tr.lr_at = lambda s, f=tr.lr_at, k=k, end=end: f(s) * (k if s < end else 1.0)
            tr.run(progress=False)
            res[mode] = {"curve": curve(out / mode)}
            print(mode, res[mode]["curve"][-1], flush=True)
        for mode in ("clean", *MODES):
            ev = out / f"eval_{mode}"
            cmd = ["fastenerf", "eval", str(out / mode), "--out", str(ev), "--no-progress"]
            subprocess.run(cmd, check=True, capture_output=True)
            metrics = json.loads((ev / "metrics.json").read_text())
            res.setdefault(mode, {})["psnr"] = metrics.get("psnr")
            print(mode, "psnr", metrics.get("psnr"), flush=True)
    except (InputError, OSError) as e:
        print(f"frozen_field.py: error: {e}", file=sys.stderr)
        return 2
    (out / "frozen_field.json").write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
