"""Diagnostic: a refined run's field scored on the test views as given and with every test
camera turned by the world rotation W its learnt training poses share against the truth
(R_learnt ≈ W · R_true, `se3.mean_world_rotation`; centres kept), to tell how much of a 2°
run's loss is that shared turn. Usage: python gauge_eval.py RUN SCENE_DIR"""

import dataclasses
import json
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

from benchmarks.curve import load_scene_dir
from fastenerf.config import TrainConfig
from fastenerf.evaluate import evaluate_field, make_eval_set
from fastenerf.run import load_checkpoint
from fastenerf.se3 import mean_world_rotation, so3_exp
from fastenerf.train import Trainer
from fastenerf.train_state import restore


def main(run: str, scene_dir: str) -> None:
    conf = json.loads((Path(run) / "config.json").read_text())["train"]
    scene = load_scene_dir(scene_dir)
    with tempfile.TemporaryDirectory() as tmp:  # the trainer's own folder, not the run's
        tr = Trainer(scene, TrainConfig.from_dict(conf), Path(tmp))
        restore(tr, load_checkpoint(Path(run) / "checkpoint.pt"))
    pr = tr.selfcal.poses
    with torch.no_grad():
        d = pr.corrections().double()
        R = so3_exp(d[:, :3]) @ pr.base[:, :3, :3].double()
        W = mean_world_rotation(R, pr.true_c2w.double()[:, :3, :3], pr.used.double())
    ev = make_eval_set(scene, 10, 1.0)
    turned = ev.c2w.copy()
    turned[:, :3, :3] = W.numpy() @ ev.c2w[:, :3, :3]
    out = {}
    for name, e in (("as given", ev), ("turned by W", dataclasses.replace(ev, c2w=turned))):
        metrics, _ = evaluate_field(tr.field, e, tr.cfg.chunk)
        out[name] = round(metrics["psnr"], 3)
    angle = np.degrees(np.arccos(np.clip((np.trace(W.numpy()) - 1) / 2, -1, 1)))
    print(json.dumps({"run": run, "W_deg": round(float(angle), 4), **out}))


if __name__ == "__main__":
    if len(sys.argv) != 3:
        print("gauge_eval.py: error: usage: gauge_eval.py RUN SCENE_DIR", file=sys.stderr)
        sys.exit(2)
    if not (Path(sys.argv[1]) / "checkpoint.pt").is_file():
        print(f"gauge_eval.py: error: {sys.argv[1]}: no checkpoint.pt", file=sys.stderr)
        sys.exit(2)
    main(sys.argv[1], sys.argv[2])
