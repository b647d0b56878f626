"""`fastenerf calibrate`: fit the turntable model (supplement A.1) to camera poses, given
(POSES.npz) or found from chequerboard frames (--chequerboard SRC: a folder of images or an
AEDAT4 recording's APS frames)."""

from __future__ import annotations

import argparse
import dataclasses

HELP = "fit the turntable (tilt, radius, centre, period) to camera poses or chequerboard frames"

CONVENTIONS = """\
chequerboard conventions:
  --board COLSxROWS counts INNER corners (a board of 10x7 squares is 9x6); --square is the
  side of one square in world units (metres, say): the calibration and the scene use them.
  The board frame has its origin at the board's centre, x along a row to the right seen
  from the printed side, y up along a column, z out of the printed side; which way is up is
  read from the image (camera upright, board standing on the plate). Poses are OpenCV
  camera-to-world (x right, y down, z forward) in that frame. Pixels: centres at +0.5.

outputs beside CALIB.json (same stem): CALIB.poses.npz (c2w (M, 4, 4), t (M,) µs when the
frames have times, frame names, reprojection RMS), and, when the lens is calibrated here
(no --intrinsics), CALIB.intrinsics.json (fx fy cx cy k1 k2, OpenCV radial model), which
--intrinsics and `fastenerf import --intrinsics` read back.
"""


def add_arguments(p) -> None:
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.epilog = CONVENTIONS
    p.add_argument(
        "poses",
        nargs="?",
        help="npz with c2w (M, 4, 4) OpenCV camera-to-world, y-up world, and optionally t (M,) "
        "µs (or give --chequerboard instead)",
    )
    cb = p.add_argument_group("chequerboard (instead of POSES.npz)")
    cb.add_argument(
        "--chequerboard",
        metavar="SRC",
        help="folder of images (sorted by name; a timestamps.txt of 'FILE T_US' lines gives "
        "their times, as `import --frames` writes it) or an AEDAT4 recording (its APS frames)",
    )
    cb.add_argument("--board", metavar="COLSxROWS", help="inner corners, e.g. 9x6")
    cb.add_argument("--square", type=float, metavar="SIDE", help="square side, world units")
    cb.add_argument(
        "--intrinsics",
        metavar="FILE",
        help="lens (K.txt, EventNeRF 5x4, or the intrinsics JSON this command writes); "
        "default: calibrate it from the board frames (cv2.calibrateCamera)",
    )
    cb.add_argument("--every", type=int, default=1, metavar="N", help="use every N-th frame")
    cb.add_argument(
        "--lens-only",
        action="store_true",
        help="calibrate the lens only and write it to --out (intrinsics JSON): for a "
        "recording of the board held at varied tilts, when the turntable views alone do not "
        "pin the lens down",
    )
    cb.add_argument(
        "--no-times",
        action="store_true",
        help="ignore the frames' times (a plate turned by hand): fit no period",
    )
    p.add_argument("--out", required=True, metavar="CALIB.json", help="calibration JSON to write")
    p.add_argument(
        "--scene",
        help="also write the fitted turntable (and a lens calibrated here) into SCENE/scene.json",
    )
    p.add_argument(
        "--frame",
        choices=("turntable", "poses"),
        default="turntable",
        help="world of the model written into --scene: 'turntable' (origin at the "
        "centre, +y the axis: the density clip surrounds the plate; default) or "
        "'poses' (the poses' world, tilt and centre as fitted)",
    )
    p.add_argument(
        "--threshold-ratio",
        metavar="SCENE",
        help="instead: count the contrast-threshold ratio C+/C- over SCENE's closed loop (the "
        "camera back at its start pose) and write it to --out; what --estimate-threshold uses",
    )
    p.add_argument(
        "--method",
        choices=("lm", "adam"),
        default="lm",
        help="solver: closed form + least squares (default) or Adam (the paper's)",
    )
    p.add_argument(
        "--compare", action="store_true", help="also run the other solver and print / plot both"
    )
    p.add_argument(
        "--plot",
        metavar="PNG",
        help="picture of the fit: (a board frame,) cameras and circle, convergence",
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="replace --out / --plot even if they are not a calibration / an image",
    )


