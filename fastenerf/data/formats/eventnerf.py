"""The EventNeRF authors' dataset folders (DESIGN §9): read as released, written for their code.

```
SCENE/<split>/                 split: train, validation, test
  events/<one file>.npz        x, y int pixels; t (see below); p ±1 (0/1 accepted)
  pose/r_NNNNN.txt             4x4 camera-to-world (OpenCV axes), one file per view
  intrinsics/r_NNNNN.txt       4x4 K = [fx 0 cx 0; 0 fy cy 0; 0 0 1 0; 0 0 0 1], optionally a
                               5th row "k1 k2 0 0" (their rays: x_u = x_d / (1 + k1 r_d² + k2 r_d⁴),
                               kept exactly as distortion_model "eventnerf")
  rgb/r_NNNNN.png              one per view: ground truth or a placeholder (their loader
                               enumerates the views by these files; real scenes hold placeholders)
SCENE/fastenerf_scene.json     only in folders written by `export_eventnerf`: our SceneConfig
                               and the similarity that maps our world to the written poses
```
Sensor 346x260 (their loader hard-codes it). Views are files sorted by name, as theirs are,
matched by file stem across pose/, intrinsics/ and rgb/ (a missing or extra file is named in
the error). Their view times come from the view's place in the listing; we take it from the
number ending the stem, so a gap in the numbering (a view deleted) keeps the other views at
their times, with a warning naming the missing views, instead of respacing them.

Their trainer (NeRF++'s sphere parametrisation) needs every camera, and the object, inside the
unit sphere. `export_eventnerf` therefore writes poses in a normalised frame
x_written = scale · (x_world − center): center the scene box's centre (on the turntable axis
x = z = 0 where the scene has a clip cylinder, so that the cylinder stays one about y), scale
such that the farthest camera centre or box corner lies at radius 0.9. The record keeps
scale and center (and the box and cylinder in the written frame, for their configs), and
`load_eventnerf` maps the poses back, so a round trip gives back our world; a folder without
the record is read in its own frame.

Time, as their `data_loader_split.py` uses it: with M views and τ_max = max(t), view i sits at
τ_i = i/(M-1)·τ_max (we count i by the view's number from the first; see above), and the
window that ends at view i and spans w views holds the events with τ_{i-w} <= τ < τ_i
(half-open on the left). Cycled (real) configs wrap windows that start
before 0 to the end of the stream. The unit of t is not stored: synthetic scenes hold the frame
index (integers 0..M-1, rendered at 1000 fps, so 1 unit = 1000 µs), real ones a float
timestamp. We detect it (`time_unit=None`): integers with max = M-1 -> "frame"; floats below
1e5 -> seconds; anything else -> µs; pass `time_unit` to override. Events are read as
t_us = round(τ·unit) + 1 and views placed at T_i = round(τ_i·unit): the extra 1 µs turns their
[τ_a, τ_b) into our (T_a, T_b] (DESIGN §3) exactly, so every window holds the same events as
theirs. (One difference remains on cycled scenes: events at exactly τ_max enter their wrapped
windows but lie after our t_end; that is the stream's last event or, on synthetic data, which
they never cycle, the last frame.)
"""

from __future__ import annotations

import json
import re
import warnings
from pathlib import Path

import numpy as np

from ...config import (
    EVENTNERF_REAL_THRESHOLD,
    IntrinsicsConfig,
    SceneConfig,
    TrajectoryConfig,
    eventnerf_real_cylinder,
)
from ...errors import InputError
from ..events import EventStream
from .native import Scene, read_event_arrays

SENSOR = (346, 260)
SPLITS = ("train", "validation", "test")
META_FILE = "fastenerf_scene.json"
TIME_UNITS_US = {"frame": 1000.0, "s": 1e6, "ms": 1e3, "us": 1.0}
REAL_BACKGROUND = [159 / 255] * 3  # their real configs composite over sRGB 159 (DESIGN §9)
IMAGE_EXTS = (".png", ".jpg", ".jpeg")


def is_eventnerf_folder(path: str | Path) -> bool:
    """True for a scene folder in the authors' layout (has train/events/)."""
    return (Path(path) / "train" / "events").is_dir()


