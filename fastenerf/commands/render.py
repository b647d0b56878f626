"""`fastenerf render`: frames, depth maps and a video of a trained run along a camera path."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from ..tonemap import Exposure

HELP = "render a trained run along an orbit or a saved camera path: PNGs and a video"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("run_dir", metavar="RUN_DIR", help="a training run folder")
    path = p.add_mutually_exclusive_group()
    path.add_argument(
        "--orbit",
        type=int,
        metavar="N",
        default=None,
        help="N frames along one orbit of the scene (default 60)",
    )
    path.add_argument(
        "--path",
        metavar="FILE.json",
        help="camera path: a JSON list of 4x4 camera-to-world matrices (OpenCV)",
    )
    p.add_argument("--out", metavar="DIR", required=True, help="output folder")
    p.add_argument(
        "--scale",
        type=float,
        default=1.0,
        help="resolution as a fraction of the sensor size (default 1)",
    )
    p.add_argument("--fps", type=float, default=24.0, help="video frame rate (default 24)")
    e = p.add_argument_group(
        "exposure",
        "events fix colours only up to exposure: the viewer's controls, applied to the PNGs "
        "and the video (log intensity L = log(c^2.2 + 1e-4) -> gain·L + ev·ln 2, then gamma)",
    )
    e.add_argument("--ev", type=float, default=0.0, help="exposure offset in stops (default 0)")
    e.add_argument(
        "--gain", type=float, default=1.0, help="log-space gain, i.e. contrast (default 1)"
    )
    e.add_argument("--gamma", type=float, default=1.0, help="display gamma (default 1)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument(
        "--force", action="store_true", help="write into --out even if it is not a render folder"
    )


def orbit_poses(scene_cfg, n: int, root=None, poses=None) -> np.ndarray:
    """n camera-to-world (n, 4, 4) around the scene.

    A looped capture's own trajectory sampled uniformly over one loop (that is an orbit of
    the scene); otherwise a level circle around the box centre at the cameras' mean distance
    and height.
    """
    from ..data.rig import Rig, look_at

    rig = Rig.from_scene(scene_cfg, root, poses)  # poses: in memory (EventNeRF folders)
    t0, t1 = scene_cfg.t_start_us, scene_cfg.t_end_us
    if scene_cfg.loop:
        return rig.pose(t0 + (np.arange(n) * (t1 - t0)) / n)
    eyes = rig.pose(np.linspace(t0, t1, 64))[:, :3, 3]
    a = np.asarray(scene_cfg.aabb, np.float64)
    c = (a[:3] + a[3:]) / 2
    rel = eyes - c
    r = float(np.mean(np.hypot(rel[:, 0], rel[:, 2])))
    h = float(np.mean(rel[:, 1]))
    th = 2 * np.pi * np.arange(n) / n
    eye = np.stack([c[0] + r * np.sin(th), np.full(n, c[1] + h), c[2] + r * np.cos(th)], -1)
    return look_at(eye, np.broadcast_to(c, eye.shape), np.array([0.0, 1.0, 0.0]))


def read_path(path: str | Path) -> np.ndarray:
    """(N, 4, 4) camera-to-world from a JSON list of 4x4 matrices, validated."""
    from ..errors import InputError

    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(f"{path}: camera path file not found") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise InputError(f"{path}: not valid JSON ({e})") from None
    if isinstance(data, dict):
        data = data.get("c2w", data.get("poses", data.get("frames")))
    try:
        c2w = np.asarray(data, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{path}: must be a list of 4x4 matrices") from None
    if c2w.ndim != 3 or c2w.shape[1:] != (4, 4) or len(c2w) == 0:
        raise InputError(f"{path}: must be a non-empty list of 4x4 matrices, got shape {c2w.shape}")
    if not np.all(np.isfinite(c2w)):
        raise InputError(f"{path}: camera path contains NaN or inf")
    return c2w


def depth_image(depth: np.ndarray, opacity: np.ndarray) -> np.ndarray:
    """Depth (H, W) as a turbo-coloured image (H, W, 3); empty pixels black."""
    from matplotlib import colormaps

    solid = opacity > 0.5
    d = depth / np.maximum(opacity, 1e-6)
    if solid.any():
        lo, hi = np.percentile(d[solid], [2, 98])
    else:
        lo, hi = 0.0, 1.0
    x = np.clip((d - lo) / max(hi - lo, 1e-6), 0, 1)
    img = colormaps["turbo"](1.0 - x)[..., :3]
    return (img * np.clip(opacity, 0, 1)[..., None]).astype(np.float32)


def write_video(path_stem: Path, frames: list[np.ndarray], fps: float) -> Path:
    """MP4 when an ffmpeg backend for imageio is installed, else an animated GIF."""
    import imageio.v3 as iio

    from ..io import atomic_path

    u8 = np.stack([(np.clip(f, 0, 1) * 255 + 0.5).astype(np.uint8) for f in frames])
    mp4 = path_stem.with_suffix(".mp4")
    try:
        with atomic_path(mp4) as tmp:
            iio.imwrite(tmp, u8, fps=fps, codec="libx264", macro_block_size=1)
        return mp4
    except Exception:  # noqa: BLE001 - no ffmpeg/pyav plugin: fall back to GIF
        pass
    gif = path_stem.with_suffix(".gif")
    with atomic_path(gif) as tmp:
        iio.imwrite(tmp, u8, duration=1000.0 / fps, loop=0)
    return gif


def render_path(
    run_dir,
    out: str | Path,
    c2w: np.ndarray | None = None,
    orbit: int = 60,
    scale: float = 1.0,
    fps: float = 24.0,
    progress: bool = True,
    exposure: Exposure | None = None,
) -> dict:
    """Render a run along c2w (N, 4, 4), or an `orbit`-frame orbit when c2w is None.

    Writes out/rgb/NNNN.png, out/depth/NNNN.png and out/video.mp4 (or .gif); the colour
    frames through `exposure` (`fastenerf.tonemap`, as the viewer shows them; None: as
    rendered).
    """
    from ..data.formats.native import Scene
    from ..data.rig import Intrinsics
    from ..io import write_image
    from ..progress import progress_bar
    from ..render import render_image
    from ..run import load_run, scene_background
    from ..tonemap import Exposure, apply_exposure

    field, scene, cfg = load_run(run_dir)
    sc, root = (scene.config, scene.root) if isinstance(scene, Scene) else (scene, None)
    if c2w is None:
        c2w = orbit_poses(sc, orbit, root, getattr(scene, "poses", None))
    intr = Intrinsics.from_config(sc.intrinsics, sc.width, sc.height)
    if scale != 1.0:
        intr = intr.scaled(scale)
    out = Path(out)
    bg = scene_background(sc)
    frames = []
    for i, pose in enumerate(progress_bar(c2w, desc="render", unit="frame", enabled=progress)):
        img = render_image(field, pose, intr, near=sc.near, background=bg, chunk=cfg.chunk)
        rgb = apply_exposure(img["rgb"], exposure or Exposure()).cpu().numpy()
        write_image(out / "rgb" / f"{i:04d}.png", rgb)
        write_image(
            out / "depth" / f"{i:04d}.png",
            depth_image(img["depth"].cpu().numpy(), img["opacity"].cpu().numpy()),
        )
        frames.append(rgb)
    video = write_video(out / "video", frames, fps)
    return {
        "frames": len(frames),
        "rgb": str(out / "rgb"),
        "depth": str(out / "depth"),
        "video": str(video),
        "size": [intr.width, intr.height],
    }


def run(args: argparse.Namespace) -> int:
    from ..errors import InputError
    from ..tonemap import Exposure

    if args.scale <= 0:
        raise InputError("--scale must be positive")
    n = 60 if args.orbit is None else args.orbit
    if n < 1:
        raise InputError("--orbit needs at least 1 frame")
    from ..outputs import RENDER, claim_output
    from .eval import check_render_memory

    claim_output(args.out, RENDER, force=args.force)
    exposure = Exposure(gain=args.gain, ev=args.ev, gamma=args.gamma).validated("render")
    c2w = read_path(args.path) if args.path else None
    check_render_memory(args.run_dir, args.scale, n if c2w is None else len(c2w), "render")
    res = render_path(
        args.run_dir,
        args.out,
        c2w,
        orbit=n,
        scale=args.scale,
        fps=args.fps,
        progress=not args.no_progress,
        exposure=exposure,
    )
    print(f"rendered {res['frames']} frames at {res['size'][0]}x{res['size'][1]}")
    print(f"wrote {res['rgb']}/, {res['depth']}/ and {res['video']}")
    return 0
