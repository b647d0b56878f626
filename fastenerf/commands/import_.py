"""`fastenerf import RECORDING.aedat4 --out SCENE`: a DV recording -> native scene folder.

The scene records the capture (DESIGN §6, §9 real-data values: thresholds 0.1, polarity offset
0, background sRGB 159, loop for a turntable, the paper's density cylinder); the trainer's preset
decides how to train on it. Provenance (source file, its absolute time origin, crop) goes to
SCENE/import.json, which `fastenerf calibrate --scene` reads to put timed calibrations on the
scene's clock.
"""

from __future__ import annotations

from typing import NamedTuple

HELP = "import an AEDAT4 recording (DV, DAVIS 346/346C) as a native scene folder"

IMPORT_FILE = "import.json"
FRAMES_DIR = "frames"
TIMESTAMPS_FILE = "timestamps.txt"  # as fastenerf.data.chequerboard reads it


def add_arguments(p) -> None:
    p.add_argument("recording", help="AEDAT4 file written by DV")
    p.add_argument(
        "--out", required=True, help="scene folder to write (an existing scene is replaced whole)"
    )
    p.add_argument(
        "--force", action="store_true", help="replace --out even if it is not a scene folder"
    )
    traj = p.add_mutually_exclusive_group()
    traj.add_argument(
        "--turntable", metavar="CALIB.json", help="turntable model from `fastenerf calibrate`"
    )
    traj.add_argument(
        "--poses",
        metavar="POSES.npz",
        help="timed poses: t (M,) µs and c2w (M, 4, 4) OpenCV camera-to-world",
    )
    p.add_argument(
        "--frame",
        choices=("turntable", "poses"),
        default="turntable",
        help="with --turntable: which world the model is written in (see calibrate)",
    )
    p.add_argument(
        "--rpm",
        type=float,
        help="turntable speed in revolutions per minute (45 in the paper); needed "
        "when the calibration has no times",
    )
    p.add_argument(
        "--direction",
        choices=("cw", "ccw"),
        help="turntable direction seen from above (overrides the calibration)",
    )
    p.add_argument(
        "--poses-relative",
        action="store_true",
        help="--poses times count from the first kept event (default: DV's clock, "
        "µs since the epoch, as the recording's frames carry)",
    )
    p.add_argument(
        "--crop",
        nargs=2,
        type=float,
        metavar=("T0", "T1"),
        help="keep events with T0 <= t < T1, µs after the recording's first event",
    )
    p.add_argument(
        "--bayer",
        choices=("rggb", "mono"),
        help="colour filter (default: rggb if the recording's frames are colour, else mono)",
    )
    p.add_argument(
        "--intrinsics",
        metavar="FILE",
        help="3x3 K.txt (OpenCV), the EventNeRF 4x4 / 5x4 file (5th row: k1 k2 0 0), or the "
        "intrinsics JSON `fastenerf calibrate --chequerboard` writes",
    )
    p.add_argument(
        "--cylinder",
        nargs=3,
        type=float,
        metavar=("R", "YMIN", "YMAX"),
        help="density clip for a turntable scene (default 0.25 -0.35 0.15, the "
        "paper's; world units of the calibration)",
    )
    p.add_argument("--no-cylinder", action="store_true", help="no density clip")
    p.add_argument("--name", help="scene name (default: the recording's file name)")
    p.add_argument(
        "--frames",
        action="store_true",
        help="also write the APS frames: SCENE/frames/NNNNNN.png and SCENE/frames/"
        f"{TIMESTAMPS_FILE} (lines 'FILE T_US', DV's clock, middle of each exposure), which "
        "`fastenerf calibrate --chequerboard SCENE/frames` reads",
    )


def run(args) -> int:
    """Load the recording, build the scene's config and write the scene folder."""
    from ..outputs import SCENE, claim_output

    claim_output(args.out, SCENE, force=args.force)

    crop = None if args.crop is None else (round(args.crop[0]), round(args.crop[1]))
    rec = _load_recording(args, crop)
    bayer = _colour_filter(args, rec)
    intr = _intrinsics(args, rec.events)
    motion = _motion(args, rec, t_end=int(rec.events.t[-1]) + 1)
    cfg = _scene_config(args, rec.events, intr, bayer, motion)
    _write_scene(args, rec, crop, cfg, motion.poses)
    return 0


class _Motion(NamedTuple):
    """How the camera moves over the scene's stream: its trajectory, whether the stream loops,
    the density cylinder, timed poses ((M,) µs, (M, 4, 4) c2w) for a timed trajectory, and the
    stream's end (µs, exclusive)."""

    trajectory: object  # TrajectoryConfig
    loop: bool
    cylinder: object  # CylinderConfig | None
    poses: tuple | None
    t_end: int


