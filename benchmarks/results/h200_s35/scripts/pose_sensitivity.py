"""Diagnostic: how much PSNR a trained field loses when each test camera is turned about its
own centre by a fixed angle (a random axis per view, seed 0), to tell how precise a pose must
be on a scene before the pose-error study's gap can close.
Usage: python pose_sensitivity.py RUN SCENE_DIR [DEG ...] (angles in degrees; default
0 0.005 0.01 0.02 0.04 0.08 0.16). One JSON line per angle on stdout."""

import dataclasses
import json
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

from benchmarks.curve import load_scene_dir
from fastenerf.config import TrainConfig
from fastenerf.errors import InputError
from fastenerf.evaluate import evaluate_field, make_eval_set
from fastenerf.run import load_checkpoint
from fastenerf.se3 import so3_exp
from fastenerf.train import Trainer
from fastenerf.train_state import restore


def turned(c2w: np.ndarray, deg: float, rng: np.random.Generator) -> np.ndarray:
    """c2w: (V, 4, 4); each rotation turned by `deg` degrees about a random axis."""
    axes = rng.normal(size=(len(c2w), 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    R = so3_exp(torch.from_numpy(axes * np.radians(deg))).numpy()
    out = c2w.copy()
    out[:, :3, :3] = R @ c2w[:, :3, :3]
    return out


def main(run: str, scene_dir: str, degs: list[float]) -> None:
    conf = json.loads((Path(run) / "config.json").read_text())["train"]
    scene = load_scene_dir(scene_dir)
    with tempfile.TemporaryDirectory() as tmp:  # the trainer's own folder, not the run's
        tr = Trainer(scene, TrainConfig.from_dict(conf), Path(tmp))
        restore(tr, load_checkpoint(Path(run) / "checkpoint.pt"))
    ev = make_eval_set(scene, 10, 1.0)
    for deg in degs:
        e = dataclasses.replace(ev, c2w=turned(ev.c2w, deg, np.random.default_rng(0)))
        metrics, _ = evaluate_field(tr.field, e, tr.cfg.chunk)
        print(json.dumps({"run": run, "deg": deg, "psnr": round(metrics["psnr"], 3)}), flush=True)


def fail(msg: str) -> None:
    print(f"pose_sensitivity.py: error: {msg}", file=sys.stderr)
    sys.exit(2)


if __name__ == "__main__":
    if len(sys.argv) < 3:
        fail("usage: pose_sensitivity.py RUN SCENE_DIR [DEG ...]")
    if not all((Path(sys.argv[1]) / f).is_file() for f in ("config.json", "checkpoint.pt")):
        fail(f"{sys.argv[1]}: no config.json and checkpoint.pt (a finished run)")
    if not Path(sys.argv[2]).is_dir():
        fail(f"SCENE_DIR {sys.argv[2]} is not a folder")
    try:
        degs = [float(x) for x in sys.argv[3:]] or [0, 0.005, 0.01, 0.02, 0.04, 0.08, 0.16]
    except ValueError:
        fail(f"angles {sys.argv[3:]} are not all numbers (degrees)")
    if not all(np.isfinite(d) and d >= 0 for d in degs):
        fail(f"angles {degs} must be finite and >= 0 (degrees)")
    try:
        main(sys.argv[1], sys.argv[2], degs)
    except InputError as e:  # a scene folder that is not one, a config that does not load
        fail(str(e))
