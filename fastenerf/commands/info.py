"""`fastenerf info PATH`: validate a scene folder or events file and print its statistics."""

from __future__ import annotations

import argparse
import json

HELP = "validate a scene folder (native or EventNeRF) or an events file and print statistics"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "path",
        help="scene folder (scene.json or EventNeRF layout) or events file "
        "(.npz, .h5, .txt, .aedat4)",
    )
    p.add_argument(
        "--sensor",
        metavar="WxH",
        default=None,
        help="sensor size for an events file that does not store it, e.g. 346x260",
    )
    p.add_argument("--json", action="store_true", help="print one JSON object instead")


def run(args: argparse.Namespace) -> int:
    from ..errors import InputError

    sensor = None
    if args.sensor:
        try:
            w, h = (int(v) for v in args.sensor.lower().split("x"))
            sensor = (w, h)
        except ValueError:
            raise InputError(f"--sensor must look like 346x260, got {args.sensor!r}") from None
    try:
        info = describe(args.path, sensor)
    except OSError as e:  # unreadable files and folders are the user's input, too
        raise InputError(f"{args.path}: {e}") from None
    if args.json:
        print(json.dumps(info, indent=2))
    else:
        print(format_info(info))
    return 0


def describe(path, sensor: tuple[int, int] | None = None) -> dict:
    """Everything `info` reports, as plain JSON-able values (validates on the way)."""
    from ..data.events import EventStream
    from ..data.formats import open_any

    obj, what = open_any(path, sensor)
    events = obj if isinstance(obj, EventStream) else obj.events
    out = {"path": str(path), "format": what}
    st = events.stats()
    n = st["events"]
    out["events"] = {
        "count": n,
        "t_first_us": st["t_first_us"],
        "t_last_us": st["t_last_us"],
        "duration_s": st["duration_s"],
        "rate_ev_per_s": st["rate_ev_per_s"],
        "positive": int((events.p > 0).sum()),
        "negative": int((events.p < 0).sum()),
        "positive_fraction": st["positive_fraction"],
        "busiest_pixel": st["busiest_pixel"],
        "active_pixels": st["active_pixels"],
        "pixels": events.width * events.height,
    }
    out["sensor"] = {"width": events.width, "height": events.height}
    if isinstance(obj, EventStream):
        return out
    scene, cfg = obj, obj.config
    rig = scene.rig()  # validates the trajectory (poses file, rotations, timestamps)
    tr = cfg.trajectory
    traj = {"kind": tr.kind}
    if tr.kind == "timed":
        t_pose = rig.trajectory.t
        traj.update(poses=len(t_pose), t_first_us=int(t_pose[0]), t_last_us=int(t_pose[-1]))
    else:
        traj.update(
            radius=tr.radius,
            period_us=tr.period_us,
            tilt_deg=tr.tilt_deg,
            elevation_deg=tr.elevation_deg,
            center=list(tr.center),
        )
    i = cfg.intrinsics
    inside = (events.t > cfg.t_start_us) & (events.t <= cfg.t_end_us)
    out.update(
        {
            "name": cfg.name,
            "kind": cfg.kind,
            "bayer": cfg.bayer,
            "intrinsics": {
                "fx": i.fx,
                "fy": i.fy,
                "cx": i.cx,
                "cy": i.cy,
                "k1": i.k1,
                "k2": i.k2,
                "distortion_model": i.distortion_model,
            },
            "trajectory": traj,
            "stream": {
                "t_start_us": cfg.t_start_us,
                "t_end_us": cfg.t_end_us,
                "loop": cfg.loop,
                "n_views": cfg.n_views,
                "events_outside": int(n - inside.sum()),
            },
            "thresholds": {
                "pos": cfg.pos_threshold,
                "neg": cfg.neg_threshold,
                "polarity_offset": cfg.polarity_offset,
            },
            "bounds": {
                "aabb": list(cfg.aabb),
                "near": cfg.near,
                "cylinder": None if cfg.cylinder is None else vars(cfg.cylinder),
            },
            "background": cfg.background,
            "test_views": {
                "count": 0 if scene.test_c2w is None else len(scene.test_c2w),
                "images": len(scene.test_rgb_paths or []),
            },
        }
    )
    return out


