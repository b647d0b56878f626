"""The native scene folder (DESIGN §6).

```
SCENE/
  scene.json          SceneConfig
  events.npz | .h5    x uint16, y uint16, t int64 µs, p int8 ±1, sorted by t
                      (+ width, height of the sensor, optional)
  poses.npz           (timed trajectories) t (M,) int64 µs, c2w (M, 4, 4) float64
  test/poses.npz      ground-truth views: t (V,) int64 µs, c2w (V, 4, 4)
  test/rgb/NNNNNN.png display-space images (gamma 2.2 of linear intensity)
```
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...config import SceneConfig
from ...errors import InputError
from ...io import atomic_path, read_npz, savez, write_image
from ..events import EventStream
from ..poses import load_poses, save_poses
from ..rig import Rig

EVENT_KEYS = ("x", "y", "t", "p")
SIZE_KEYS = ("width", "height")  # optional, in files written by `write_events`


@dataclass
class Scene:
    """A loaded scene: config, events, and (if present) ground-truth test views.

    poses: the timed trajectory held in memory, (t (M,) int64 µs, c2w (M, 4, 4) float64),
    or None for a turntable; readers of foreign layouts (EventNeRF folders) fill it instead
    of writing a poses file into the user's dataset.
    """

    root: Path
    config: SceneConfig
    events: EventStream
    test_t: np.ndarray | None = None  # (V,) int64 µs
    test_c2w: np.ndarray | None = None  # (V, 4, 4) float64
    test_rgb_paths: list[Path] | None = None
    poses: tuple[np.ndarray, np.ndarray] | None = None

    def rig(self) -> Rig:
        """The scene's `Rig` (intrinsics, pose(t), Bayer), from the in-memory poses if any."""
        return Rig.from_scene(self.config, self.root, self.poses)

    def load_test_images(self) -> np.ndarray:
        """Ground-truth test views (V, H, W, 3) float32 in [0, 1], display space."""
        import imageio.v3 as iio

        if not self.test_rgb_paths:
            raise InputError(f"{self.root}: no ground-truth test views (test/rgb/*.png)")
        imgs = []
        for p in self.test_rgb_paths:
            img = iio.imread(p)
            img = np.repeat(img[..., None], 3, -1) if img.ndim == 2 else img[..., :3]
            imgs.append(img.astype(np.float32) / (65535.0 if img.dtype == np.uint16 else 255.0))
        return np.stack(imgs)


def read_event_arrays(path: str | Path) -> dict[str, np.ndarray]:
    """Raw arrays x, y, t, p of an `.npz` or `.h5` events file (not yet validated), plus
    `width`/`height` (0-d) when the file stores them; one-line errors for damaged files."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: events file not found")
    if path.suffix == ".npz":
        return read_npz(path, EVENT_KEYS, SIZE_KEYS, what="events file")
    if path.suffix in (".h5", ".hdf5"):
        import h5py

        try:
            with h5py.File(path, "r") as f:
                g = f["events"] if "events" in f else f
                missing = [k for k in EVENT_KEYS if k not in g]
                if missing:
                    raise InputError(f"{path}: missing dataset(s) {missing} (needs x, y, t, p)")
                out = {k: g[k][()] for k in EVENT_KEYS}
                out.update({k: np.asarray(g.attrs[k]) for k in SIZE_KEYS if k in g.attrs})
                return out
        except InputError:
            raise
        except (OSError, KeyError, ValueError) as e:
            raise InputError(f"{path}: cannot read HDF5 (truncated or corrupt: {e})") from None
    raise InputError(f"{path}: unknown events format (use .npz or .h5)")


def read_events(path: str | Path, width: int, height: int) -> EventStream:
    """Read `events.npz` or `events.h5` with one-line errors for every kind of damage."""
    arrays = read_event_arrays(path)
    if "width" in arrays and "height" in arrays:
        stored = (int(arrays["width"]), int(arrays["height"]))
        if stored != (width, height):
            raise InputError(
                f"{path}: events of a {stored[0]}x{stored[1]} sensor, but the scene "
                f"says {width}x{height}"
            )
    arrays = {k: arrays[k] for k in EVENT_KEYS}
    return EventStream.from_arrays(**arrays, width=width, height=height, source=str(path))


def write_events(path: str | Path, ev: EventStream) -> Path:
    """Write events as native npz (or h5 by suffix), atomically."""
    path = Path(path)
    arrays = {"x": ev.x, "y": ev.y, "t": ev.t, "p": ev.p}
    if path.suffix in (".h5", ".hdf5"):
        import h5py

        with atomic_path(path) as tmp:
            with h5py.File(tmp, "w") as f:
                for k, a in arrays.items():
                    f.create_dataset(k, data=a, compression="gzip", compression_opts=1)
                f.attrs["width"], f.attrs["height"] = ev.width, ev.height
        return path
    size = {"width": np.int64(ev.width), "height": np.int64(ev.height)}
    return savez(path, compressed=True, **arrays, **size)


def load_scene(root: str | Path) -> Scene:
    """Load a native scene folder (validating everything) or raise one clear `InputError`."""
    root = Path(root)
    if not root.exists():
        raise InputError(f"{root}: no such scene folder")
    cfg = SceneConfig.load(root)
    events = read_events(root / cfg.events_file, cfg.width, cfg.height)
    scene = Scene(root, cfg, events)
    if cfg.trajectory.kind == "timed":
        scene.poses = load_poses(root / cfg.trajectory.poses_file)
    test_poses = root / "test" / "poses.npz"
    if test_poses.is_file():
        scene.test_t, scene.test_c2w = load_poses(test_poses)
        rgb = sorted((root / "test" / "rgb").glob("*.png"))
        if rgb and len(rgb) != len(scene.test_c2w):
            raise InputError(f"{root / 'test'}: {len(rgb)} images but {len(scene.test_c2w)} poses")
        scene.test_rgb_paths = rgb or None
    return scene


def save_scene(
    root: str | Path,
    cfg: SceneConfig,
    events: EventStream,
    test_t: np.ndarray | None = None,
    test_c2w: np.ndarray | None = None,
    test_rgb: np.ndarray | None = None,
    poses: tuple | None = None,
) -> Path:
    """Write a native scene folder into `root` (files written atomically).

    test_rgb: (V, H, W, 3) float display space in [0, 1]; poses: (t, c2w) for timed scenes.
    """
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    write_events(root / cfg.events_file, events)
    if poses is not None:
        save_poses(root / (cfg.trajectory.poses_file or "poses.npz"), *poses)
    if test_c2w is not None:
        save_poses(root / "test" / "poses.npz", test_t, test_c2w)
        if test_rgb is not None:
            for i, img in enumerate(test_rgb):
                write_image(root / "test" / "rgb" / f"{i:06d}.png", img)
    cfg.save(root / "scene.json")  # last: a folder with scene.json is complete
    return root
