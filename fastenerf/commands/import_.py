"""`fastenerf import RECORDING.aedat4 --out SCENE`: a DV recording -> native scene folder.

The scene records the capture (DESIGN §6, §9 real-data values: thresholds 0.1, polarity offset
0, background sRGB 159, loop for a turntable, the paper's density cylinder); the trainer's preset
decides how to train on it. Provenance (source file, its absolute time origin, crop) goes to
SCENE/import.json, which `fastenerf calibrate --scene` reads to put timed calibrations on the
scene's clock.
"""

from __future__ import annotations

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
    import math
    from pathlib import Path

    from ..outputs import SCENE, claim_output

    claim_output(args.out, SCENE, force=args.force)

    from ..config import CylinderConfig, IntrinsicsConfig, SceneConfig, TrajectoryConfig
    from ..data.formats.aedat import load_aedat4
    from ..data.formats.eventnerf import REAL_BACKGROUND
    from ..data.formats.native import save_scene
    from ..data.intrinsics import read_intrinsics
    from ..errors import InputError
    from ..io import atomic_dir, write_json

    crop = None if args.crop is None else (round(args.crop[0]), round(args.crop[1]))
    rec = load_aedat4(args.recording, t_crop_us=crop, keep_frames=args.frames)
    if args.frames and not rec.frames:
        raise InputError(f"{args.recording}: --frames, but the recording has no APS frames")
    ev = rec.events
    print(
        f"{args.recording}: {len(ev):,} events, {ev.width}x{ev.height}, "
        f"{ev.duration_us * 1e-6:.3f} s, frames {list(rec.frame_formats) or 'none'}"
    )

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
    intr = read_intrinsics(args.intrinsics, ev.width, ev.height) if args.intrinsics else None
    if intr is None:
        intr = IntrinsicsConfig(
            fx=float(ev.width), fy=float(ev.width), cx=ev.width / 2, cy=ev.height / 2
        )
        print(
            "warning: no --intrinsics: wrote a nominal pinhole (fx = fy = width); calibrate "
            "the lens and import again before training"
        )

    t_end = int(ev.t[-1]) + 1
    poses = None
    loop = False
    cylinder = None
    if args.turntable:
        from ..data.calibrate import load_calibration

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
        loop = True
        revs = t_end / traj.period_us
        k = max(1, round(revs))
        if abs(t_end - k * traj.period_us) <= 0.01 * traj.period_us:
            t_end = k * traj.period_us  # whole revolutions: the loop closes exactly
        else:
            print(
                f"warning: the events span {revs:.3f} revolutions; for a seamless loop crop "
                f"to whole ones, e.g. --crop T0 T0+{traj.period_us * k}"
            )
        if not args.no_cylinder:
            cylinder = CylinderConfig(*args.cylinder) if args.cylinder else CylinderConfig()
    elif args.poses:
        from ..data.calibrate import load_calibration_poses

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
        poses = (t, c2w)
        traj = TrajectoryConfig(kind="timed", poses_file="poses.npz")
        if args.cylinder and not args.no_cylinder:
            cylinder = CylinderConfig(*args.cylinder)
    else:
        traj = TrajectoryConfig(kind="turntable")
        if args.rpm:
            traj.period_us = round(60e6 / args.rpm)
        loop = True
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
    if not all(math.isfinite(v) for v in (traj.radius, traj.period_us)):
        raise InputError(f"{args.turntable}: turntable parameters are not finite")

    cfg = SceneConfig(
        name=args.name or Path(args.recording).stem,
        width=ev.width,
        height=ev.height,
        intrinsics=intr,
        trajectory=traj,
        bayer=None if bayer == "mono" else "rggb",
        pos_threshold=0.1,
        neg_threshold=0.1,
        polarity_offset=0.0,
        t_start_us=0,
        t_end_us=t_end,
        loop=loop,
        cylinder=cylinder,
        background=list(REAL_BACKGROUND),
        kind="real",
    ).validate(f"{args.out}/scene.json")
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
    return 0


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
