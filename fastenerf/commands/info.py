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
    out["events"] = _event_stats(events)
    out["sensor"] = {"width": events.width, "height": events.height}
    if isinstance(obj, EventStream):
        return out
    out.update(_scene_info(obj))
    return out


def _event_stats(events) -> dict:
    """Counts, times (µs, s), rate (events/s), polarity split and pixel activity of a stream."""
    st = events.stats()
    return {
        "count": st["events"],
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


def _trajectory_info(cfg, rig) -> dict:
    """A timed trajectory's pose count and time span (µs), or a turntable's parameters."""
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
    return traj


def _scene_info(scene) -> dict:
    """What a scene folder adds to its events: camera, trajectory, stream, thresholds, bounds,
    background and test views."""
    cfg, events = scene.config, scene.events
    rig = scene.rig()  # validates the trajectory (poses file, rotations, timestamps)
    traj = _trajectory_info(cfg, rig)
    i = cfg.intrinsics
    inside = (events.t > cfg.t_start_us) & (events.t <= cfg.t_end_us)
    return {
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
            "events_outside": int(len(events) - inside.sum()),
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


def _si(v: float) -> str:
    for div, unit in ((1e9, "G"), (1e6, "M"), (1e3, "k")):
        if abs(v) >= div:
            return f"{v / div:.2f} {unit}"
    return f"{v:.2f} "


def format_info(d: dict) -> str:
    """Aligned `key  value` lines for people."""
    rows = [("path", d["path"]), ("format", d["format"])]
    if "name" in d:
        rows.append(("scene", f"{d['name']} ({d['kind']})"))
    s = d["sensor"]
    bayer = f", bayer {d['bayer']}" if d.get("bayer") else (", mono" if "bayer" in d else "")
    rows.append(("sensor", f"{s['width']}x{s['height']}{bayer}"))
    rows += _event_rows(d["events"])
    if "trajectory" in d:
        rows += _scene_rows(d)
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"{k:<{width}}  {v}" for k, v in rows)


def _event_rows(e: dict) -> list[tuple[str, str]]:
    """The event count, and for a non-empty stream its times, rate, polarity and pixels."""
    rows = [("events", f"{e['count']:,}")]
    if not e["count"]:
        return rows
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
    return rows


def _scene_rows(d: dict) -> list[tuple[str, str]]:
    """The rows only a scene folder has: camera, poses, stream, thresholds, bounds, background
    and test views."""
    i = d["intrinsics"]
    dist = (
        f", k1={i['k1']:g} k2={i['k2']:g} ({i['distortion_model']})" if i["k1"] or i["k2"] else ""
    )
    st, th, tv = d["stream"], d["thresholds"], d["test_views"]
    return [
        ("intrinsics", f"fx={i['fx']:g} fy={i['fy']:g} cx={i['cx']:g} cy={i['cy']:g}{dist}"),
        ("poses", _poses_text(d["trajectory"])),
        (
            "stream",
            f"{st['t_start_us'] * 1e-6:.6f} s .. {st['t_end_us'] * 1e-6:.6f} s, "
            f"{st['n_views']:,} views, {'loop' if st['loop'] else 'no loop'}"
            + (f", {st['events_outside']:,} events outside" if st["events_outside"] else ""),
        ),
        (
            "thresholds",
            f"+{th['pos']:g} / -{th['neg']:g}, polarity offset {th['polarity_offset']:g}",
        ),
        ("bounds", _bounds_text(d["bounds"])),
        (
            "background",
            "none" if d["background"] is None else " ".join(f"{c:.3f}" for c in d["background"]),
        ),
        (
            "test views",
            f"{tv['count']} ({tv['images']} with ground-truth images)" if tv["count"] else "none",
        ),
    ]


def _poses_text(t: dict) -> str:
    """A timed trajectory's pose count and span, or a turntable's parameters, in one line."""
    if t["kind"] == "timed":
        return (
            f"{t['poses']:,} timed, {t['t_first_us'] * 1e-6:.6f} s .. {t['t_last_us'] * 1e-6:.6f} s"
        )
    return (
        f"turntable radius {t['radius']:g}, period "
        f"{t['period_us'] * 1e-6:g} s, tilt {t['tilt_deg']:g} deg, "
        f"elevation {t['elevation_deg']:g} deg"
    )


def _bounds_text(bo: dict) -> str:
    """The box, near plane and density cylinder (if any) in one line."""
    cyl = bo["cylinder"]
    return f"aabb {bo['aabb']}, near {bo['near']:g}" + (
        f", cylinder r={cyl['radius']:g} y {cyl['y_min']:g}..{cyl['y_max']:g}" if cyl else ""
    )
