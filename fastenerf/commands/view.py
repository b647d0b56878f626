"""`fastenerf view`: the interactive viewer, live training, and headless snapshots."""

from __future__ import annotations

import argparse

HELP = "interactive viewer of a run (or of a model training live); headless snapshots"


def add_arguments(p: argparse.ArgumentParser) -> None:
    from ..backends import BACKEND_NAMES

    p.add_argument("run", nargs="?", metavar="RUN_DIR", help="a run folder (trained or training)")
    p.add_argument(
        "--train",
        metavar="SCENE_DIR",
        help="train on this scene in the background and view the model live",
    )
    p.add_argument(
        "--backend",
        choices=list(BACKEND_NAMES),
        default="ngp",
        help="field backend with --train (default ngp)",
    )
    p.add_argument(
        "--preset",
        choices=["fast", "eventnerf"],
        default="fast",
        help="training preset with --train (default fast)",
    )
    p.add_argument("--minutes", type=float, help="training budget with --train")
    p.add_argument(
        "--resume", action="store_true", help="with --train: continue the run already in --out"
    )
    p.add_argument("--out", help="run folder for --train (default runs/SCENE-BACKEND-view)")
    p.add_argument(
        "--snapshot",
        metavar="OUT.png",
        help="render one frame headless (EGL, no window) through the GL path and exit",
    )
    p.add_argument(
        "--pose",
        metavar="C2W.json",
        help="camera for --snapshot: a 4x4 c2w JSON or a camera path (first frame)",
    )
    p.add_argument(
        "--view-index",
        type=int,
        metavar="I",
        help="camera for --snapshot: the scene's I-th view (test views when the "
        "scene has them, else its pose grid)",
    )
    p.add_argument("--size", metavar="WxH", help="snapshot size (default the scene's sensor)")
    p.add_argument(
        "--mode",
        choices=["rgb", "depth", "opacity", "occupancy"],
        default="rgb",
        help="what to show: rgb (the field's colour, default), depth (distance along the ray, "
        "colour-mapped), opacity (how much of each ray the field stops), occupancy (the "
        "occupancy grid's cells that are marked occupied, chequered by cell; ngp)",
    )
    p.add_argument("--ev", type=float, default=0.0, help="exposure offset in stops")
    p.add_argument("--fov", type=float, help="vertical field of view in degrees")
    p.add_argument("--window", default="1280x800", metavar="WxH", help="window size")
    p.add_argument("--fps", type=float, default=30.0, help="target frame rate while moving")
    p.add_argument(
        "--force", action="store_true", help="replace --snapshot even if it is not an image"
    )
    # test hooks: close after N frames and save the window's image
    p.add_argument("--max-frames", type=int, help=argparse.SUPPRESS)
    p.add_argument("--window-shot", help=argparse.SUPPRESS)


def _size(s: str, what: str) -> tuple[int, int]:
    from fastenerf.errors import InputError

    try:
        w, h = (int(v) for v in s.lower().split("x"))
    except ValueError:
        raise InputError(f"{what} must be WIDTHxHEIGHT, e.g. 800x600 (got {s!r})") from None
    if w < 1 or h < 1 or w > 16384 or h > 16384:
        raise InputError(f"{what} {s!r} is out of range (1..16384 per side)")
    return w, h


def run(args) -> int:
    from fastenerf.errors import FastenerfError, InputError
    from fastenerf.viewer.frame import ViewSettings
    from fastenerf.viewer.source import ViewSource
    from fastenerf.viewer.tonemap import Exposure

    if (args.run is None) == (args.train is None):
        raise InputError("give either RUN_DIR or --train SCENE_DIR")
    if args.train and args.snapshot:
        raise InputError("--snapshot renders a run folder; it does not train")
    if args.pose and args.view_index is not None:
        raise InputError("give --pose or --view-index, not both")
    check_view_outputs(args)
    exposure = Exposure(ev=args.ev).validated("--ev")
    if args.train:
        src = ViewSource.from_training(
            args.train,
            args.backend,
            out_dir=args.out,
            preset=args.preset,
            resume=args.resume,
            minutes=args.minutes,
        )
    else:
        src = ViewSource.from_run(args.run)
    settings = ViewSettings(
        mode=args.mode, exposure=exposure, near=src.near, background=src.background
    )
    if args.snapshot:
        return _snapshot(args, src, settings)

    from fastenerf.viewer.app import Viewer

    v = Viewer(
        src,
        window_size=_size(args.window, "--window"),
        target_fps=args.fps,
        max_frames=args.max_frames,
        window_shot=args.window_shot,
        settings=settings,
    )
    if args.fov:
        v.fov_y = args.fov
    try:
        v.run()
    except RuntimeError as e:
        if "glfwInit" not in str(e):
            raise
        raise FastenerfError(_NO_WINDOW.format(f"no window could be opened ({e})")) from None
    if args.window_shot:
        print(f"fastenerf view: wrote {args.window_shot}")
    if src.out_dir is not None:
        print(f"fastenerf view: screenshots and paths go to {src.out_dir}")
    return 0


_NO_WINDOW = (
    "{}: the viewer needs a display; run it on a desktop, under `xvfb-run`, "
    "or render headless with --snapshot OUT.png"
)


def has_display() -> bool:
    """False where no window can be opened: Linux/BSD without DISPLAY or WAYLAND_DISPLAY."""
    import os
    import sys

    if sys.platform.startswith(("win", "darwin")):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def check_view_outputs(args) -> None:
    """Before any work: a display for the window, and writable outputs."""
    from fastenerf.errors import FastenerfError
    from fastenerf.outputs import IMAGE, RUN, claim_output

    if not args.snapshot and not has_display():
        raise FastenerfError(_NO_WINDOW.format("no display (DISPLAY is not set)"))
    for path, flag in ((args.snapshot, "--snapshot"), (args.window_shot, "--window-shot")):
        if path:
            claim_output(path, IMAGE, force=args.force, flag=flag)
    if args.train and args.out:
        claim_output(args.out, RUN, force=None)


def _snapshot(args, src, settings) -> int:
    import numpy as np

    from fastenerf.errors import InputError
    from fastenerf.io import write_image
    from fastenerf.viewer.blit import snapshot
    from fastenerf.viewer.camera import fov_y_of, intrinsics_for_fov, load_camera_path

    intr = src.intrinsics
    if args.pose:
        c2w, path_intr = load_camera_path(args.pose)[0]
        intr = path_intr or intr
    elif args.view_index is not None:
        if src.views is None or len(src.views) == 0:
            raise InputError(f"{args.run}: the run's scene has no views to index")
        if not 0 <= args.view_index < len(src.views):
            raise InputError(
                f"--view-index {args.view_index} is out of range (0..{len(src.views) - 1})"
            )
        c2w = src.views[args.view_index]
    else:
        c2w = src.default_camera().c2w
    size = _size(args.size, "--size") if args.size else None
    fov = args.fov or (fov_y_of(intr) if intr is not None else 50.0)
    if intr is None or args.fov or (size is not None and size != (intr.width, intr.height)):
        # a free camera: undistorted, centred, the requested size and field of view
        w, h = size or ((intr.width, intr.height) if intr is not None else (800, 600))
        intr = intrinsics_for_fov(w, h, fov)
    img = snapshot(src.field, np.asarray(c2w), intr, settings)
    out = write_image(args.snapshot, img)
    print(f"fastenerf view: wrote {out} ({intr.width}x{intr.height})")
    return 0