def run(args) -> int:
    from pathlib import Path

    from ..config import SceneConfig
    from ..data.calibrate import fit_turntable, load_calibration_poses, write_calibration

    if args.threshold_ratio:
        return _threshold_ratio(args)
    outputs = _check_arguments(args)
    cfg = SceneConfig.load(args.scene) if args.scene else None
    if args.lens_only:
        return _lens_only(args, cfg)
    found = None
    if args.chequerboard:
        found, c2w, t, extra = _chequerboard_poses(args, outputs)
        source = args.chequerboard
    else:
        c2w, t = load_calibration_poses(args.poses)
        extra = {"poses_file": str(args.poses)}
        source = args.poses
    fit = fit_turntable(c2w, t, method=args.method, source=str(source))
    others = {}
    if args.compare:
        other = "adam" if args.method == "lm" else "lm"
        others[other] = fit_turntable(c2w, t, method=other, source=str(source))
    _print_fit(fit, others)
    if others:
        extra["comparison"] = {
            f.method: {
                "iterations": f.iterations,
                "time_s": f.time_s,
                "final_loss": float(f.loss_history[-1]),
                **f.residuals,
            }
            for f in [fit, *others.values()]
        }
    out = write_calibration(args.out, fit, extra)
    print(f"wrote {out}")
    if args.plot:
        print(f"wrote {_plot(args, fit, c2w, others, found)}")
    if cfg is not None:
        _update_scene(args, cfg, fit, found)
        print(f"wrote {cfg.save(Path(args.scene))}")
    return 0


def _check_arguments(args) -> dict:
    """Validate the arguments and that every output can be written, before any work.
    Returns the output paths by role."""
    from pathlib import Path

    from ..errors import InputError

    if (args.poses is None) == (args.chequerboard is None):
        raise InputError("give either POSES.npz or --chequerboard SRC (with --board, --square)")
    out = Path(args.out)
    outputs = {"out": out}
    if args.chequerboard:
        if args.board is None or args.square is None:
            raise InputError("--chequerboard needs --board COLSxROWS and --square SIDE")
        if args.every < 1:
            raise InputError(f"--every {args.every}: must be a positive whole number")
        if args.lens_only and args.intrinsics:
            raise InputError("--lens-only calibrates the lens: leave out --intrinsics")
        stem = out.with_suffix("") if out.suffix == ".json" else out
        outputs["poses"] = stem.with_name(stem.name + ".poses.npz")
        if args.intrinsics is None:
            outputs["intrinsics"] = stem.with_name(stem.name + ".intrinsics.json")
    elif args.board or args.square or args.intrinsics or args.no_times or args.lens_only:
        raise InputError(
            "--board, --square, --intrinsics, --no-times and --lens-only go with --chequerboard"
        )
    if args.lens_only:
        outputs = {"out": out}
    if args.plot and not args.lens_only:
        outputs["plot"] = Path(args.plot)
    from ..config import SceneConfig
    from ..outputs import CALIBRATION, IMAGE, SCENE_UPDATE, claim_output

    for role, path in outputs.items():
        if role == "out":
            claim_output(path, CALIBRATION, force=args.force)
        elif role == "plot":
            claim_output(path, IMAGE, force=args.force, flag="--plot")
        else:
            _check_writable(path, role)
    if args.scene:  # the scene to update: valid and writable before the fit
        SceneConfig.load(args.scene)
        scene = Path(args.scene).resolve()
        folder = scene.parent if scene.is_file() else scene
        claim_output(folder, SCENE_UPDATE, force=None, flag="--scene")
    return outputs


def _threshold_ratio(args) -> int:
    """--threshold-ratio SCENE: the ratio counted over its loop, printed and written to --out."""
    from ..data.formats import load_any
    from ..data.loop_ratio import scene_loop_ratio
    from ..errors import InputError
    from ..io import write_json
    from ..outputs import THRESHOLD_RATIO, claim_output

    if args.poses or args.chequerboard or args.scene or args.plot:
        raise InputError(
            "--threshold-ratio SCENE takes no POSES.npz, --chequerboard, --scene or --plot"
        )
    claim_output(args.out, THRESHOLD_RATIO, force=args.force)
    scene = load_any(args.threshold_ratio)
    loop = scene_loop_ratio(scene)
    print(loop.summary(scene.config.neg_threshold))
    out = {**dataclasses.asdict(loop), "scene": str(args.threshold_ratio)}
    out["pos_at_scene_neg"] = loop.ratio * scene.config.neg_threshold
    print(f"wrote {write_json(args.out, out)}")
    return 0


def _check_writable(path, what: str) -> None:
    """One-line error unless a file can be created at `path` (its folder exists and takes
    a new file, or can be made)."""
    import os
    import tempfile
    from pathlib import Path

    from ..errors import InputError

    path = Path(path)
    if path.is_dir():
        raise InputError(f"{path}: is a folder ({what} names a file)")
    folder = path.parent
    while not folder.exists():
        folder = folder.parent
    if not folder.is_dir():
        raise InputError(f"{path}: cannot be written ({what}): {folder} is not a folder")
    try:
        fd, probe = tempfile.mkstemp(prefix=".write-probe.", dir=folder)
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        raise InputError(f"{path}: cannot be written ({what}): {e.strerror}") from None


