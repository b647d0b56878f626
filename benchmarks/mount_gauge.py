"""How much of a camera-mount turn a rigid motion of the scene imitates, on a scene's own rig.

    python -m benchmarks.mount_gauge --scene DIR [--deg 2] [--views 60] [--points 400] \
        [--perturb-seed S ...] [--out OUT]

A mount error turns every camera by the same rotation M in its own frame, c2w_i · M. What the
events cannot tell apart from the truth is the part a field can explain by itself: the same
scene moved rigidly, G · X. For each turn (M about the camera's x, y and z axes, and about the
axes `bench study mount-error --seed S` draws), this projects random points of the scene's box
into every view (the rig at `--views` times over the recording) through the exact poses, and
through the turned poses with the scene moved by the rigid motion G that best matches those
images (least squares over G's six parameters, the points and the views). It reports both
image errors (rms, pixels) and the share of the turn's error G removes: near 100 % means the
turn is nearly a gauge of that rig, which no training on its events can learn back and which
exact test poses then show as a shifted scene.

Outputs in OUT: mount_gauge.json and mount_gauge.md.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from benchmarks.cli import benchmark_main
from fastenerf.data.formats import load_scene_folder
from fastenerf.errors import InputError
from fastenerf.io import atomic_path, write_json
from fastenerf.perturb import mount_axis

CAMERA_AXES = {
    "x (pitch)": (1.0, 0.0, 0.0),
    "y (yaw)": (0.0, 1.0, 0.0),
    "z (roll)": (0.0, 0.0, 1.0),
}


def project_all(c2w: np.ndarray, points: np.ndarray, intrinsics) -> np.ndarray:
    """Pixels (V, N, 2) of points (N, 3) world units in the V views c2w (V, 4, 4) (OpenCV
    frame, z forward); a point behind a camera is an input error (the box must be in view)."""
    w2c = np.linalg.inv(c2w)
    cam = np.einsum("vij,nj->vni", w2c[:, :3, :3], points) + w2c[:, None, :3, 3]
    if np.any(cam[..., 2] <= 0):
        raise InputError("a point of the scene's box is behind a camera")
    return np.stack([intrinsics.project(c) for c in cam])


def rigid(p: np.ndarray, points: np.ndarray) -> np.ndarray:
    """points (N, 3) moved by the rigid motion p = [rotation vector (rad), shift (world)]."""
    return points @ Rotation.from_rotvec(p[:3]).as_matrix().T + p[3:]


def imitation(c2w, points, intrinsics, axis, deg: float) -> dict:
    """The image error (rms px) of a `deg` turn about the camera-frame `axis` (3,), before and
    after the rigid motion of the scene that best imitates it, and that motion."""
    M = np.eye(4)
    M[:3, :3] = Rotation.from_rotvec(np.deg2rad(deg) * np.asarray(axis, np.float64)).as_matrix()
    exact = project_all(c2w, points, intrinsics)
    turned = c2w @ M

    def residual(p):
        return (project_all(turned, rigid(p, points), intrinsics) - exact).ravel()

    before = float(np.sqrt(np.mean(residual(np.zeros(6)) ** 2)))
    fit = least_squares(residual, np.zeros(6), x_scale="jac")
    after = float(np.sqrt(np.mean(fit.fun**2)))
    return {
        "axis": [float(a) for a in axis],
        "rms_px": before,
        "rms_px_after_rigid": after,
        "imitated": 1.0 - after / before if before > 0 else 0.0,
        "rigid_rotation_deg": float(np.rad2deg(np.linalg.norm(fit.x[:3]))),
        "rigid_shift": float(np.linalg.norm(fit.x[3:])),
    }


def run(args: argparse.Namespace) -> int:
    if not (0 < args.deg <= 30):
        raise InputError(f"--deg must be in (0, 30], got {args.deg}")
    for flag, n in (("--views", args.views), ("--points", args.points)):
        if n < 1:
            raise InputError(f"{flag} must be at least 1, got {n}")
    if any(s < 0 for s in args.perturb_seed):
        raise InputError(f"--perturb-seed must be >= 0, got {args.perturb_seed}")
    scene = load_scene_folder(args.scene)
    cfg, rig = scene.config, scene.rig()
    t = np.linspace(cfg.t_start_us, cfg.t_end_us, args.views, endpoint=False).astype(np.int64)
    c2w = np.asarray(rig.pose(t), np.float64)
    lo, hi = np.asarray(cfg.aabb, np.float64).reshape(2, 3)
    points = lo + (hi - lo) * np.random.default_rng(0).random((args.points, 3))
    axes = dict(CAMERA_AXES)
    for s in args.perturb_seed:
        axes[f"seed {s}"] = mount_axis(s)
    rows = {name: imitation(c2w, points, rig.intrinsics, a, args.deg) for name, a in axes.items()}
    res = {"benchmark": "mount_gauge", "scene": cfg.name, "deg": args.deg}
    res.update(views=args.views, points=args.points, turns=rows)
    md = [
        f"### A {args.deg:g}° mount turn on {cfg.name}'s rig ({args.views} views, "
        f"{args.points} points of its box)",
        "",
        "| turn about | camera-frame axis | image error (px rms) | after the best rigid motion "
        "of the scene | imitated |",
        "|---|---|---:|---:|---:|",
    ]
    for name, r in rows.items():
        ax = ", ".join(f"{a:.2f}" for a in r["axis"])
        md.append(
            f"| {name} | ({ax}) | {r['rms_px']:.2f} | {r['rms_px_after_rigid']:.2f} | "
            f"{100 * r['imitated']:.0f} % |"
        )
    text = "\n".join(md) + "\n"
    print(text)
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        write_json(out / "mount_gauge.json", res)
        with atomic_path(out / "mount_gauge.md") as tmp:
            tmp.write_text(text)
    return 0


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scene", required=True, help="scene folder")
    p.add_argument("--deg", type=float, default=2.0, help="the turn, degrees (0, 30]")
    p.add_argument("--views", type=int, default=60, help="views over the recording")
    p.add_argument("--points", type=int, default=400, help="random points of the scene's box")
    p.add_argument("--perturb-seed", type=int, nargs="*", default=[], help="study seeds' axes")
    p.add_argument("--out", default=None, help="folder for mount_gauge.json / .md")


def main(argv: list[str] | None = None) -> int:
    return benchmark_main("mount_gauge", __doc__, add_arguments, run, argv, out_folder=True)


if __name__ == "__main__":
    sys.exit(main())
