"""Diagnostic: a fresh field trained on the poses a refined run ended with (its pose
corrections loaded, then held: refine_start 0.999), to tell whether a 2° run's PSNR is held
back by its field's early fit to wrong poses or by the poses it ends with.
Usage: python restart_field.py RUN_A SCENE_DIR OUT [STEPS]"""

import dataclasses
import json
import math
import sys
from pathlib import Path

import torch

from benchmarks.curve import load_scene_dir, train_curve
from benchmarks.session import session_info
from benchmarks.study_report import final_eval
from fastenerf.config import TrainConfig
from fastenerf.evaluate import make_eval_set
from fastenerf.hooks import Hook


class LoadPoses(Hook):
    def __init__(self, ck: Path):
        self.state = torch.load(ck, map_location="cpu", weights_only=False)["self_calibration"]

    def on_start(self, trainer) -> None:
        trainer.selfcal.poses.load_state_dict(self.state["poses"])


def main(run_a: str, scene_dir: str, out: str, steps: int = 3000) -> None:
    conf = json.loads((Path(run_a) / "config.json").read_text())["train"]
    cfg = TrainConfig.from_dict(conf)
    cfg = dataclasses.replace(cfg, refine_start=0.999, steps=steps).validate()
    scene = load_scene_dir(scene_dir)
    ev = make_eval_set(scene, 10, 1.0)
    device = torch.device("cpu")
    train_curve(
        scene,
        cfg,
        out,
        ev,
        [math.inf],
        label={"study": "restart_field"},
        session=session_info(device),
        extra_hooks=[LoadPoses(Path(run_a) / "checkpoint.pt")],
        progress=False,
    )
    fe = final_eval(Path(out), ev, len(ev.views) // 2, device)
    corr = json.loads((Path(out) / "progress.json").read_text()).get("self_calibration")
    print(json.dumps({"psnr": fe["psnr"], "ssim": fe["ssim"], "self_calibration": corr}))


def fail(msg: str) -> None:
    print(f"restart_field.py: error: {msg}", file=sys.stderr)
    sys.exit(2)


if __name__ == "__main__":
    if len(sys.argv) not in (4, 5):
        fail("usage: restart_field.py RUN_A SCENE_DIR OUT [STEPS]")
    a = Path(sys.argv[1])
    if not ((a / "config.json").is_file() and (a / "checkpoint.pt").is_file()):
        fail(f"{a}: no config.json and checkpoint.pt (a finished refined run)")
    if Path(sys.argv[3]).exists():
        fail(f"{sys.argv[3]} exists: give a new folder (nothing was written)")
    if len(sys.argv) == 5 and not (sys.argv[4].isdigit() and int(sys.argv[4]) > 0):
        fail(f"STEPS {sys.argv[4]!r} is not a positive whole number")
    main(sys.argv[1], sys.argv[2], sys.argv[3], *(int(x) for x in sys.argv[4:]))