def _load_recording(args, crop):
    """The AEDAT4 recording (events cropped to `crop` µs, frames if asked), with a summary line."""
    from ..data.formats.aedat import load_aedat4
    from ..errors import InputError

    rec = load_aedat4(args.recording, t_crop_us=crop, keep_frames=args.frames)
    if args.frames and not rec.frames:
        raise InputError(f"{args.recording}: --frames, but the recording has no APS frames")
    ev = rec.events
    print(
        f"{args.recording}: {len(ev):,} events, {ev.width}x{ev.height}, "
        f"{ev.duration_us * 1e-6:.3f} s, frames {list(rec.frame_formats) or 'none'}"
    )
    return rec


def _colour_filter(args, rec) -> str:
    """The colour filter, "rggb" or "mono": --bayer, else guessed from the recording's frames
    (and said so)."""
    bayer = args.bayer or ("rggb" if rec.color_frames else "mono")
    if args.bayer is None:
        print(
            f"colour filter: {bayer} ("
            + (
                "colour frames"
                if rec.color_frames
                else "gray or no frames; pass --bayer rggb for a DAVIS 346C"
            )
            + ")"
        )
    return bayer


def _intrinsics(args, ev):
    """--intrinsics read for the sensor, else a nominal pinhole (fx = fy = width) with a warning."""
    from ..config import IntrinsicsConfig
    from ..data.intrinsics import read_intrinsics

    intr = read_intrinsics(args.intrinsics, ev.width, ev.height) if args.intrinsics else None
    if intr is None:
        intr = IntrinsicsConfig(
            fx=float(ev.width), fy=float(ev.width), cx=ev.width / 2, cy=ev.height / 2
        )
        print(
            "warning: no --intrinsics: wrote a nominal pinhole (fx = fy = width); calibrate "
            "the lens and import again before training"
        )
    return intr


def _motion(args, rec, t_end: int) -> _Motion:
    """The camera's motion from --turntable, --poses or neither (a placeholder turntable)."""
    import math

    from ..errors import InputError

    if args.turntable:
        motion = _calibrated_turntable(args, rec, t_end)
    elif args.poses:
        motion = _timed_poses(args, rec, t_end)
    else:
        motion = _placeholder_turntable(args, t_end)
    traj = motion.trajectory
    if not all(math.isfinite(v) for v in (traj.radius, traj.period_us)):
        raise InputError(f"{args.turntable}: turntable parameters are not finite")
    return motion


def _calibrated_turntable(args, rec, t_end: int) -> _Motion:
    """The --turntable calibration on the scene's clock; the stream's end snapped to whole
    revolutions when it is within 1% of them, so the loop closes exactly."""
    from ..config import CylinderConfig
    from ..data.calibrate import load_calibration
    from ..errors import InputError

    traj, calib = load_calibration(args.turntable, args.frame)
    if args.rpm:
        traj.period_us, traj.t0_us = round(60e6 / args.rpm), 0  # phase: any start will do
    elif calib.get("period_fitted", False):
        # Timed calibration on DV's clock: move its reference time onto the scene's clock
        # (a whole number of periods away, so the angle at every time is unchanged).
        traj.t0_us = (traj.t0_us - rec.t_origin_us) % traj.period_us
    else:
        raise InputError(
            f"{args.turntable}: has no fitted period (no times); pass --rpm "
            "(45 for the paper's turntable)"
        )
    if args.direction:
        traj.clockwise = args.direction == "cw"
    revs = t_end / traj.period_us
    k = max(1, round(revs))
    if abs(t_end - k * traj.period_us) <= 0.01 * traj.period_us:
        t_end = k * traj.period_us  # whole revolutions: the loop closes exactly
    else:
        print(
            f"warning: the events span {revs:.3f} revolutions; for a seamless loop crop "
            f"to whole ones, e.g. --crop T0 T0+{traj.period_us * k}"
        )
    cylinder = None
    if not args.no_cylinder:
        cylinder = CylinderConfig(*args.cylinder) if args.cylinder else CylinderConfig()
    return _Motion(traj, True, cylinder, None, t_end)


