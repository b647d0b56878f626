"""`fastenerf calibrate POSES.npz --out CALIB.json`: fit the turntable model (supplement A.1)."""

from __future__ import annotations

HELP = "fit the turntable (axis tilt, radius, centre, period) to observed camera poses"


def add_arguments(p) -> None:
    p.add_argument(
        "poses",
        help="npz with c2w (M, 4, 4) OpenCV camera-to-world, y-up world, and optionally t (M,) µs",
    )
    p.add_argument("--out", required=True, help="calibration JSON to write")
    p.add_argument("--scene", help="also write the fitted turntable into SCENE/scene.json")
    p.add_argument(
        "--frame",
        choices=("turntable", "poses"),
        default="turntable",
        help="world of the model written into --scene: 'turntable' (origin at the "
        "centre, +y the axis: the density clip surrounds the plate; default) or "
        "'poses' (the poses' world, tilt and centre as fitted)",
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
    p.add_argument("--plot", help="PNG of the fit: cameras, circle, convergence")
    p.add_argument(
        "--force",
        action="store_true",
        help="replace --out / --plot even if they are not a calibration / an image",
    )


def run(args) -> int:
    import dataclasses
    import json
    from pathlib import Path

    from ..config import SceneConfig
    from ..data.calibrate import (
        fit_turntable,
        load_calibration_poses,
        plot_calibration,
        write_calibration,
    )
    from ..outputs import CALIBRATION, IMAGE, SCENE_UPDATE, claim_output

    claim_output(args.out, CALIBRATION, force=args.force)
    if args.plot:
        claim_output(args.plot, IMAGE, force=args.force, flag="--plot")
    if args.scene:  # the scene to update: valid and writable before the fit
        SceneConfig.load(args.scene)
        scene = Path(args.scene).resolve()
        claim_output(
            scene.parent if scene.is_file() else scene, SCENE_UPDATE, force=None, flag="--scene"
        )
    c2w, t = load_calibration_poses(args.poses)
    fit = fit_turntable(c2w, t, method=args.method, source=args.poses)
    others = {}
    if args.compare:
        other = "adam" if args.method == "lm" else "lm"
        others[other] = fit_turntable(c2w, t, method=other, source=args.poses)
    for f in [fit, *others.values()]:
        r = f.residuals
        print(
            f"{f.method:>4}: {f.iterations} iterations, {f.time_s:.3f} s, "
            f"axis rms {r['axis_rms']:.3g}, angle rms {r['angle_rms_deg']:.4f}° "
            f"({r['angle_rms_rad']:.2e} rad), position rms {r['position_rms']:.3g}, "
            f"roll rms {r['roll_rms_deg']:.3f}°"
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
    extra = {"poses_file": str(args.poses)}
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
        print(f"wrote {plot_calibration(args.plot, fit, c2w, others)}")
    if args.scene:
        cfg = SceneConfig.load(args.scene)
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
        cfg.validate(str(args.scene))
        print(f"wrote {cfg.save(args.scene)}")
    return 0
