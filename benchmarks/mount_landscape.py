"""The event loss along the line from a mount-error run's shared row to the truth, field frozen.

    python -m benchmarks.mount_landscape RUN --scene DIR [--field-from RUN2] [--batches 40]

RUN: a finished `bench study mount-error ... --set refine_poses=true refine_shared=true` run
(runs/mount-2deg). Its field is loaded frozen; the shared row is set to row + t · (truth - row)
for t in --ts (t = 0: the row it learnt; 1: the exact inverse of its mount turn, -angle · axis
in the camera frame) and the mean loss over the same --batches batches is printed. With
--field-from the field is another run's (e.g. the 0° level's: a field trained at the exact
poses) and the row starts at zero. Nothing is trained and RUN is not written (a copy is).
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import tempfile
from pathlib import Path

import torch

from benchmarks.cli import benchmark_main
from fastenerf.config import TrainConfig
from fastenerf.data.formats import load_scene_folder
from fastenerf.errors import InputError
from fastenerf.run import load_checkpoint
from fastenerf.train import Trainer


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("run", help="a mount-error study run folder (runs/mount-2deg)")
    p.add_argument("--scene", required=True, help="the scene folder it was trained on")
    p.add_argument("--field-from", help="use this run's field instead (row starts at zero)")
    p.add_argument("--batches", type=int, default=40, help="batches averaged (default 40)")
    p.add_argument("--ts", default="-0.5,-0.25,0,0.25,0.5,0.75,1,1.25", help="points on the line")


def _points(text: str) -> list[float]:
    """--ts as finite floats (one-line InputError otherwise)."""
    try:
        ts = [float(s) for s in text.split(",")]
    except ValueError:
        raise InputError(f"--ts must be comma-separated numbers, got {text!r}") from None
    if not ts or not all(math.isfinite(t) for t in ts):
        raise InputError(f"--ts must be finite numbers, got {text!r}")
    return ts


def _checked(args: argparse.Namespace) -> tuple[Path, dict, dict, list[float]]:
    """The run folder, its config.json, its mount report and the points, or a one-line
    InputError saying what is wrong and where."""
    src = Path(args.run)
    if args.batches < 1:
        raise InputError(f"--batches must be at least 1, got {args.batches}")
    ts = _points(args.ts)
    for need in (src / "config.json", src / "checkpoint.pt"):
        if not need.is_file():
            raise InputError(f"{src}: no {need.name} (a finished mount-error study run?)")
    if args.field_from and not (Path(args.field_from) / "checkpoint.pt").is_file():
        raise InputError(f"{args.field_from}: no checkpoint.pt (--field-from wants a run)")
    try:
        cfg_json = json.loads((src / "config.json").read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise InputError(f"{src / 'config.json'}: not readable JSON ({e})") from None
    mount = (cfg_json.get("perturbation") or {}).get("mount")
    if not mount or not (cfg_json.get("train") or {}).get("refine_shared"):
        raise InputError(f"{src} is not a refine_shared run of a mount-error study")
    return src, cfg_json, mount, ts


def run(args: argparse.Namespace) -> int:
    src, cfg_json, mount, ts = _checked(args)
    with tempfile.TemporaryDirectory() as tmp:
        shutil.copytree(src, tmp, dirs_exist_ok=True)
        cfg = TrainConfig.from_dict(cfg_json["train"])
        tr = Trainer(load_scene_folder(args.scene), cfg, tmp, resume=True)
        row = tr.selfcal.poses.delta.detach().clone()
        if args.field_from:
            tr.field.load_state_dict(
                load_checkpoint(Path(args.field_from) / "checkpoint.pt")["field"]
            )
            row.zero_()
        truth = torch.zeros_like(row)
        axis = torch.tensor(mount["axis"], dtype=row.dtype)
        truth[0, :3] = -math.radians(mount["angle_deg"]) * axis
        torch.manual_seed(123)
        batches = [tr.sampler.sample() for _ in range(args.batches)]
        tr.field.eval()
        print(
            f"row {[round(math.degrees(v), 3) for v in row[0, :3].tolist()]} deg, "
            f"truth {[round(math.degrees(v), 3) for v in truth[0, :3].tolist()]} deg"
        )
        for t in ts:
            with torch.no_grad():
                tr.selfcal.poses.delta.copy_(row + t * (truth - row))
                loss = sum(float(tr._forward(b)[1].detach()) for b in batches) / len(batches)
            print(f"t={t:+.2f}  loss={loss:.4f}", flush=True)
    return 0


def main(argv: list[str] | None = None) -> int:
    return benchmark_main("mount_landscape", __doc__, add_arguments, run, argv)


if __name__ == "__main__":
    raise SystemExit(main())