def _chequerboard_poses(args, outputs: dict):
    """Board frames -> (BoardPoses, c2w, t or None, JSON extras); prints what it found and
    writes the poses (and a lens calibrated here) beside the calibration."""
    import numpy as np

    from ..data.chequerboard import Board, poses_from_chequerboard, progress_enabled
    from ..data.intrinsics import write_intrinsics
    from ..io import savez

    board = Board.parse(args.board, args.square)
    found = poses_from_chequerboard(
        args.chequerboard, board, args.intrinsics, args.every, progress_enabled()
    )
    det, intr = found.detections, found.intrinsics
    skipped = det.n_frames - det.n_found
    print(
        f"{args.chequerboard}: board {board} found in {det.n_found} of {det.n_frames} frames "
        f"({skipped} skipped: board not found"
        + (f"; {found.rejected} rejected: reprojection error" if found.rejected else "")
        + f"), {len(det.names)} poses, reprojection rms {np.sqrt(np.mean(found.rms_px**2)):.3f} px"
    )
    lens = (
        f"fx {intr.fx:.2f}, fy {intr.fy:.2f}, cx {intr.cx:.2f}, cy {intr.cy:.2f}, "
        f"k1 {intr.k1:.4f}, k2 {intr.k2:.4f}"
    )
    w, h = det.size
    if found.lens_rms_px is None:
        print(f"lens ({args.intrinsics}): {lens}")
    else:
        print(f"lens calibrated from the board ({w}x{h}, rms {found.lens_rms_px:.3f} px): {lens}")
        p = write_intrinsics(
            outputs["intrinsics"],
            intr,
            w,
            h,
            {"rms_px": found.lens_rms_px, "views": len(det.names), "source": args.chequerboard},
        )
        print(f"wrote {p}")
    t = det.t_us
    arrays = dict(
        c2w=found.c2w,
        frame=np.asarray(det.names),
        index=det.index,
        reprojection_rms_px=found.rms_px,
        K=np.array([[intr.fx, 0, intr.cx], [0, intr.fy, intr.cy], [0, 0, 1.0]]),
        k1k2=np.array([intr.k1, intr.k2]),
    )
    if t is not None:
        arrays["t"] = t
        if np.any(np.diff(t) <= 0):
            t = None  # repeated or unordered frame times: no period can be fitted
            print("warning: the frames' times do not increase; fitting without times")
    print(f"wrote {savez(outputs['poses'], **arrays)}")
    if t is None or args.no_times:
        t = None
        print("no frame times used: the period is not fitted (give --rpm at import)")
    extra = {
        "poses_file": str(outputs["poses"]),
        "chequerboard": {
            "source": str(args.chequerboard),
            "board": str(board),
            "square": board.square,
            "image_size": [w, h],
            "frames": det.n_frames,
            "found": det.n_found,
            "rejected": found.rejected,
            "used": len(det.names),
            "reprojection_rms_px": float(np.sqrt(np.mean(found.rms_px**2))),
            "intrinsics": dataclasses.asdict(intr),
            "intrinsics_from": args.intrinsics or str(outputs["intrinsics"]),
            "lens_rms_px": found.lens_rms_px,
        },
    }
    return found, found.c2w, t, extra


def _plot(args, fit, c2w, others: dict, found):
    """The calibration picture; with a chequerboard, the middle used frame with its corners
    and the board's axes (x red, y green, z blue), and the board in 3D."""
    import numpy as np

    from ..data.calibration_plot import FrameOverlay, plot_calibration

    if found is None:
        return plot_calibration(args.plot, fit, c2w, others)
    from ..data.chequerboard import Board, board_outline, project, read_frame

    board = Board.parse(args.board, args.square)
    det = found.detections
    i = len(det.names) // 2
    size, intr = det.size, found.intrinsics
    L = 2.5 * board.square
    axes = project(np.array([[0, 0, 0], [L, 0, 0], [0, L, 0], [0, 0, L]]), c2w[i], intr, size)
    overlay = FrameOverlay(
        read_frame(args.chequerboard, int(det.index[i])),
        det.corners[i],
        axes,
        f"{det.names[i]}: corners (+), board axes x y z",
        project(board_outline(board), c2w[i], intr, size),
    )
    return plot_calibration(args.plot, fit, c2w, others, overlay, board_outline(board))


