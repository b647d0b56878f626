"""`fastenerf perturb noise|poses`: a perturbed copy of an events file or a scene folder.

`noise EVENTS --fraction F --out NOISY.npz` adds round(F·N) uniform noise events (supplement J);
`poses SCENE --deg X --out NEW_SCENE` turns every training pose by X° about a random axis
(supplement I) and writes a native scene folder with the turned timed poses, the same events
and the test views unchanged. Both print what was measured on the result (`fastenerf.perturb`).
The studies apply the same perturbations in memory through `PerturbConfig`; these copies are
for looking at, for other tools, or for training by hand.
"""

from __future__ import annotations

import argparse

HELP = "write a perturbed copy for robustness studies: noise events, or camera-pose error"

PERTURB_FILE = "perturb.json"  # in a perturbed scene folder: what was done, measured


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="what", metavar="WHAT", required=True)
    n = sub.add_parser(
        "noise",
        help="add uniformly random events to an events file",
        description="Add uniformly random events (x, y over the sensor, t over the stream's "
        "time range, polarity ±1 with equal odds), their number a fraction of the clean "
        "count, merged in time order; written as a native .npz events file.",
    )
    n.add_argument(
        "events",
        metavar="EVENTS",
        help="events file (.npz, .h5, .txt, .aedat4) or a scene folder (its training stream)",
    )
    n.add_argument(
        "--fraction",
        type=float,
        required=True,
        help="noise events per clean event, in [0, 10] (0.05 = 5 %%)",
    )
    n.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    n.add_argument(
        "--sensor",
        metavar="WxH",
        help="sensor size for an events file that does not store it (else max x, y + 1)",
    )
    n.add_argument("--out", required=True, help="noisy events file to write (.npz)")
    n.add_argument("--json", action="store_true", help="print the report as one JSON object")

    q = sub.add_parser(
        "poses",
        help="turn every training pose by a fixed angle about a random axis",
        description="Turn every training pose's rotation by a fixed angle about its own "
        "random axis (camera centres stay; a turntable is sampled on the training pose grid "
        "first) and write a native scene folder with these timed poses, the same events and "
        "the test views unchanged.",
    )
    q.add_argument("scene", metavar="SCENE_DIR", help="scene folder (native or EventNeRF)")
    q.add_argument("--deg", type=float, required=True, help="angle in degrees, in [0, 180)")
    q.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    q.add_argument("--out", required=True, help="scene folder to write (replaced atomically)")
    q.add_argument("--json", action="store_true", help="print the report as one JSON object")


def run(args: argparse.Namespace) -> int:
    if args.what == "noise":
        return _run_noise(args)
    return _run_poses(args)


def _run_noise(args) -> int:
    import json
    import math
    from pathlib import Path

    from ..config import PerturbConfig
    from ..data.events import EventStream
    from ..data.formats import open_any
    from ..data.formats.native import write_events
    from ..errors import InputError
    from ..perturb import add_noise_events

    if not (math.isfinite(args.fraction) and 0.0 <= args.fraction <= 10.0):
        raise InputError(f"--fraction must be in [0, 10] (0.05 = 5 %), got {args.fraction}")
    _check_seed(args.seed)
    cfg = PerturbConfig(noise_fraction=args.fraction, seed=args.seed).validate("arguments")
    src, out = Path(args.events), Path(args.out)
    if out.suffix.lower() != ".npz":
        raise InputError(f"{out}: --out must be a .npz file (the native events format)")
    _refuse_same(src, out)
    if out.exists():
        _check_replaceable_events(out)
    sensor = _parse_sensor(args.sensor) if args.sensor else None
    try:
        obj, what = open_any(src, sensor)
    except OSError as e:
        raise InputError(f"{src}: {e}") from None
    events = obj if isinstance(obj, EventStream) else obj.events
    noisy, report = add_noise_events(events, cfg.noise_fraction, cfg.seed)
    write_events(out, noisy)
    report = {"source": str(src), "format": what, **report, "out": str(out)}
    if args.json:
        print(json.dumps(report, indent=2))
        return 0
    print(
        f"{src}: {what}, {report['clean_events']:,} events, sensor {report['sensor']}, "
        f"t {report['t_range_us'][0]}..{report['t_range_us'][1]} µs"
    )
    pos = report["noise_positive_fraction"]
    print(
        f"added {report['added_events']:,} uniform noise events (seed {cfg.seed}): measured "
        f"fraction {report['measured_fraction']:.6f} of the clean count (asked "
        f"{cfg.noise_fraction:g})" + (f", {pos:.1%} positive" if pos is not None else "")
    )
    print(f"wrote {out} ({len(noisy):,} events, native npz)")
    return 0


