"""The x-gradient mask on the CPU: benchmarks.profile_step's step wall with the mask (the
tree's), without it (SelfCalibration.grad_rays patched to None) and with no refinement at all
(`plain`), alternated in one process.

    python benchmarks/results/cpu_s38/scripts/mask_ab.py SCENE OUT [REPEATS]

Refined (refine_start 0) on windows up to 200 views, the pose gradient from those up to 50
(what the GPU default trains on once the poses settle), 2,048 rays per step on the CPU. On the
GPU: `DEVICE=cuda WARMUP=1500` (the preset's rays per step; warm-up steps past the early
cone and the occupancy grid's first carving).
"""

import json
import os
import sys
from pathlib import Path

import benchmarks.profile_step as P
from fastenerf.errors import InputError
from fastenerf.self_calibration import SelfCalibration

DEVICE, WARMUP = os.environ.get("DEVICE", "cpu"), os.environ.get("WARMUP", "100")
TRAIN = {"refine_poses": True, "refine_start": 0.0, "win_max": 200, "refine_win_max": 50}
if DEVICE == "cpu":
    TRAIN["rays_per_step"] = 2048


def main(argv: list[str]) -> int:
    why = None
    if len(argv) not in (2, 3):
        why = "usage: mask_ab.py SCENE OUT [REPEATS]"
    elif not Path(argv[0]).is_dir():
        why = f"SCENE {argv[0]} is not a folder"
    elif len(argv) == 3 and not (argv[2].isdigit() and int(argv[2]) > 0):
        why = f"REPEATS must be a whole number >= 1, got {argv[2]!r}"
    elif DEVICE not in ("cpu", "cuda") or not WARMUP.isdigit():
        why = f"DEVICE must be cpu or cuda and WARMUP a whole number, got {DEVICE}, {WARMUP}"
    if why:
        print(f"mask_ab.py: error: {why}", file=sys.stderr)
        return 2
    out, repeats = Path(argv[1]), int(argv[2]) if len(argv) == 3 else 2
    if out.exists():
        print(f"mask_ab.py: error: {out} exists (nothing written)", file=sys.stderr)
        return 2
    prop, rows = SelfCalibration.grad_rays, []
    plain = {**TRAIN, "refine_poses": False}
    plain.pop("refine_win_max")
    for r in range(repeats):
        for name in ("mask", "no_mask", "plain"):
            train = plain if name == "plain" else TRAIN
            variant = f"{name}=" + json.dumps({"train": train})
            SelfCalibration.grad_rays = prop if name == "mask" else property(lambda s: None)
            d = out / f"{name}_{r}"
            args = ["--scene", argv[0], "--device", DEVICE, "--warmup", WARMUP, "--steps", "20"]
            try:
                rc = P.main([*args, "--variant", variant, "--out", str(d)])
            except (InputError, OSError) as e:
                print(f"mask_ab.py: error: {e}", file=sys.stderr)
                return 2
            if rc != 0:
                return rc  # profile_step said what was wrong, in one line
            res = json.loads((d / "profile_step.json").read_text())
            rows.append(
                {
                    "variant": name,
                    "repeat": r,
                    **{
                        k: res.get(k) for k in ("wall_ms_unprofiled", "wall_ms", "samples_per_step")
                    },
                }
            )
            print(rows[-1], flush=True)
    SelfCalibration.grad_rays = prop
    (out / "mask_ab.json").write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
