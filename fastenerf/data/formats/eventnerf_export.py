"""Writing EventNeRF dataset folders that the authors' code loads (`export_eventnerf`).

The layout, the time convention and the unit-sphere normalisation are those the reader
(`fastenerf.data.formats.eventnerf`) undoes; this module holds only the writing side.
"""

from __future__ import annotations

import os
import shutil
import warnings
from pathlib import Path

import numpy as np

from ...errors import InputError
from ...io import atomic_dir, write_json
from ..rig import Intrinsics
from .eventnerf import META_FILE, SENSOR, _to_written, unit_sphere_normalisation
from .native import Scene


def export_eventnerf(
    scene: Scene, out_dir: str | Path, n_views: int | None = None, *, strict_sensor: bool = False
) -> Path:
    """Write `scene` as an EventNeRF folder (train, validation, test) that their code can load.

    n_views: training views, uniform in time over the stream (default: config.n_views).
    Events outside (t_start, t_end] lie in no window and are left out; t is written as float64
    seconds since t_start (minus the 1 µs of the (a, b] -> [a, b) shift), and view i is posed
    at their time i/(n-1)·max(t), so their windows hold exactly our events. Intrinsics with
    OpenCV distortion are converted to their model by a least-squares fit over the sensor
    (the worst pixel error of the fit is stored in fastenerf_scene.json; a warning above
    0.1 px). validation/ and test/ hold the scene's test views with their ground truth (at
    least 3 views, as their validation logging needs), otherwise every 10th training view
    with placeholder images; each split gets (a hard link to) the events file, which their
    loader requires. The folder is built beside `out_dir` and renamed into place.
    Their loader hard-codes a 346x260 sensor: another size is written with a warning (our
    `load_eventnerf` reads it back at its size from the record), or refused if `strict_sensor`.
    """
    cfg = scene.config
    if (cfg.width, cfg.height) != SENSOR:
        msg = (
            f"{scene.root}: sensor {cfg.width}x{cfg.height} is not the 346x260 that the "
            "EventNeRF authors' loader hard-codes"
        )
        if strict_sensor:
            raise InputError(msg)
        warnings.warn(msg + "; their code cannot read this folder", stacklevel=2)
    n = int(n_views or cfg.n_views)
    if n < 3:
        raise InputError(f"export_eventnerf: needs at least 3 views, got {n}")
    ev = scene.events
    t0 = cfg.t_start_us
    keep = (ev.t > t0) & (ev.t <= cfg.t_end_us)
    if not keep.any():
        raise InputError(f"{scene.root}: no events in ({t0}, {cfg.t_end_us}] µs to export")
    tau_us = ev.t[keep] - 1 - t0  # >= 0: our (a, b] is their [a - 1, b - 1)
    tau_max = int(tau_us.max())
    t_views = t0 + np.arange(n) / (n - 1) * tau_max  # float µs: exactly their view times
    rig = scene.rig()
    c2w = rig.pose(t_views)
    K, fit_px = _eventnerf_intrinsics(rig.intrinsics)
    if fit_px > 0.1:
        warnings.warn(
            f"export_eventnerf: OpenCV distortion fits their model only to {fit_px:.2f} px",
            stacklevel=2,
        )

    test_c2w, test_rgb, test_t = _export_test_views(scene, c2w, t_views)
    norm = unit_sphere_normalisation(cfg, np.concatenate([c2w, test_c2w]))
    c2w, test_c2w = _to_written(c2w, norm), _to_written(test_c2w, norm)
    out_dir = Path(out_dir)
    placeholder = _placeholder_png(cfg.width, cfg.height)
    with atomic_dir(out_dir) as tmp:
        train = tmp / "train"
        events_file = train / "events" / "events.npz"
        events_file.parent.mkdir(parents=True)
        np.savez_compressed(
            events_file,
            x=ev.x[keep],
            y=ev.y[keep],
            t=tau_us.astype(np.float64) * 1e-6,
            p=ev.p[keep],
        )
        _write_views(train, c2w, K, [None] * n, placeholder)
        for split in ("validation", "test"):
            _write_views(tmp / split, test_c2w, K, test_rgb or [None] * len(test_c2w), placeholder)
            _link_or_copy(events_file, tmp / split / "events" / "events.npz")
        write_json(
            tmp / META_FILE,
            {
                "scene": cfg.to_dict(),
                "time_unit": "s",
                "t_origin_us": t0,
                "written_intrinsics": K.tolist(),
                "distortion_fit_max_px": fit_px,
                "test_t_us": None if test_t is None else np.asarray(test_t).tolist(),
                "normalisation": norm,
            },
        )
    return out_dir


