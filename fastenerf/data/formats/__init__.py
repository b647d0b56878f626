"""Readers and writers of event data: one entry point, `load_any`, that tells them apart.

- native scene folder (has scene.json)            -> `Scene`     (native.load_scene)
- EventNeRF scene folder (has train/events/)      -> `Scene`     (eventnerf.load_eventnerf)
- one events file .npz / .h5 / .txt / .aedat4     -> `EventStream`

A single .npz / .h5 holds x, y, t, p (native: t int64 µs); a float t with fractions is read as
seconds (as in EventNeRF's real data), and the sensor size comes from the argument, the
file's stored width/height, or max(x) + 1 by max(y) + 1, in that order.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ...errors import InputError
from ..events import EventStream
from .native import Scene, read_event_arrays

EVENT_FILE_SUFFIXES = (".npz", ".h5", ".hdf5", ".txt", ".aedat4")


def load_any(path: str | Path, sensor: tuple[int, int] | None = None) -> Scene | EventStream:
    """A scene folder as a `Scene`, a single events file as an `EventStream`.

    sensor: (width, height) for event files that do not say (otherwise taken from the file's
    header or stored size, else inferred as max(x) + 1 by max(y) + 1).
    """
    return open_any(path, sensor)[0]


def open_any(
    path: str | Path, sensor: tuple[int, int] | None = None
) -> tuple[Scene | EventStream, str]:
    """`load_any`, plus a few words on what was read (format; where the sensor size came from)."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: no such file or folder")
    if path.is_dir():
        if (path / "scene.json").is_file():
            from .native import load_scene

            return load_scene(path), "native scene folder"
        from .eventnerf import is_eventnerf_folder, load_eventnerf

        if is_eventnerf_folder(path):
            return load_eventnerf(path), "EventNeRF scene folder (split train)"
        raise InputError(f"{path}: not a scene folder (no scene.json, no train/events/)")
    return open_events(path, sensor)


def open_events(path: str | Path, sensor: tuple[int, int] | None = None) -> tuple[EventStream, str]:
    """Read one events file; returns the stream and a note on the format and sensor source."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".txt":
        from .txt import read_txt, txt_header

        header = txt_header(path)
        w, h = sensor or (None, None)
        src = "given" if sensor else "header" if header else "inferred from max x, y"
        return read_txt(path, w, h), f"text events (sensor {src})"
    if suffix == ".aedat4":
        try:
            from .aedat import read_aedat4
        except ImportError:
            raise InputError(
                f"{path}: the AEDAT4 reader (fastenerf/data/formats/aedat.py) is not available yet"
            ) from None
        return read_aedat4(path), "AEDAT4 recording"
    if suffix in (".npz", ".h5", ".hdf5"):
        raw = read_event_arrays(path)
        if sensor:
            (w, h), src = sensor, "given"
        elif "width" in raw and "height" in raw:
            (w, h), src = (int(raw["width"]), int(raw["height"])), "stored in the file"
        else:
            (w, h), src = _infer_sensor(raw), "inferred from max x, y"
        t, unit = np.asarray(raw["t"]), ""
        if t.dtype.kind == "f" and np.all(np.isfinite(t)) and np.any(t != np.round(t)):
            t, unit = np.round(t * 1e6), ", float t read as seconds"  # e.g. EventNeRF's real data
        ev = EventStream.from_arrays(raw["x"], raw["y"], t, raw["p"], w, h, str(path))
        return ev, f"{suffix[1:]} events (sensor {src}{unit})"
    raise InputError(f"{path}: unknown events format (one of {', '.join(EVENT_FILE_SUFFIXES)})")


def _infer_sensor(raw: dict) -> tuple[int, int]:
    x, y = np.asarray(raw["x"]), np.asarray(raw["y"])
    if x.size == 0 or x.dtype.kind not in "iuf" or y.dtype.kind not in "iuf":
        return 1, 1  # EventStream.from_arrays reports what is wrong
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
        return 1, 1
    return int(max(x.max(), 0)) + 1, int(max(y.max(), 0)) + 1


def load_scene_folder(path: str | Path) -> Scene:
    """A scene to train on: a native scene folder or an EventNeRF dataset folder."""
    path = Path(path)
    scene, _ = open_any(path)
    if not isinstance(scene, Scene):
        raise InputError(f"{path}: an event file, not a scene folder (no poses or intrinsics)")
    return scene
