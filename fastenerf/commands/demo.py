"""`fastenerf demo`: synthesise the built-in scene, train, evaluate, render an orbit.

Sizes are chosen by device so the whole demo fits its budget: on a CUDA GPU the full
346x260 sensor and a 1000-frame loop with about a minute of training; on a CPU (e.g. a
2-core CI machine) a 173x130 sensor, 300 frames and a few minutes of training, rendered at
reduced size, the whole demo in well under 15 minutes. Both train the ngp backend (on a CPU
with the CPU preset, fastenerf.cpu_preset); vanilla where the ngp kernels cannot load.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

HELP = "end-to-end demo: make the built-in scene, train on its events, evaluate, render"

# Per-device demo settings (see the module docstring).
GPU = {
    "size": (346, 260),
    "frames": 1000,
    "minutes": 1.0,
    "eval_views": None,
    "eval_scale": 1.0,
    "orbit": 60,
    "orbit_scale": 1.0,
}
CPU = {
    "size": (173, 130),
    "frames": 300,
    "minutes": 5.0,
    "eval_views": 10,
    "eval_scale": 1.0,
    "orbit": 24,
    "orbit_scale": 0.75,
}
# Per-backend training settings on a CPU. ngp: the CPU preset (fastenerf.cpu_preset, applied
# by TrainConfig.resolved) is the demo's. vanilla (--backend vanilla): a small network and a
# high learning rate (the reference-sized MLP gets a few hundred steps in the budget).
CPU_TRAIN = {
    "vanilla": {
        "lr": 1e-2,
        "lr_final": 1e-3,
        "backend_options": {
            "depth": 3,
            "width": 64,
            "pos_freqs": 6,
            "dir_freqs": 2,
            "n_coarse": 16,
            "n_fine": 16,
        },
    },
    "ngp": {},
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    from ..backends import BACKEND_NAMES

    p.add_argument("--out", metavar="DIR", required=True, help="demo folder to write")
    p.add_argument(
        "--backend",
        choices=list(BACKEND_NAMES),
        default=None,
        help="field backend (default: ngp; vanilla where the ngp kernels cannot load)",
    )
    p.add_argument(
        "--minutes",
        type=float,
        default=None,
        help="training budget (default 1 on a GPU, 5 on a CPU)",
    )
    p.add_argument(
        "--scene",
        default=None,
        metavar="NAME",
        help="built-in scene to synthesise (default blocks; `fastenerf synth --list` names "
        "them) or a mesh file",
    )
    p.add_argument(
        "--force", action="store_true", help="replace --out even if it is not a demo folder"
    )
    p.add_argument("--device", default="auto", help="auto (default), cpu or cuda")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")


def default_backend() -> str:
    try:
        from ..fields import backend_module

        backend_module("ngp")
        return "ngp"
    except Exception:  # noqa: BLE001 - ngp kernels missing or broken: the plain backend works
        return "vanilla"


def run(args: argparse.Namespace) -> int:
    import shutil

    from ..config import train_preset
    from ..data.formats.native import load_scene
    from ..data.synth import DEFAULT_SCENE, make_scene
    from ..errors import InputError
    from ..evaluate import evaluate_run, format_metrics
    from ..outputs import DEMO, claim_output
    from ..run import resolve_device
    from ..train import Trainer
    from .render import render_path

    claim_output(args.out, DEMO, force=args.force)
    t_start = time.perf_counter()
    device = resolve_device(args.device)
    gpu = device.type == "cuda"
    s = GPU if gpu else CPU
    backend = args.backend or default_backend()
    minutes = s["minutes"] if args.minutes is None else args.minutes
    if minutes <= 0:
        raise InputError("--minutes must be positive")
    out = Path(args.out)
    scene_dir, run_dir, orbit_dir = out / "scene", out / "run", out / "orbit"
    progress = not args.no_progress
    name = args.scene or DEFAULT_SCENE

    w, h = s["size"]
    print(f"[1/4] synthesising '{name}' at {w}x{h}, {s['frames']} frames -> {scene_dir}")
    make_scene(name, scene_dir, width=w, height=h, frames=s["frames"], progress=progress)
    scene = load_scene(scene_dir)
    print(f"      {len(scene.events):,} events")

    print(f"[2/4] training {backend} for {minutes:g} min on {device} -> {run_dir}")
    if run_dir.exists():
        shutil.rmtree(run_dir)  # a demo always starts fresh
    extra = {} if gpu else dict(CPU_TRAIN[backend])
    cfg = train_preset(
        "fast",
        backend,
        minutes=minutes,
        device=str(device),
        eval_every_s=10.0 if gpu else 20.0,
        **extra,
    )
    trainer = Trainer(scene, cfg, run_dir)
    summary = trainer.run(progress=progress)
    if summary["failure"]:
        raise InputError(summary["failure"])
    if summary["interrupted"]:
        print(f"interrupted; the run is in {run_dir} (resume with fastenerf train --resume)")
        return 130
    del trainer

    print(f"[3/4] evaluating on the test views -> {run_dir / 'metrics.json'}")
    metrics = evaluate_run(
        run_dir, max_views=s["eval_views"], scale=s["eval_scale"], progress=progress
    )

    print(f"[4/4] rendering a {s['orbit']}-frame orbit -> {orbit_dir}")
    res = render_path(
        run_dir, orbit_dir, orbit=s["orbit"], scale=s["orbit_scale"], progress=progress
    )

    print()
    print(
        f"demo finished in {(time.perf_counter() - t_start) / 60:.1f} min "
        f"({summary['steps']} steps, {summary['train_seconds']:.0f} s training, {backend})"
    )
    print(f"  {format_metrics(metrics)}")
    print(f"  scene:       {scene_dir}")
    print(f"  run:         {run_dir}  (metrics.json, metrics.jsonl, checkpoint.pt)")
    print(f"  comparison:  {metrics['sheet']}  (prediction | ground truth | error)")
    print(f"  test views:  {metrics['images']}/")
    print(f"  orbit:       {res['video']}  (+ {res['rgb']}/, {res['depth']}/)")
    return 0