def load_eventnerf(
    root: str | Path,
    split: str = "train",
    *,
    test_split: str | None = "auto",
    time_unit: str | None = None,
    sensor: tuple[int, int] | None = None,
) -> Scene:
    """Read one EventNeRF scene folder into a `Scene` (nothing is written into `root`).

    split: the split whose events and views make the stream (their training split is "train").
    test_split: where ground-truth test views come from: "auto" takes "test", then "validation",
      if its rgb/ images are real images (not one constant placeholder) and the scene is not a
      real capture (their real rgb/ files are placeholders); None for no test views.
    time_unit: "frame" (1000 µs), "s", "ms" or "us" per unit of the file's t; None detects it.
    sensor: (width, height); None: our export record's size if present, else 346x260.
    Returns a Scene whose config has a "timed" trajectory, the poses in `Scene.poses`
    (t (M,) int64 µs, c2w (M, 4, 4)), events in µs (see the module docstring for the mapping).
    """
    root = Path(root)
    if not (root / split).is_dir():
        raise InputError(
            f"{root}: no '{split}' folder (an EventNeRF scene has "
            f"{'/'.join(SPLITS)} folders with events/, pose/, intrinsics/, rgb/)"
        )
    meta = _read_meta(root)
    views = _read_views(root / split, require_events=True)
    views["c2w"] = _from_written(views["c2w"], meta, root)
    n = len(views["c2w"])
    if n < 2:
        raise InputError(f"{root / split / 'pose'}: needs at least 2 views, found {n}")
    slot = views["index"] - views["index"][0]  # view i's place in the sequence (gaps kept)
    n_slots = int(slot[-1]) + 1
    raw = read_event_arrays(views["events"])
    tau = np.asarray(raw["t"])
    src = str(views["events"])
    if tau.ndim != 1 or tau.dtype.kind not in "iuf" or len(tau) == 0:
        raise InputError(f"{src}: 't' must be a non-empty 1-D numeric array")
    if tau.dtype.kind == "f" and not np.all(np.isfinite(tau)):
        raise InputError(f"{src}: 't' is NaN or inf at event {int(np.argmax(~np.isfinite(tau)))}")

    unit = time_unit or (meta or {}).get("time_unit") or _detect_time_unit(tau, n_slots)
    if unit not in TIME_UNITS_US:
        raise InputError(f"{src}: unknown time unit {unit!r} (one of {list(TIME_UNITS_US)})")
    scale = TIME_UNITS_US[unit]
    origin = int((meta or {}).get("t_origin_us", 0))
    tau_max = float(tau.max())
    t_us = np.round(tau.astype(np.float64) * scale).astype(np.int64) + 1 + origin
    width, height = sensor or (
        (meta["scene"]["width"], meta["scene"]["height"]) if meta else SENSOR
    )
    events = EventStream.from_arrays(raw["x"], raw["y"], t_us, raw["p"], width, height, src)

    span_us = tau_max * scale
    t_views = origin + np.round(slot / (n_slots - 1) * span_us).astype(np.int64)
    if np.any(np.diff(t_views) <= 0):
        raise InputError(
            f"{src}: the stream ({span_us:.0f} µs) is too short for {n_slots} views "
            "at distinct microseconds"
        )
    kind = "synthetic" if unit == "frame" else "real"
    cfg = _scene_config(root, meta, views, kind, width, height, t_views, n_slots)
    scene = Scene(root, cfg, events, poses=(t_views, views["c2w"]))
    _attach_test_views(scene, root, split, test_split, views, meta, kind)
    return scene


# ---------------------------------------------------------------------------- reading


def _detect_time_unit(tau: np.ndarray, n_views: int) -> str:
    integral = tau.dtype.kind in "iu" or bool(np.all(tau == np.round(tau)))
    if integral and tau.min() >= 0 and tau.max() == n_views - 1:
        return "frame"  # synthetic: t is the frame index, one frame per view at 1000 fps
    if tau.dtype.kind == "f" and tau.max() < 1e5:
        return "s"
    return "us"


def _read_meta(root: Path) -> dict | None:
    path = root / META_FILE
    if not path.is_file():
        return None
    try:
        meta = json.loads(path.read_text())
        SceneConfig.from_dict(meta["scene"], str(path))
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError) as e:
        raise InputError(f"{path}: not a valid fastenerf export record ({e})") from None
    return meta


def _listing(folder: Path, exts: tuple[str, ...]) -> list[Path]:
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in exts)