def _lens_only(args, cfg) -> int:
    """--lens-only: board frames -> intrinsics JSON at --out (and into --scene)."""
    from pathlib import Path

    from ..data.chequerboard import Board, poses_from_chequerboard, progress_enabled
    from ..data.intrinsics import write_intrinsics

    board = Board.parse(args.board, args.square)
    found = poses_from_chequerboard(args.chequerboard, board, None, args.every, progress_enabled())
    det, intr = found.detections, found.intrinsics
    w, h = det.size
    print(
        f"{args.chequerboard}: board {board} found in {det.n_found} of {det.n_frames} frames, "
        f"{len(det.names)} used; lens rms {found.lens_rms_px:.3f} px: fx {intr.fx:.2f}, "
        f"fy {intr.fy:.2f}, cx {intr.cx:.2f}, cy {intr.cy:.2f}, k1 {intr.k1:.4f}, k2 {intr.k2:.4f}"
    )
    if cfg is not None and (w, h) != (cfg.width, cfg.height):
        from ..errors import InputError

        raise InputError(
            f"{args.scene}: the scene is {cfg.width}x{cfg.height}, the board frames {w}x{h}"
        )
    extra = {"rms_px": found.lens_rms_px, "views": len(det.names), "source": args.chequerboard}
    print(f"wrote {write_intrinsics(args.out, intr, w, h, extra)}")
    if cfg is not None:
        cfg.intrinsics = intr
        print(f"wrote {cfg.save(Path(args.scene))}")
    return 0


def _print_fit(fit, others: dict) -> None:
    for f in [fit, *others.values()]:
        r = f.residuals
        print(
            f"{f.method:>4}: {f.iterations} iterations, {f.time_s:.3f} s, "
            f"axis rms {r['axis_rms']:.3g}, angle rms {r['angle_rms_deg']:.4f}° "
            f"({r['angle_rms_rad']:.2e} rad), position rms {r['position_rms']:.3g}, "
            f"roll rms {r['roll_rms_deg']:.3f}°"
            + (f", time rms {r['time_rms_deg']:.3f}°" if "time_rms_deg" in r else "")
        )
    tr = fit.trajectory
    print(
        f"tilt α = {tr.tilt_deg:.4f}°, radius {tr.radius:.5g}, centre "
        f"[{', '.join(f'{c:.4g}' for c in tr.center)}], elevation {tr.elevation_deg:.3f}°, "
        + (
            f"period {tr.period_us} µs, {'clockwise' if tr.clockwise else 'counter-clockwise'}"
            if fit.period_fitted
            else "no times: period not fitted"
        )
        + f", poses cover {fit.extras['arc_deg']:.0f}°"
    )
    if fit.extras["arc_deg"] < 60:
        print(
            f"warning: the poses cover only {fit.extras['arc_deg']:.0f}° of the circle; "
            "radius and centre are poorly determined"
        )
    if fit.residuals.get("time_rms_deg", 0.0) > 1.0:
        print(
            f"warning: the poses' angles stray {fit.residuals['time_rms_deg']:.1f}° (rms) from a "
            "uniform rotation; if the plate was turned by hand, pass --no-times"
        )


def _update_scene(args, cfg, fit, found) -> None:
    """Write the fitted turntable (and a lens found here) into the scene's config."""
    import dataclasses
    import json
    from pathlib import Path

    new = fit.axis_aligned() if args.frame == "turntable" else fit.trajectory
    prov = Path(args.scene) / "import.json"
    if fit.period_fitted and prov.is_file():
        # Timed poses on DV's clock (the recording's frames): shift t0 onto the scene's
        # clock by whole periods, leaving the angle at every time unchanged.
        origin = int(json.loads(prov.read_text()).get("t_origin_us", 0))
        new = dataclasses.replace(new, t0_us=(new.t0_us - origin) % new.period_us)
    elif not fit.period_fitted and cfg.trajectory.kind == "turntable":
        # No times here: keep the scene's own rotation (period, phase, direction).
        old = cfg.trajectory
        new = dataclasses.replace(
            new,
            period_us=old.period_us,
            phase_deg=old.phase_deg,
            t0_us=old.t0_us,
            clockwise=old.clockwise,
        )
    cfg.trajectory = dataclasses.replace(new, kind="turntable", poses_file=None)
    if found is not None:
        w, h = found.detections.size
        if (w, h) == (cfg.width, cfg.height):
            cfg.intrinsics = found.intrinsics
        else:
            print(
                f"warning: the board frames are {w}x{h} but the scene {cfg.width}x{cfg.height}: "
                "its intrinsics are left as they were"
            )
    cfg.validate(str(args.scene))