def _timed_poses(args, rec, t_end: int) -> _Motion:
    """The --poses file on the scene's clock (a timed trajectory, no loop)."""
    from ..config import CylinderConfig, TrajectoryConfig
    from ..data.calibrate import load_calibration_poses
    from ..errors import InputError

    c2w, t = load_calibration_poses(args.poses)
    if t is None:
        raise InputError(f"{args.poses}: timed poses need an array 't' (µs)")
    if not args.poses_relative:
        t = t - rec.t_origin_us
    if t[0] > 0 or t[-1] < t_end - 1:
        print(
            f"warning: poses span [{t[0]}, {t[-1]}] µs but the events [0, {t_end - 1}]; "
            "outside it the pose is held constant"
        )
    traj = TrajectoryConfig(kind="timed", poses_file="poses.npz")
    cylinder = None
    if args.cylinder and not args.no_cylinder:
        cylinder = CylinderConfig(*args.cylinder)
    return _Motion(traj, False, cylinder, (t, c2w), t_end)


def _placeholder_turntable(args, t_end: int) -> _Motion:
    """A default turntable (at --rpm if given) to be replaced by `fastenerf calibrate`."""
    from ..config import CylinderConfig, TrajectoryConfig

    traj = TrajectoryConfig(kind="turntable")
    if args.rpm:
        traj.period_us = round(60e6 / args.rpm)
    cylinder = (
        None
        if args.no_cylinder
        else (CylinderConfig(*args.cylinder) if args.cylinder else CylinderConfig())
    )
    print(
        "warning: no --turntable or --poses: wrote a placeholder turntable; run "
        "`fastenerf calibrate --chequerboard CALIB.aedat4 --board COLSxROWS --square SIDE "
        f"--out CALIB.json --scene {args.out}` (or with POSES.npz) next"
    )
    return _Motion(traj, True, cylinder, None, t_end)


def _scene_config(args, ev, intr, bayer: str, motion: _Motion):
    """scene.json for a real capture (DESIGN §9's real-data thresholds and background)."""
    from pathlib import Path

    from ..config import SceneConfig
    from ..data.formats.eventnerf import REAL_BACKGROUND

    return SceneConfig(
        name=args.name or Path(args.recording).stem,
        width=ev.width,
        height=ev.height,
        intrinsics=intr,
        trajectory=motion.trajectory,
        bayer=None if bayer == "mono" else "rggb",
        pos_threshold=0.1,
        neg_threshold=0.1,
        polarity_offset=0.0,
        t_start_us=0,
        t_end_us=motion.t_end,
        loop=motion.loop,
        cylinder=motion.cylinder,
        background=list(REAL_BACKGROUND),
        kind="real",
    ).validate(f"{args.out}/scene.json")


def _write_scene(args, rec, crop, cfg, poses) -> None:
    """The scene folder at --out as a whole (import.json, frames if asked, the scene), then a
    summary of the events."""
    from pathlib import Path

    from ..data.formats.native import save_scene
    from ..io import atomic_dir, write_json

    ev = rec.events
    out = Path(args.out)
    with atomic_dir(out) as tmp:  # the scene whole: nothing of an older one survives
        write_json(
            tmp / IMPORT_FILE,
            {
                "source": str(Path(args.recording).resolve()),
                "t_origin_us": rec.t_origin_us,
                "crop_us": list(crop) if crop else None,
                "frame_formats": list(rec.frame_formats),
                "events": len(ev),
                "trajectory_from": args.turntable or args.poses or None,
                "intrinsics_from": args.intrinsics,
                "frames": len(rec.frames) if args.frames else None,
            },
        )
        if args.frames:
            _write_frames(tmp / FRAMES_DIR, rec, args.recording)
        save_scene(tmp, cfg, ev, poses=poses)
    if args.frames:
        print(f"wrote {out / FRAMES_DIR}")
    n_pos = int((ev.p > 0).sum())
    print(
        f"{n_pos:,} positive / {len(ev) - n_pos:,} negative events, time origin "
        f"{rec.t_origin_us} µs (DV clock)"
    )
    print(f"wrote {out}")


def _write_frames(folder, rec, source: str):
    """The recording's APS frames as PNGs (8- or 16-bit gray, or RGB(A)) with a timestamps
    file, replacing `folder` as a whole (atomically)."""
    import imageio.v3 as iio

    from ..io import atomic_dir

    lines = [
        f"# APS frames of {source}: FILE T_US (DV clock, µs since the epoch, middle of the "
        "exposure)",
        f"# the scene's clock is T_US - {rec.t_origin_us} (import.json t_origin_us)",
    ]
    with atomic_dir(folder) as tmp:
        for i, fr in enumerate(rec.frames):
            name = f"{i:06d}.png"
            iio.imwrite(tmp / name, fr.rgb())
            lines.append(f"{name} {fr.t_us}")
        (tmp / TIMESTAMPS_FILE).write_text("\n".join(lines) + "\n")
    print(f"{len(rec.frames)} APS frames ({', '.join(rec.frame_formats)})")
    return folder