def _read_matrix(path: Path, rows: tuple[int, ...]) -> np.ndarray:
    """A whitespace-separated matrix of 4 columns and one of `rows` rows, float64."""
    try:
        vals = np.array([float(v) for v in path.read_text().split()], dtype=np.float64)
    except (ValueError, UnicodeDecodeError, OSError) as e:
        raise InputError(f"{path}: not a matrix of numbers ({e})") from None
    for r in rows:
        if len(vals) == 4 * r:
            if not np.all(np.isfinite(vals)):
                raise InputError(f"{path}: contains NaN or inf")
            return vals.reshape(r, 4)
    shapes = " or ".join(f"{r}x4" for r in rows)
    raise InputError(
        f"{path}: expected a {shapes} matrix ({' or '.join(str(4 * r) for r in rows)}"
        f" numbers), found {len(vals)} numbers"
    )


def _read_views(split_dir: Path, require_events: bool) -> dict:
    """Poses (M, 4, 4), the one shared intrinsics (5, 4), rgb paths and the events file."""
    pose_files = _listing(split_dir / "pose", (".txt",))
    intr_files = _listing(split_dir / "intrinsics", (".txt",))
    rgb_files = _listing(split_dir / "rgb", IMAGE_EXTS)
    if not pose_files:
        raise InputError(f"{split_dir / 'pose'}: no pose files (*.txt)")
    _match_views(split_dir, pose_files, "intrinsics", intr_files)
    if rgb_files:  # optional: a folder may come without images
        _match_views(split_dir, pose_files, "rgb", rgb_files)
    index = _view_numbers(split_dir / "pose", pose_files)
    c2w = np.stack([_read_matrix(p, (4,)) for p in pose_files])
    _check_poses(c2w, pose_files)
    intr = None
    for p in intr_files:
        m = _read_matrix(p, (4, 5))
        m = np.concatenate([m, np.zeros((1, 4))]) if len(m) == 4 else m
        if intr is None:
            _check_intrinsics(m, p)
            intr, first = m, p
        elif not np.allclose(
            m[[0, 0, 1, 1, 4, 4], [0, 2, 1, 2, 0, 1]],
            intr[[0, 0, 1, 1, 4, 4], [0, 2, 1, 2, 0, 1]],
            rtol=1e-6,
            atol=1e-9,
        ):
            raise InputError(
                f"{p}: intrinsics differ from {first.name} (fastenerf supports one "
                "camera per scene)"
            )
    events = _listing(split_dir / "events", (".npz",))
    if require_events and len(events) != 1:
        raise InputError(
            f"{split_dir / 'events'}: needs exactly one .npz events file, found {len(events)}"
        )
    return {
        "c2w": c2w,
        "intrinsics": intr,
        "rgb": rgb_files,
        "events": events[0] if events else None,
        "pose_files": pose_files,
        "index": index,
    }


def _names(items: list[str], limit: int = 3) -> str:
    more = f" and {len(items) - limit} more" if len(items) > limit else ""
    return ", ".join(items[:limit]) + more


def _match_views(split_dir: Path, pose_files: list[Path], sub: str, files: list[Path]) -> None:
    """One `sub` file per pose file, matched by file stem; a missing or extra file named."""
    stems = [f.stem for f in files]
    dup = sorted({s for s in stems if stems.count(s) > 1})
    if dup:
        twice = [f.name for f in files if f.stem == dup[0]]
        raise InputError(f"{split_dir / sub}: two files for view {dup[0]} ({', '.join(twice)})")
    have, want = set(stems), {p.stem for p in pose_files}
    missing = [p.name for p in pose_files if p.stem not in have]
    extra = [f.name for f in files if f.stem not in want]
    if missing:
        raise InputError(
            f"{split_dir}: pose/{missing[0]} has no {sub}/{Path(missing[0]).stem}.* file "
            f"(missing for {_names(missing)}; one pose, intrinsics and rgb file per view)"
        )
    if extra:
        raise InputError(
            f"{split_dir}: {sub}/{extra[0]} has no pose/{Path(extra[0]).stem}.txt file "
            f"(no pose for {_names(extra)}; one pose, intrinsics and rgb file per view)"
        )


def _view_numbers(pose_dir: Path, files: list[Path]) -> np.ndarray:
    """(M,) int64: each view's number (the digits ending its stem) in the sequence, or
    0..M-1 where the stems carry no numbers. A gap in the numbers is kept (the views keep
    the times they have in the complete sequence) and reported as a warning."""
    found = [re.search(r"(\d+)$", f.stem) for f in files]
    if not all(found):
        return np.arange(len(files), dtype=np.int64)
    num = np.array([int(m.group(1)) for m in found], dtype=np.int64)
    if np.any(np.diff(num) <= 0):
        i = int(np.flatnonzero(np.diff(num) <= 0)[0])
        raise InputError(
            f"{pose_dir}: view numbers are not in file-name order ({files[i].name} sorts "
            f"before {files[i + 1].name}); number the views with zero-padded, distinct numbers"
        )
    gaps = sorted(set(range(int(num[0]), int(num[-1]) + 1)) - set(num.tolist()))
    if gaps:
        width = len(found[0].group(1))
        prefix = files[0].stem[: found[0].start()]
        names = [f"{prefix}{g:0{width}d}" for g in gaps]
        warnings.warn(
            f"{pose_dir}: {len(gaps)} view(s) missing from the sequence {files[0].stem}.."
            f"{files[-1].stem}: {_names(names)}; the other views keep their times by number "
            "(their loader would respace them)",
            stacklevel=3,
        )
    return num


