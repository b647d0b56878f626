"""The CPU pose study's 2° run (ngp, refine_poses, the motion prior, 3000 steps) with training
config overrides per run, side by side in one process: knots against rows on the CPU.

    PYTHONPATH=. python benchmarks/results/cpu_s39/scripts/pose_variants.py SCENE OUT [STEPS]

RUNS (environment, ';'-separated NAME:KEY=VALUE,KEY=VALUE..., default "rows:;k64:refine_knots=64")
picks the runs; DEG (default 2) the perturbation. Writes OUT/NAME/ (the runs) and
OUT/pose_variants.json (the rotation error at each logged step, each run's PSNR by `fastenerf
eval`'s rule).
"""

import json
import os
import subprocess
import sys

from dirhold import parse_args, score  # this folder's (the script's own, first on sys.path)

from fastenerf.config import train_preset
from fastenerf.data.formats import load_scene_folder
from fastenerf.errors import InputError
from fastenerf.train import Trainer

PRIOR = {"smooth_poses": 121, "smooth_order": 1}  # the CPU pose study's (300 views)
RUNS = os.environ.get("RUNS", "rows:;k64:refine_knots=64")


def parse_runs(text: str) -> list[tuple[str, dict]]:
    runs = []
    for item in text.split(";"):
        name, _, sets = item.partition(":")
        kv = dict(s.split("=", 1) for s in sets.split(",") if s)
        runs.append((name, {k: json.loads(v) for k, v in kv.items()}))
    return runs


def main(argv: list[str]) -> int:
    if (args := parse_args(argv, "pose_variants.py")) is None:
        return 2
    scene_dir, out, steps = args
    try:
        runs, deg = parse_runs(RUNS), float(os.environ.get("DEG", "2"))
    except ValueError as e:
        print(f"pose_variants.py: error: RUNS {RUNS!r} or DEG: {e}", file=sys.stderr)
        return 2
    res = {}
    try:
        out.mkdir(parents=True)
        for name, sets in runs:
            cfg = train_preset(
                "fast",
                "ngp",
                device="cpu",
                steps=steps,
                log_every=50,
                refine_poses=True,
                **PRIOR,
                **sets,
            )
            cfg.perturb.pose_error_deg = deg
            Trainer(load_scene_folder(scene_dir), cfg.validate(), out / name).run(progress=False)
            res[name] = {"sets": sets, **score(out, name)}
            (out / "pose_variants.json").write_text(json.dumps(res, indent=1))
    except (InputError, OSError, TypeError, subprocess.CalledProcessError) as e:
        print(f"pose_variants.py: error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