def _run_poses(args) -> int:
    import json
    import math
    from pathlib import Path

    from ..config import PerturbConfig
    from ..data.formats import load_scene_folder
    from ..errors import InputError
    from ..perturb import perturb_poses, pose_grid_times, timed_samples

    if not (math.isfinite(args.deg) and 0.0 <= args.deg < 180.0):
        raise InputError(f"--deg must be in [0, 180) degrees, got {args.deg}")
    _check_seed(args.seed)
    cfg = PerturbConfig(pose_error_deg=args.deg, seed=args.seed).validate("arguments")
    src, out = Path(args.scene), Path(args.out)
    _refuse_same(src, out)
    if out.exists():
        _check_replaceable_scene(out)
    try:
        scene = load_scene_folder(src)
    except OSError as e:
        raise InputError(f"{src}: {e}") from None
    grid = pose_grid_times(scene.config)
    rig, pose = perturb_poses(scene.rig(), cfg.pose_error_deg, cfg.seed, grid)
    report = {"source": str(src), **pose, "test_views": _n_test(scene), "out": str(out)}
    write_perturbed_scene(out, scene, timed_samples(rig.trajectory), report)
    if args.json:
        print(json.dumps(report, indent=2))
        return 0
    g = pose["grid"]
    print(
        f"{src}: {pose['poses']} training poses ({pose['sampled']}) turned by "
        f"{cfg.pose_error_deg:g}° about random axes (seed {cfg.seed})"
    )
    print(
        f"measured: mean {pose['measured_mean_deg']:.6f}°, max {pose['measured_max_deg']:.6f}°; "
        f"on the training grid ({g['poses']} poses) mean {g['measured_mean_deg']:.6f}°, max "
        f"{g['measured_max_deg']:.6f}°; camera centres moved by at most "
        f"{pose['centre_shift_max']:.3g}"
    )
    print(f"test views: {report['test_views']} copied unchanged")
    print(f"wrote {out} (native scene folder, timed trajectory; {PERTURB_FILE} records this)")
    return 0


def write_perturbed_scene(out, scene, poses: tuple, report: dict) -> None:
    """A native scene folder at `out` (replaced whole, atomically): `scene`'s config with a timed
    trajectory `poses` = (t (M,) µs, c2w (M, 4, 4)), its events, its test views byte for byte
    (PNG; other image formats are converted losslessly), and `report` as perturb.json."""
    import copy
    import shutil

    from ..config import TrajectoryConfig
    from ..data.formats.native import save_poses, write_events
    from ..io import atomic_dir, write_json

    cfg = copy.deepcopy(scene.config)
    cfg.trajectory = TrajectoryConfig(kind="timed", poses_file="poses.npz")
    cfg.events_file = "events.npz"
    with atomic_dir(out) as tmp:
        write_events(tmp / cfg.events_file, scene.events)
        save_poses(tmp / cfg.trajectory.poses_file, *poses)
        if scene.test_c2w is not None:
            save_poses(tmp / "test" / "poses.npz", scene.test_t, scene.test_c2w)
            rgb_dir = tmp / "test" / "rgb"
            for i, path in enumerate(scene.test_rgb_paths or []):
                rgb_dir.mkdir(parents=True, exist_ok=True)
                dst = rgb_dir / f"{i:06d}.png"
                if path.suffix.lower() == ".png":
                    shutil.copyfile(path, dst)
                else:
                    import imageio.v3 as iio

                    iio.imwrite(dst, iio.imread(path))
        write_json(tmp / PERTURB_FILE, report)
        cfg.save(tmp / "scene.json")  # last: a folder with scene.json is complete


def _n_test(scene) -> int:
    return 0 if scene.test_c2w is None else len(scene.test_c2w)


def _parse_sensor(s: str) -> tuple[int, int]:
    from ..errors import InputError

    try:
        w, h = (int(v) for v in s.lower().split("x"))
    except ValueError:
        raise InputError(f"--sensor must look like 346x260, got {s!r}") from None
    return w, h


def _check_seed(seed: int) -> None:
    from ..errors import InputError

    if seed < 0:
        raise InputError(f"--seed must be a non-negative integer, got {seed}")


def _refuse_same(src, out) -> None:
    from ..errors import InputError

    if out.exists() and src.exists() and out.resolve() == src.resolve():
        raise InputError(f"{out}: --out is the input itself; write the copy elsewhere")


def _check_replaceable_events(out) -> None:
    """An existing --out may be replaced only if it is an events file (the same kind)."""
    from ..data.formats.native import read_event_arrays
    from ..errors import InputError

    if not out.is_file():
        raise InputError(f"{out}: exists and is not a file; not overwriting it")
    try:
        read_event_arrays(out)
    except InputError:
        raise InputError(
            f"{out}: exists and is not an events file; not overwriting it (choose another --out)"
        ) from None


def _check_replaceable_scene(out) -> None:
    """An existing --out may be replaced only if it is a native scene folder or empty."""
    from ..errors import InputError

    if out.is_dir() and ((out / "scene.json").is_file() or not any(out.iterdir())):
        return
    raise InputError(
        f"{out}: exists and is not a native scene folder (no scene.json); not overwriting it"
    )