def _check_poses(c2w: np.ndarray, files: list[Path]) -> None:
    R = c2w[:, :3, :3]
    err = np.abs(np.einsum("nij,nik->njk", R, R) - np.eye(3)).max((1, 2))
    bottom = np.abs(c2w[:, 3] - [0, 0, 0, 1]).max(1)
    bad = (err > 1e-3) | (np.linalg.det(R) < 0) | (bottom > 1e-6)
    if bad.any():
        raise InputError(
            f"{files[int(np.argmax(bad))]}: not a rigid camera-to-world matrix "
            "(rotation must be orthonormal with det +1, last row 0 0 0 1)"
        )


def _check_intrinsics(m: np.ndarray, path: Path) -> None:
    fx, fy = m[0, 0], m[1, 1]
    if fx <= 0 or fy <= 0:
        raise InputError(f"{path}: focal lengths must be positive (fx={fx}, fy={fy})")
    if (
        abs(m[0, 1]) > 1e-9 * fx
        or abs(m[1, 0]) > 1e-9 * fy
        or np.abs(m[2, :3] - [0, 0, 1]).max() > 1e-9
    ):
        raise InputError(f"{path}: K must be [fx 0 cx; 0 fy cy; 0 0 1] (no skew)")


def _is_placeholder(path: Path) -> bool:
    """A constant image stands for "no ground truth" (what `export_eventnerf` writes)."""
    import imageio.v3 as iio

    try:
        img = iio.imread(path)
    except Exception as e:  # imageio raises many types for damaged files
        raise InputError(f"{path}: cannot read image ({e})") from None
    return bool(img.min() == img.max())


def _scene_config(
    root: Path,
    meta: dict | None,
    views: dict,
    kind: str,
    width: int,
    height: int,
    t_views: np.ndarray,
    n_views: int,
) -> SceneConfig:
    m = views["intrinsics"]
    intr = IntrinsicsConfig(
        fx=float(m[0, 0]),
        fy=float(m[1, 1]),
        cx=float(m[0, 2]),
        cy=float(m[1, 2]),
        k1=float(m[4, 0]),
        k2=float(m[4, 1]),
        distortion_model="eventnerf",
    )
    if meta is not None:  # our own export: restore what the layout cannot hold
        cfg = SceneConfig.from_dict(meta["scene"], str(root / META_FILE))
        written = np.zeros((5, 4))
        w = np.asarray(meta.get("written_intrinsics", np.zeros((0, 4))), dtype=np.float64)
        written[: len(w)] = w
        if not np.allclose(written, m, rtol=1e-12, atol=0.0):
            cfg.intrinsics = intr  # the files were edited since the export: they win
        keep_span = cfg.t_start_us <= t_views[0] and cfg.t_end_us >= t_views[-1]
    else:
        real = kind == "real"
        # a released real scene of the authors' gets its config's clip and threshold (DESIGN §9)
        threshold = EVENTNERF_REAL_THRESHOLD.get(root.name.lower(), 0.1) if real else 0.25
        cfg = SceneConfig(
            name=root.name,
            width=width,
            height=height,
            intrinsics=intr,
            trajectory=TrajectoryConfig(kind="timed"),
            bayer="rggb",
            pos_threshold=threshold,
            neg_threshold=threshold,
            loop=real,
            cylinder=eventnerf_real_cylinder(root.name) if real else None,
            background=REAL_BACKGROUND if real else [0.0, 0.0, 0.0],
            kind=kind,
        )
        keep_span = False
    cfg.width, cfg.height = width, height
    cfg.trajectory = TrajectoryConfig(kind="timed", poses_file="poses.npz")
    if not keep_span:  # (an export's own span keeps its loop period exactly)
        cfg.t_start_us, cfg.t_end_us = int(t_views[0]), int(t_views[-1])
    cfg.n_views = n_views  # views of the complete sequence (a gap keeps its place)
    return cfg.validate(str(root))


