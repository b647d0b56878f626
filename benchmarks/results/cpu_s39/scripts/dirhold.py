"""Does holding back view-dependent colour early stop the field absorbing the pose error? The
CPU pose study's run (ngp, the motion prior, 3000 steps) with the colour network's view
directions reduced to their constant spherical-harmonic term over the first FRAC of the steps
(the field can then explain a view-to-view mismatch only by moving geometry or the poses).

    PYTHONPATH=. python benchmarks/results/cpu_s39/scripts/dirhold.py SCENE OUT [STEPS]

RUNS (environment, comma-separated NAME:FRAC:DEG, default
joint:0:2,dir20:0.2:2,dir50:0.5:2,joint0:0:0,dir50_0:0.5:0) picks the runs. Writes OUT/NAME/
(the runs) and OUT/dirhold.json (the rotation error left at each logged step, each run's PSNR
by `fastenerf eval`'s rule).
"""

import json
import os
import subprocess
import sys
from pathlib import Path

import torch

from fastenerf.config import train_preset
from fastenerf.data.formats import load_scene_folder
from fastenerf.errors import InputError
from fastenerf.fields.ngp import NGPField
from fastenerf.train import Trainer

PRIOR = {"smooth_poses": 121, "smooth_order": 1}  # the CPU pose study's (300 views)
RUNS = os.environ.get("RUNS", "joint:0:2,dir20:0.2:2,dir50:0.5:2,joint0:0:0,dir50_0:0.5:0")


def config(steps: int, deg: float):
    cfg = train_preset(
        "fast", "ngp", device="cpu", steps=steps, log_every=50, refine_poses=True, **PRIOR
    )
    cfg.perturb.pose_error_deg = deg
    return cfg.validate()


def hold_directions(tr: Trainer, until: int) -> None:
    """Zero the SH terms of degree >= 1 in the colour network's input while step < until."""
    step = {"s": 0}
    lr_at = tr.lr_at

    def lr_and_step(s, f=lr_at):
        step["s"] = s
        return f(s)

    tr.lr_at = lr_and_step
    radiance = NGPField._radiance.__get__(tr.field)

    def held(geo, d):
        if step["s"] >= until or not torch.is_grad_enabled():
            return radiance(geo, d)
        from fastenerf.fields.ngp import _cast, as_float32, sh_encode

        sh = sh_encode(as_float32(d))
        sh = torch.cat([sh[:, :1], torch.zeros_like(sh[:, 1:])], -1)
        rgb = tr.field.color_net(torch.cat([geo, _cast(sh, geo.dtype)], -1))
        return torch.sigmoid(_cast(rgb, torch.float32))

    tr.field._radiance = held


def parse_args(argv: list[str], prog: str) -> tuple[str, Path, int] | None:
    """SCENE OUT [STEPS] (3000 unless given), or None after one usage line on stderr."""
    bad_n = len(argv) == 3 and not (argv[2].isdigit() and int(argv[2]) > 0)
    if len(argv) not in (2, 3) or not Path(argv[0]).is_dir() or Path(argv[1]).exists() or bad_n:
        print(f"{prog}: error: usage: SCENE (a folder) OUT (new) [STEPS >= 1]", file=sys.stderr)
        return None
    return argv[0], Path(argv[1]), int(argv[2]) if len(argv) == 3 else 3000


def score(out: Path, name: str) -> dict:
    """Run OUT/NAME's rotation error at each logged step and its PSNR by `fastenerf eval`'s
    rule (into OUT/eval_NAME); printed too."""
    rows = [json.loads(x) for x in (out / name / "metrics.jsonl").read_text().splitlines()]
    curve = [[r["step"], r.get("pose_error_deg")] for r in rows]
    ev = out / f"eval_{name}"
    cmd = ["fastenerf", "eval", str(out / name), "--out", str(ev), "--no-progress"]
    subprocess.run(cmd, check=True, capture_output=True)
    psnr = json.loads((ev / "metrics.json").read_text()).get("psnr")
    print(name, psnr, curve[-1], flush=True)
    return {"curve": curve, "psnr": psnr}


def main(argv: list[str]) -> int:
    if (args := parse_args(argv, "dirhold.py")) is None:
        return 2
    scene_dir, out, steps = args
    try:
        runs = [(n, float(f), float(d)) for n, f, d in (r.split(":") for r in RUNS.split(","))]
    except ValueError:
        print(f"dirhold.py: error: RUNS {RUNS!r} is not NAME:FRAC:DEG,...", file=sys.stderr)
        return 2
    res = {}
    try:
        out.mkdir(parents=True)
        for name, frac, deg in runs:
            tr = Trainer(load_scene_folder(scene_dir), config(steps, deg), out / name)
            if frac > 0:
                hold_directions(tr, int(frac * steps))
            tr.run(progress=False)
            res[name] = {"frac": frac, "deg": deg, **score(out, name)}
            (out / "dirhold.json").write_text(json.dumps(res, indent=1))
    except (InputError, OSError, subprocess.CalledProcessError) as e:
        print(f"dirhold.py: error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