def _si(v: float) -> str:
    for div, unit in ((1e9, "G"), (1e6, "M"), (1e3, "k")):
        if abs(v) >= div:
            return f"{v / div:.2f} {unit}"
    return f"{v:.2f} "


def format_info(d: dict) -> str:
    """Aligned `key  value` lines for people."""
    e = d["events"]
    rows = [("path", d["path"]), ("format", d["format"])]
    if "name" in d:
        rows.append(("scene", f"{d['name']} ({d['kind']})"))
    s = d["sensor"]
    bayer = f", bayer {d['bayer']}" if d.get("bayer") else (", mono" if "bayer" in d else "")
    rows.append(("sensor", f"{s['width']}x{s['height']}{bayer}"))
    rows.append(("events", f"{e['count']:,}"))
    if e["count"]:
        rows.append(
            (
                "time",
                f"{e['t_first_us'] * 1e-6:.6f} s .. {e['t_last_us'] * 1e-6:.6f} s "
                f"(duration {e['duration_s']:.6f} s)",
            )
        )
        rate = e["rate_ev_per_s"]
        rows.append(("rate", f"{_si(rate)}ev/s" if rate is not None else "n/a (one instant)"))
        rows.append(
            (
                "polarity",
                f"{e['positive']:,} positive / {e['negative']:,} negative "
                f"({100 * e['positive_fraction']:.1f}% positive)",
            )
        )
        b = e["busiest_pixel"]
        rows.append(("busiest pixel", f"x={b['x']} y={b['y']} with {b['events']:,} events"))
        rows.append(
            (
                "active pixels",
                f"{e['active_pixels']:,} of {e['pixels']:,} "
                f"({100 * e['active_pixels'] / e['pixels']:.1f}%)",
            )
        )
    if "trajectory" in d:
        i = d["intrinsics"]
        dist = (
            f", k1={i['k1']:g} k2={i['k2']:g} ({i['distortion_model']})"
            if i["k1"] or i["k2"]
            else ""
        )
        rows.append(
            ("intrinsics", f"fx={i['fx']:g} fy={i['fy']:g} cx={i['cx']:g} cy={i['cy']:g}{dist}")
        )
        t = d["trajectory"]
        if t["kind"] == "timed":
            rows.append(
                (
                    "poses",
                    f"{t['poses']:,} timed, {t['t_first_us'] * 1e-6:.6f} s .. "
                    f"{t['t_last_us'] * 1e-6:.6f} s",
                )
            )
        else:
            rows.append(
                (
                    "poses",
                    f"turntable radius {t['radius']:g}, period "
                    f"{t['period_us'] * 1e-6:g} s, tilt {t['tilt_deg']:g} deg, "
                    f"elevation {t['elevation_deg']:g} deg",
                )
            )
        st = d["stream"]
        rows.append(
            (
                "stream",
                f"{st['t_start_us'] * 1e-6:.6f} s .. {st['t_end_us'] * 1e-6:.6f} s, "
                f"{st['n_views']:,} views, {'loop' if st['loop'] else 'no loop'}"
                + (f", {st['events_outside']:,} events outside" if st["events_outside"] else ""),
            )
        )
        th = d["thresholds"]
        rows.append(
            (
                "thresholds",
                f"+{th['pos']:g} / -{th['neg']:g}, polarity offset {th['polarity_offset']:g}",
            )
        )
        bo = d["bounds"]
        cyl = bo["cylinder"]
        rows.append(
            (
                "bounds",
                f"aabb {bo['aabb']}, near {bo['near']:g}"
                + (
                    f", cylinder r={cyl['radius']:g} y {cyl['y_min']:g}..{cyl['y_max']:g}"
                    if cyl
                    else ""
                ),
            )
        )
        rows.append(
            (
                "background",
                "none"
                if d["background"] is None
                else " ".join(f"{c:.3f}" for c in d["background"]),
            )
        )
        tv = d["test_views"]
        rows.append(
            (
                "test views",
                f"{tv['count']} ({tv['images']} with ground-truth images)"
                if tv["count"]
                else "none",
            )
        )
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"{k:<{width}}  {v}" for k, v in rows)