def _attach_test_views(
    scene: Scene,
    root: Path,
    split: str,
    test_split: str | None,
    train: dict,
    meta: dict | None,
    kind: str,
) -> None:
    if test_split is None:
        return
    if test_split == "auto":
        candidates = [] if kind == "real" and meta is None else ["test", "validation"]
    else:
        if not (root / test_split).is_dir():
            raise InputError(f"{root}: no '{test_split}' split for test views")
        candidates = [test_split]
    for name in candidates:
        if name == split or not (root / name).is_dir():
            continue
        views = _read_views(root / name, require_events=False)
        if not views["rgb"] or _is_placeholder(views["rgb"][0]):
            if test_split != "auto":
                raise InputError(f"{root / name / 'rgb'}: no ground-truth images")
            continue
        if not np.allclose(views["intrinsics"], train["intrinsics"], rtol=1e-6, atol=1e-9):
            raise InputError(f"{root / name / 'intrinsics'}: differ from the '{split}' split's")
        v = len(views["c2w"])
        t_meta = (meta or {}).get("test_t_us")
        if t_meta is not None and len(t_meta) == v:
            test_t = np.asarray(t_meta, dtype=np.int64)
        else:  # their test views carry no time: nominal, uniform over the stream by number
            cfg = scene.config
            slot = views["index"] - views["index"][0]
            frac = slot / max(int(slot[-1]), 1)
            test_t = np.round(cfg.t_start_us + frac * (cfg.t_end_us - cfg.t_start_us))
            test_t = test_t.astype(np.int64)
        scene.test_t, scene.test_rgb_paths = test_t, views["rgb"]
        scene.test_c2w = _from_written(views["c2w"], meta, root)
        return


# ---------------------------------------------------------------------------- writing


UNIT_SPHERE_RADIUS = 0.9  # where the farthest camera or box corner lands: inside, with margin


def unit_sphere_normalisation(cfg: SceneConfig, c2w: np.ndarray) -> dict:
    """The similarity x_written = scale · (x_world − center) that puts every camera centre of
    c2w (N, 4, 4) and every corner of the scene's box inside the unit sphere (at most
    `UNIT_SPHERE_RADIUS`). Returns {"scale", "center" [3], "aabb" [6], "cylinder"} with
    the box and the clip cylinder (r, y_min, y_max, or None) in the written frame."""
    a = np.asarray(cfg.aabb, np.float64)
    center = (a[:3] + a[3:]) / 2
    if cfg.cylinder is not None:
        center[[0, 2]] = 0.0  # the cylinder's axis (x = z = 0) stays the y axis
    corners = np.stack(np.meshgrid(*zip(a[:3], a[3:], strict=True), indexing="ij"), -1)
    reach = max(
        float(np.linalg.norm(c2w[:, :3, 3] - center, axis=1).max()),
        float(np.linalg.norm(corners.reshape(-1, 3) - center, axis=1).max()),
    )
    scale = UNIT_SPHERE_RADIUS / reach
    cyl = cfg.cylinder
    return {
        "scale": scale,
        "center": center.tolist(),
        "aabb": (scale * (a - np.tile(center, 2))).tolist(),
        "cylinder": None
        if cyl is None
        else [cyl.radius * scale, (cyl.y_min - center[1]) * scale, (cyl.y_max - center[1]) * scale],
    }


def _to_written(c2w: np.ndarray, norm: dict) -> np.ndarray:
    out = np.array(c2w, dtype=np.float64)
    out[:, :3, 3] = norm["scale"] * (out[:, :3, 3] - np.asarray(norm["center"]))
    return out


def _from_written(c2w: np.ndarray, meta: dict | None, root: Path) -> np.ndarray:
    """Written poses (M, 4, 4) back to our world by the record's similarity (as they are where
    the folder has no record, or one from before the normalisation)."""
    norm = (meta or {}).get("normalisation")
    if not norm:
        return c2w
    try:
        scale, center = float(norm["scale"]), np.asarray(norm["center"], np.float64)
    except (KeyError, TypeError, ValueError) as e:
        raise InputError(f"{root / META_FILE}: bad 'normalisation' record ({e})") from None
    if not (
        np.isfinite(scale) and scale > 0 and center.shape == (3,) and np.isfinite(center).all()
    ):
        raise InputError(
            f"{root / META_FILE}: 'normalisation' needs a positive scale and a 3-vector center"
        )
    out = np.array(c2w, dtype=np.float64)
    out[:, :3, 3] = out[:, :3, 3] / scale + center
    return out