def _export_test_views(scene: Scene, c2w: np.ndarray, t_views: np.ndarray):
    """(c2w (V, 4, 4), rgb paths or None, t (V,) µs) of validation/ and test/: the scene's test
    views with ground truth when it has 3 or more, else every 10th training view (at least 3)."""
    if scene.test_c2w is not None and len(scene.test_c2w) >= 3:
        return scene.test_c2w, scene.test_rgb_paths, scene.test_t
    n = len(c2w)
    idx = np.arange(0, n, 10) if n >= 30 else np.linspace(0, n - 1, 3).astype(int)
    return c2w[idx], None, np.round(t_views[idx]).astype(np.int64)


def _eventnerf_intrinsics(intr: Intrinsics) -> tuple[np.ndarray, float]:
    """Their 4x4 (or 5x4 with k1 k2) matrix for `intr`, and the fit's worst error in pixels."""
    K = np.eye(4)
    K[0, 0], K[1, 1], K[0, 2], K[1, 2] = intr.fx, intr.fy, intr.cx, intr.cy
    if not intr.distorted:
        return K, 0.0
    if intr.model == "eventnerf":
        k1, k2, err = intr.k1, intr.k2, 0.0
    else:
        k1, k2, err = _fit_division_model(intr)
    return np.concatenate([K, [[k1, k2, 0.0, 0.0]]]), err


def _fit_division_model(intr: Intrinsics) -> tuple[float, float, float]:
    """(k1, k2) of x_u = x_d / (1 + k1 r_d² + k2 r_d⁴) closest to OpenCV `intr` over the
    sensor's distorted radii, by linear least squares; and the worst error in pixels."""
    corners_u = np.array([0.0, intr.width]) - intr.cx
    corners_v = np.array([0.0, intr.height]) - intr.cy
    r_max = np.hypot(np.abs(corners_u).max() / intr.fx, np.abs(corners_v).max() / intr.fy)
    rd = np.linspace(0.0, r_max, 512)[1:]
    ru = intr.undistort(np.stack([rd, np.zeros_like(rd)], -1))[:, 0]
    A = np.stack([rd**2, rd**4], -1)
    (k1, k2), *_ = np.linalg.lstsq(A, rd / ru - 1.0, rcond=None)
    ru_fit = rd / (1.0 + k1 * rd**2 + k2 * rd**4)
    return float(k1), float(k2), float(np.abs(ru_fit - ru).max() * max(intr.fx, intr.fy))


def _placeholder_png(width: int, height: int) -> bytes:
    import imageio.v3 as iio

    return iio.imwrite("<bytes>", np.zeros((height, width, 3), np.uint8), extension=".png")


def _write_matrix(path: Path, m: np.ndarray) -> None:
    path.write_text("\n".join(" ".join(f"{v:.17g}" for v in row) for row in m) + "\n")


def _write_views(split_dir: Path, c2w: np.ndarray, K: np.ndarray, rgb: list, placeholder: bytes):
    for sub in ("pose", "intrinsics", "rgb"):
        (split_dir / sub).mkdir(parents=True, exist_ok=True)
    for i, (pose, src) in enumerate(zip(c2w, rgb, strict=True)):
        name = f"r_{i:05d}"
        _write_matrix(split_dir / "pose" / f"{name}.txt", pose)
        _write_matrix(split_dir / "intrinsics" / f"{name}.txt", K)
        if src is None:
            (split_dir / "rgb" / f"{name}.png").write_bytes(placeholder)
        else:
            shutil.copyfile(src, split_dir / "rgb" / f"{name}{Path(src).suffix.lower()}")


def _link_or_copy(src: Path, dst: Path) -> None:
    dst.parent.mkdir(parents=True, exist_ok=True)
    try:
        os.link(src, dst)
    except OSError:
        shutil.copyfile(src, dst)
