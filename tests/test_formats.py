"""Event-file formats on real files: native folders, EventNeRF folders, text, `fastenerf info`."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from fastenerf.cli import main
from fastenerf.config import IntrinsicsConfig, TrajectoryConfig
from fastenerf.data.events import EventIndex, EventStream
from fastenerf.data.formats import load_any
from fastenerf.data.formats.eventnerf import load_eventnerf
from fastenerf.data.formats.eventnerf_export import export_eventnerf
from fastenerf.data.formats.native import (
    Scene,
    load_poses,
    load_scene,
    read_events,
    save_poses,
    save_scene,
    write_events,
)
from fastenerf.data.formats.txt import read_txt
from fastenerf.data.rig import Intrinsics, TimedPoses, Turntable
from fastenerf.errors import InputError

AEDAT = Path("/work/shared/external-aedat/aedat__test_data.aedat4")


def one_line_error(fn, *args, match: str, **kw) -> str:
    with pytest.raises(InputError) as e:
        fn(*args, **kw)
    msg = str(e.value)
    assert "\n" not in msg, msg
    for m in match.split("|"):
        assert m in msg, msg
    return msg


def assert_same_events(a: EventStream, b: EventStream):
    assert (a.width, a.height) == (b.width, b.height)
    for k in "xytp":
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k))
        assert getattr(a, k).dtype == getattr(b, k).dtype


def timed_poses(cfg, n=40):
    """Poses along the config's turntable, as a timed trajectory (t int64 µs, c2w)."""
    t = np.linspace(cfg.t_start_us, cfg.t_end_us, n).round().astype(np.int64)
    return t, Turntable(cfg.trajectory)(t)


@pytest.fixture
def test_views(rng):
    def make(cfg, v=4):
        t = np.linspace(cfg.t_start_us, cfg.t_end_us, v, endpoint=False).astype(np.int64)
        rgb = rng.random((v, cfg.height, cfg.width, 3)).astype(np.float32)
        return t, Turntable(cfg.trajectory)(t), rgb

    return make


# ---------------------------------------------------------------------------- native


@pytest.mark.parametrize("events_file", ["events.npz", "events.h5"])
def test_native_round_trip(tmp_path, random_stream, scene_config, test_views, events_file):
    cfg = scene_config(
        24,
        16,
        events_file=events_file,
        trajectory=TrajectoryConfig(kind="timed", poses_file="poses.npz"),
    )
    ev = random_stream(n=500, width=24, height=16, t_max=999_000)
    poses = timed_poses(scene_config(24, 16))
    tt, tc, rgb = test_views(cfg)
    save_scene(tmp_path / "s", cfg, ev, tt, tc, rgb, poses=poses)
    scene = load_scene(tmp_path / "s")
    assert scene.config == cfg
    assert_same_events(scene.events, ev)
    np.testing.assert_array_equal(scene.poses[0], poses[0])
    np.testing.assert_array_equal(scene.poses[1], poses[1])
    np.testing.assert_array_equal(scene.test_t, tt)
    np.testing.assert_allclose(scene.load_test_images(), rgb, atol=0.5 / 255 + 1e-6)
    rig = scene.rig()
    np.testing.assert_allclose(rig.pose(poses[0]), poses[1], atol=1e-9)


def truncate(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


@pytest.mark.parametrize("name", ["events.npz", "events.h5"])
def test_truncated_events_file(tmp_path, random_stream, name):
    path = tmp_path / name
    write_events(path, random_stream(n=20_000, t_max=10**6))
    assert_same_events(read_events(path, 16, 12), read_events(path, 16, 12))
    truncate(path)
    one_line_error(read_events, path, 16, 12, match=f"{path}: |truncated or corrupt")


def test_h5_events_group_and_stored_size(tmp_path, random_stream):
    import h5py

    ev = random_stream(n=100)
    with h5py.File(tmp_path / "g.h5", "w") as f:
        g = f.create_group("events")
        for k in "xytp":
            g.create_dataset(k, data=getattr(ev, k))
        g.attrs["width"], g.attrs["height"] = 16, 12
    assert_same_events(read_events(tmp_path / "g.h5", 16, 12), ev)
    assert_same_events(load_any(tmp_path / "g.h5"), ev)
    one_line_error(read_events, tmp_path / "g.h5", 20, 12, match="16x12 sensor|says 20x12")


def test_truncated_and_broken_scene_files(tmp_path, random_stream, scene_config):
    cfg = scene_config(16, 12, trajectory=TrajectoryConfig(kind="timed", poses_file="poses.npz"))
    save_scene(tmp_path, cfg, random_stream(), poses=timed_poses(cfg))
    truncate(tmp_path / "poses.npz")
    one_line_error(load_scene, tmp_path, match="poses.npz: |truncated or corrupt")
    save_poses(tmp_path / "poses.npz", np.arange(3), np.tile(np.eye(4), (4, 1, 1)))
    one_line_error(load_scene, tmp_path, match="poses.npz: |4 poses but 't' has shape (3,)")
    save_poses(tmp_path / "poses.npz", np.arange(4), np.tile(np.eye(3), (4, 1, 1)))
    one_line_error(load_scene, tmp_path, match="'c2w' must be (M, 4, 4)")
    (tmp_path / "poses.npz").unlink()
    one_line_error(load_scene, tmp_path, match="poses.npz: poses file not found")
    np.savez(tmp_path / "events.npz", x=[1], y=[1], t=[0])
    one_line_error(load_scene, tmp_path, match="events.npz: missing array(s) ['p']")


def test_scene_json_problems_name_the_key(tmp_path, random_stream, scene_config):
    cfg = scene_config(16, 12)
    save_scene(tmp_path, cfg, random_stream())
    d = json.loads((tmp_path / "scene.json").read_text())
    del d["intrinsics"]["cy"]
    (tmp_path / "scene.json").write_text(json.dumps(d))
    one_line_error(load_scene, tmp_path, match="scene.json: missing key 'intrinsics.cy'")
    d["intrinsics"] = np.eye(3).tolist()  # a K matrix where an object belongs
    (tmp_path / "scene.json").write_text(json.dumps(d))
    one_line_error(load_scene, tmp_path, match="'intrinsics' must be an object")
    d = cfg.to_dict()
    d["width"] = 8  # the events file says 16x12
    (tmp_path / "scene.json").write_text(json.dumps(d))
    one_line_error(load_scene, tmp_path, match="events.npz: events of a 16x12 sensor|says 8x12")
    with np.load(tmp_path / "events.npz") as z:  # without a stored size: x beyond the sensor
        np.savez(tmp_path / "events.npz", **{k: z[k] for k in "xytp"})
    one_line_error(load_scene, tmp_path, match="events.npz: x=|outside the 8x12 sensor")


def test_test_view_count_mismatch(tmp_path, random_stream, scene_config, test_views):
    cfg = scene_config(16, 12)
    tt, tc, rgb = test_views(cfg, 4)
    save_scene(tmp_path, cfg, random_stream(), tt, tc, rgb)
    (tmp_path / "test" / "rgb" / "000003.png").unlink()
    one_line_error(load_scene, tmp_path, match="3 images but 4 poses")


# ---------------------------------------------------------------------------- EventNeRF


def their_window(ts, i, w, n_views, cycle):
    """Event index set of the reference loader's window ending at view i spanning w views
    (their data_loader_split.py: searchsorted-left on both ends; wrap by concatenation)."""
    tmax = ts.max()
    start_time = (i - w) / (n_views - 1)
    if start_time < 0:
        start_time += 1
    end = np.searchsorted(ts, i / (n_views - 1) * tmax)
    start = np.searchsorted(ts, start_time * tmax)
    if start <= end:
        return np.arange(start, end)
    return np.r_[np.arange(start, len(ts)), np.arange(0, end)]


def write_their_folder(root: Path, rng, n_views, t, x, y, p, k=None, rgb=None):
    """An EventNeRF scene folder written by hand, the way their released data look."""
    for split in ("train", "validation", "test"):
        s = root / split
        for sub in ("events", "pose", "intrinsics", "rgb"):
            (s / sub).mkdir(parents=True)
        np.savez(s / "events" / "out.npz", x=x, y=y, t=t, p=p)
        c2w = Turntable(TrajectoryConfig(radius=0.9, period_us=n_views))(np.arange(n_views))
        for i in range(n_views):
            np.savetxt(s / "pose" / f"r_{i:05d}.txt", c2w[i])
            K = [[280.0, 0, 170.5, 0], [0, 281.0, 131.5, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
            np.savetxt(s / "intrinsics" / f"r_{i:05d}.txt", K + ([] if k is None else [k]))
            img = (
                rgb[i]
                if rgb is not None and split == "test"
                else np.full((260, 346, 3), 90, np.uint8)
            )
            iio.imwrite(s / "rgb" / f"r_{i:05d}.png", img)
    return c2w


def test_their_synthetic_folder(tmp_path, rng):
    """Integer frame-index times (0..M-1): read as 1000 fps, and every window holds exactly
    the events that their loader puts in it."""
    m, n = 30, 6000
    t = np.sort(rng.integers(0, m, n))
    t[-1] = m - 1
    x, y, p = rng.integers(0, 346, n), rng.integers(0, 260, n), rng.choice([-1, 1], n)
    gt = rng.integers(0, 255, (m, 260, 346, 3), dtype=np.uint8)
    c2w = write_their_folder(tmp_path / "lego", rng, m, t, x, y, p, rgb=gt)
    scene = load_eventnerf(tmp_path / "lego")
    cfg = scene.config
    assert (cfg.kind, cfg.loop, cfg.bayer, cfg.pos_threshold) == ("synthetic", False, "rggb", 0.25)
    assert (cfg.width, cfg.height, cfg.n_views, cfg.name) == (346, 260, m, "lego")
    assert (cfg.intrinsics.fx, cfg.intrinsics.cy, cfg.intrinsics.k1) == (280.0, 131.5, 0.0)
    np.testing.assert_array_equal(scene.poses[0], np.arange(m) * 1000)  # view i at i ms
    np.testing.assert_allclose(scene.poses[1], c2w, atol=1e-12)
    np.testing.assert_array_equal(scene.events.t, t * 1000 + 1)
    assert (tmp_path / "lego" / "poses.npz").exists() is False  # nothing written there
    idx = EventIndex(scene.events, 1.0, t_start=cfg.t_start_us, t_end=cfg.t_end_us, loop=False)
    T = scene.poses[0]
    for i, w in [(5, 1), (12, 5), (29, 10), (29, 29), (7, 3)]:
        sel = their_window(t, i, w, m, cycle=False)
        want = np.zeros(346 * 260)
        np.add.at(want, y[sel] * 346 + x[sel], p[sel])
        np.testing.assert_array_equal(idx.accumulate(T[i - w], T[i]).ravel(), want)
    # test views: the test split's real images (not placeholders)
    assert len(scene.test_c2w) == m and scene.test_rgb_paths[0].name == "r_00000.png"
    np.testing.assert_array_equal(iio.imread(scene.test_rgb_paths[3]), gt[3])
    rig = scene.rig()
    np.testing.assert_allclose(rig.pose(T[[3, 7]]), c2w[[3, 7]], atol=1e-12)


def test_their_real_folder_cycles(tmp_path, rng):
    """Float timestamps, distortion row, placeholder images, cycled windows."""
    m, n = 25, 5000
    t = np.sort(rng.random(n) * 7.3)
    x, y, p = rng.integers(0, 346, n), rng.integers(0, 260, n), rng.choice([-1, 1], n)
    write_their_folder(tmp_path / "plant", rng, m, t, x, y, p, k=[-0.12, 0.03, 0, 0])
    scene = load_eventnerf(tmp_path / "plant")
    cfg = scene.config
    assert (cfg.kind, cfg.loop, cfg.pos_threshold) == ("real", True, 0.1)
    assert cfg.background == pytest.approx([159 / 255] * 3)
    intr = cfg.intrinsics
    assert (intr.k1, intr.k2, intr.distortion_model) == (-0.12, 0.03, "eventnerf")
    assert scene.test_c2w is None  # real captures have placeholders only
    np.testing.assert_array_equal(scene.events.t, np.round(t * 1e6).astype(np.int64) + 1)
    idx = EventIndex(scene.events, 1.0, t_start=cfg.t_start_us, t_end=cfg.t_end_us, loop=True)
    T = scene.poses[0]
    for i, w in [(3, 5), (0, 4), (20, 6), (24, 24), (1, 1)]:
        sel = their_window(t, i, w, m, cycle=True)
        sel = sel[t[sel] < t.max()]  # the one documented difference: events at exactly max(t)
        want = np.zeros(346 * 260)
        np.add.at(want, y[sel] * 346 + x[sel], p[sel])
        t0 = T[i - w] if i - w >= 0 else T[i - w + m - 1] - (T[-1] - T[0])
        np.testing.assert_array_equal(idx.accumulate(t0, T[i]).ravel(), want)


def test_their_folder_problems(tmp_path, rng):
    n = 100
    args = (
        np.sort(rng.integers(0, 10, n)),
        rng.integers(0, 346, n),
        rng.integers(0, 260, n),
        rng.choice([-1, 1], n),
    )
    root = tmp_path / "s"
    write_their_folder(root, rng, 10, *args)
    load_eventnerf(root)
    bad = root / "train" / "intrinsics" / "r_00004.txt"
    bad.write_text("300 0 173\n0 300 130\n0 0 1\n")
    one_line_error(load_eventnerf, root, match=f"{bad}: expected a 4x4 or 5x4 matrix")
    bad.write_text("300 0 173 0\n0 300 130 0\n0 0 1 0\n0 0 0 1\n")
    one_line_error(load_eventnerf, root, match="r_00004.txt: intrinsics differ from r_00000.txt")
    bad.unlink()
    one_line_error(load_eventnerf, root, match="pose/r_00004.txt has no intrinsics/r_00004.*")
    shutil.copy(root / "train" / "intrinsics" / "r_00000.txt", bad)
    (root / "train" / "rgb" / "r_00002.png").unlink()
    one_line_error(load_eventnerf, root, match="pose/r_00002.txt has no rgb/r_00002.*")
    shutil.copy(root / "train" / "rgb" / "r_00000.png", root / "train" / "rgb" / "r_00002.jpg")
    load_eventnerf(root)  # matched by stem, whatever the image format
    shutil.copy(root / "train" / "rgb" / "r_00000.png", root / "train" / "rgb" / "r_00002.png")
    one_line_error(load_eventnerf, root, match="two files for view r_00002")
    (root / "train" / "rgb" / "r_00002.jpg").unlink()
    (root / "train" / "pose" / "r_00007.txt").unlink()  # only the pose: the others are extra
    one_line_error(load_eventnerf, root, match="intrinsics/r_00007.txt has no pose/r_00007.txt")
    shutil.copy(root / "train" / "pose" / "r_00000.txt", root / "train" / "pose" / "r_00007.txt")
    pose = root / "train" / "pose" / "r_00001.txt"
    pose.write_text("1 0 0 0\n0 1 0 0\n0 0 -1 0\n0 0 0 1\n")  # a reflection
    one_line_error(load_eventnerf, root, match="r_00001.txt: not a rigid camera-to-world")
    pose.write_text("1 0 0 0\n0 1 0 0\n0 0 1 nan\n0 0 0 1\n")
    one_line_error(load_eventnerf, root, match="r_00001.txt: contains NaN")
    shutil.copy(root / "train" / "pose" / "r_00000.txt", pose)
    np.savez(root / "train" / "events" / "other.npz", x=[0], y=[0], t=[0], p=[1])
    one_line_error(load_eventnerf, root, match="exactly one .npz events file, found 2")
    (root / "train" / "events" / "other.npz").unlink()
    np.savez(root / "train" / "events" / "out.npz", x=[0, 400], y=[0, 0], t=[0, 9], p=[1, 1])
    one_line_error(load_eventnerf, root, match="out.npz: x=400 at event 1 is outside")
    one_line_error(load_eventnerf, tmp_path, match="no 'train' folder")


def test_their_folder_with_a_view_removed_keeps_the_view_times(tmp_path, rng):
    """A whole view deleted (pose, intrinsics, rgb): the others keep their times by number,
    the gap is named in a warning, and the time unit is still the frame index."""
    m, n = 20, 3000
    t = np.sort(rng.integers(0, m, n))
    t[-1] = m - 1
    x, y, p = rng.integers(0, 346, n), rng.integers(0, 260, n), rng.choice([-1, 1], n)
    c2w = write_their_folder(tmp_path / "s", rng, m, t, x, y, p)
    for sub, ext in (("pose", "txt"), ("intrinsics", "txt"), ("rgb", "png")):
        (tmp_path / "s" / "train" / sub / f"r_00007.{ext}").unlink()
    with pytest.warns(UserWarning, match=r"1 view\(s\) missing .*: r_00007; the other views"):
        scene = load_eventnerf(tmp_path / "s", test_split=None)
    keep = np.delete(np.arange(m), 7)
    np.testing.assert_array_equal(scene.poses[0], keep * 1000)  # not respaced over 19 views
    np.testing.assert_allclose(scene.poses[1], c2w[keep], atol=1e-12)
    assert scene.config.n_views == m and scene.config.kind == "synthetic"


def test_their_folder_with_misordered_view_numbers(tmp_path, rng):
    m, n = 6, 500
    t = np.sort(rng.integers(0, m, n))
    t[-1] = m - 1
    x, y, p = rng.integers(0, 346, n), rng.integers(0, 260, n), rng.choice([-1, 1], n)
    write_their_folder(tmp_path / "s", rng, m, t, x, y, p)
    for sub, ext in (("pose", "txt"), ("intrinsics", "txt"), ("rgb", "png")):
        src = tmp_path / "s" / "train" / sub / f"r_00005.{ext}"
        src.rename(src.with_name(f"r_9.{ext}"))
        src = tmp_path / "s" / "train" / sub / f"r_00004.{ext}"
        src.rename(src.with_name(f"r_10.{ext}"))  # name order: ..., r_00003, r_10, r_9 (10 > 9)
    msg = "not in file-name order (r_10.txt sorts before r_9.txt)"
    one_line_error(load_eventnerf, tmp_path / "s", match=msg)


def make_scene(
    tmp_path,
    random_stream,
    scene_config,
    test_views,
    *,
    intr=None,
    t_start=0,
    timed=False,
    n_test=5,
) -> Scene:
    cfg = scene_config(
        t_start_us=t_start, t_end_us=t_start + 1_000_000, **({"intrinsics": intr} if intr else {})
    )
    cfg.trajectory.t0_us = t_start
    poses = None
    if timed:
        poses = timed_poses(cfg, 60)
        cfg.trajectory = TrajectoryConfig(kind="timed", poses_file="poses.npz")
    ev = random_stream(
        n=30_000, width=346, height=260, t_max=t_start + 1_000_000, t_min=t_start + 1
    )
    tt, tc, rgb = test_views(cfg, n_test) if n_test else (None, None, None)
    save_scene(tmp_path / "native", cfg, ev, tt, tc, rgb, poses=poses)
    return load_scene(tmp_path / "native")


@pytest.mark.parametrize("timed,t_start", [(False, 0), (True, 250_000)])
def test_native_to_eventnerf_round_trip(
    tmp_path, random_stream, scene_config, test_views, timed, t_start
):
    intr = IntrinsicsConfig(300.0, 302.0, 172.5, 129.0, -0.25, 0.07, "eventnerf")
    scene = make_scene(
        tmp_path, random_stream, scene_config, test_views, intr=intr, t_start=t_start, timed=timed
    )
    out = export_eventnerf(scene, tmp_path / "en", n_views=80)
    assert sorted(p.name for p in out.iterdir()) == [
        "fastenerf_scene.json",
        "test",
        "train",
        "validation",
    ]
    assert len(list((out / "train" / "rgb").glob("*.png"))) == 80
    back = load_eventnerf(out)
    assert_same_events(back.events, scene.events)
    assert back.config.intrinsics == scene.config.intrinsics
    for k in ("loop", "kind", "pos_threshold", "bayer", "t_start_us", "t_end_us", "name"):
        assert getattr(back.config, k) == getattr(scene.config, k), k
    t, c2w = back.poses
    assert len(t) == 80 and t[0] == t_start
    np.testing.assert_allclose(c2w, scene.rig().pose(t), atol=1e-5)
    np.testing.assert_array_equal(back.test_t, scene.test_t)
    np.testing.assert_allclose(back.test_c2w, scene.test_c2w, atol=1e-12)
    np.testing.assert_array_equal(back.load_test_images(), scene.load_test_images())
    # their loader reads the files alone: the 5th row holds k1 k2, the poses are 4x4
    k = np.loadtxt(out / "train" / "intrinsics" / "r_00000.txt")
    np.testing.assert_allclose(k[4], [-0.25, 0.07, 0, 0])
    np.testing.assert_allclose(k[:3, :3], [[300, 0, 172.5], [0, 302, 129], [0, 0, 1]])
    # the written poses: the same rotations, centres in the unit-sphere frame of the record
    norm = json.loads((out / "fastenerf_scene.json").read_text())["normalisation"]
    written = np.loadtxt(out / "train" / "pose" / "r_00011.txt")
    np.testing.assert_allclose(written[:3, :3], c2w[11][:3, :3], atol=1e-15)
    np.testing.assert_allclose(
        written[:3, 3], norm["scale"] * (c2w[11][:3, 3] - norm["center"]), atol=1e-15
    )
    # and without our record: the folder alone gives the same events (shifted to start at 0)
    (out / "fastenerf_scene.json").unlink()
    bare = load_eventnerf(out)
    np.testing.assert_array_equal(bare.events.t, scene.events.t - t_start)
    assert bare.config.intrinsics == scene.config.intrinsics
    assert bare.config.kind == "real" and bare.test_c2w is None  # float t: real, no auto GT
    named = load_eventnerf(out, test_split="test")  # in the written (unit-sphere) frame
    np.testing.assert_allclose(named.test_c2w[:, :3, :3], scene.test_c2w[:, :3, :3], atol=1e-12)
    np.testing.assert_allclose(
        named.test_c2w[:, :3, 3],
        norm["scale"] * (scene.test_c2w[:, :3, 3] - norm["center"]),
        atol=1e-12,
    )


@pytest.mark.parametrize("cylinder", [False, True])
def test_export_puts_cameras_and_object_in_the_unit_sphere(
    tmp_path, random_stream, scene_config, test_views, cylinder
):
    """Their trainer (NeRF++) refuses rays whose line passes outside the unit sphere: every
    written camera centre, in every split, must lie inside it, and so must the object's box.
    The record's similarity maps it back: poses, box and clip restored."""
    from fastenerf.config import CylinderConfig

    cyl = CylinderConfig(radius=0.25, y_min=-0.14, y_max=0.195) if cylinder else None
    cfg = scene_config(aabb=[-0.4, -0.3, -0.2, 0.6, 0.5, 0.4], cylinder=cyl)
    assert np.linalg.norm(Turntable(cfg.trajectory)(np.array([0]))[0, :3, 3]) > 2
    tt, tc, rgb = test_views(cfg, 4)
    ev = random_stream(n=20_000, width=346, height=260, t_max=1_000_000)
    save_scene(tmp_path / "native", cfg, ev, tt, tc, rgb)
    scene = load_scene(tmp_path / "native")
    out = export_eventnerf(scene, tmp_path / "en", n_views=40)
    centres = np.stack([np.loadtxt(p)[:3, 3] for p in out.glob("*/pose/*.txt")])
    assert len(centres) == 40 + 2 * 4 and np.linalg.norm(centres, axis=1).max() < 1.0
    meta = json.loads((out / "fastenerf_scene.json").read_text())
    norm = meta["normalisation"]
    box = np.asarray(norm["aabb"])
    corners = np.stack(np.meshgrid(*zip(box[:3], box[3:], strict=True), indexing="ij"), -1).reshape(
        -1, 3
    )
    assert np.linalg.norm(corners, axis=1).max() < 1.0
    # the farthest of cameras and box sits at 0.9: the frame uses the sphere, not a corner of it
    far = max(np.linalg.norm(centres, axis=1).max(), np.linalg.norm(corners, axis=1).max())
    assert far == pytest.approx(0.9, abs=1e-9)
    if cylinder:  # the clip in their frame: a cylinder about the y axis, scaled
        s, c = norm["scale"], norm["center"]
        assert c[0] == c[2] == 0.0
        assert norm["cylinder"] == pytest.approx([0.25 * s, (-0.14 - c[1]) * s, (0.195 - c[1]) * s])
    # their intersect_sphere: every pixel ray's closest point to the origin inside the sphere
    K = np.loadtxt(out / "train" / "intrinsics" / "r_00000.txt")[:3, :3]
    pose = np.loadtxt(out / "train" / "pose" / "r_00007.txt")
    u, v = np.meshgrid(np.arange(0, 346, 7) + 0.5, np.arange(0, 260, 7) + 0.5)
    d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    d = d.reshape(-1, 3) @ pose[:3, :3].T
    o = pose[:3, 3]
    p = o - ((d @ o) / (d * d).sum(1))[:, None] * d
    assert (p * p).sum(1).max() < 1.0
    # the round trip gives back our world
    back = load_eventnerf(out)
    t, c2w = back.poses
    np.testing.assert_allclose(c2w, scene.rig().pose(t), atol=1e-5)  # views at whole µs
    np.testing.assert_allclose(back.test_c2w, scene.test_c2w, atol=1e-12)
    assert back.config.aabb == cfg.aabb and back.config.cylinder == cfg.cylinder
    assert back.config.near == cfg.near
    # a damaged record is one line naming the file
    meta["normalisation"]["scale"] = -1.0
    (out / "fastenerf_scene.json").write_text(json.dumps(meta))
    one_line_error(load_eventnerf, out, match="fastenerf_scene.json|positive scale")


def test_export_converts_opencv_distortion(tmp_path, random_stream, scene_config, test_views):
    intr = IntrinsicsConfig(300.0, 300.0, 173.0, 130.0, -0.1, 0.02, "opencv")
    scene = make_scene(tmp_path, random_stream, scene_config, test_views, intr=intr, n_test=0)
    out = export_eventnerf(scene, tmp_path / "en", n_views=30)
    meta = json.loads((out / "fastenerf_scene.json").read_text())
    assert meta["distortion_fit_max_px"] < 0.05
    assert load_eventnerf(out).config.intrinsics == intr  # restored from our record
    (out / "fastenerf_scene.json").unlink()
    bare = load_eventnerf(out)
    assert bare.config.intrinsics.distortion_model == "eventnerf"
    assert bare.test_c2w is None  # the placeholders are not ground truth
    a = Intrinsics.from_config(intr, 346, 260)
    b = Intrinsics.from_config(bare.config.intrinsics, 346, 260)
    u, v = np.meshgrid(np.arange(0, 346, 5) + 0.5, np.arange(0, 260, 5) + 0.5)
    rays = a.pixel_to_camera(u.ravel(), v.ravel())
    assert np.abs(b.project(rays) - a.project(rays)).max() < meta["distortion_fit_max_px"] + 1e-6


def test_export_refusals_and_atomic_replace(tmp_path, random_stream, scene_config, test_views):
    scene = make_scene(tmp_path, random_stream, scene_config, test_views, n_test=0)
    out = export_eventnerf(scene, tmp_path / "en", n_views=10)
    (out / "train" / "stale.txt").write_text("old")
    export_eventnerf(scene, out, n_views=12)
    assert not (out / "train" / "stale.txt").exists()
    assert len(list((out / "train" / "pose").iterdir())) == 12
    assert len(list((out / "validation" / "pose").iterdir())) == 3  # >= 3 for their logging
    one_line_error(export_eventnerf, scene, tmp_path / "x", n_views=2, match="at least 3 views")
    assert not (tmp_path / "x").exists()


def test_export_of_another_sensor_size(tmp_path, random_stream, scene_config):
    cfg = scene_config(32, 24)
    scene = Scene(tmp_path, cfg, random_stream(n=3000, width=32, height=24, t_max=10**6))
    one_line_error(
        export_eventnerf, scene, tmp_path / "x", strict_sensor=True, match="not the 346x260"
    )
    assert not (tmp_path / "x").exists()
    with pytest.warns(UserWarning, match="their code cannot read"):
        out = export_eventnerf(scene, tmp_path / "x", n_views=20)
    back = load_eventnerf(out)
    assert (back.config.width, back.config.height) == (32, 24)
    assert_same_events(back.events, scene.events)


# ---------------------------------------------------------------------------- text files


def write_lines(path: Path, lines) -> Path:
    path.write_text("\n".join(lines) + "\n")
    return path


def test_txt_both_column_orders(tmp_path, random_stream):
    ev = random_stream(n=300, width=40, height=30, t_max=2_000_000)
    rows = list(zip(ev.t, ev.x, ev.y, ev.p, strict=True))
    ecd = write_lines(
        tmp_path / "ecd.txt",
        ["# t x y p, seconds"] + [f"{t * 1e-6:.6f} {x} {y} {int(p > 0)}" for t, x, y, p in rows],
    )
    got = read_txt(ecd, 40, 30)
    assert_same_events(got, ev)
    xytp = write_lines(
        tmp_path / "xytp.txt", ["40 30"] + [f"{x} {y} {t} {p}" for t, x, y, p in rows]
    )
    assert_same_events(read_txt(xytp), ev)  # order, unit and sensor all from the file
    assert_same_events(read_txt(xytp, order="xytp"), ev)
    ms = write_lines(tmp_path / "ms.txt", [f"{t} {x} {y} {p}" for t, x, y, p in rows])
    got = read_txt(ms, 40, 30, time_unit="ms")
    np.testing.assert_array_equal(got.t, ev.t * 1000)
    inferred = read_txt(ms)
    assert (inferred.width, inferred.height) == (ev.x.max() + 1, ev.y.max() + 1)


def test_txt_malformed_lines_name_the_line(tmp_path):
    good = ["346 260", "# comment", "0.000100 5 6 1", "", "0.000200 7 8 0"]
    path = tmp_path / "e.txt"
    write_lines(path, good + ["0.000300 9 1"])
    one_line_error(read_txt, path, match=f"{path}: line 6: expected 4 columns|found 3")
    write_lines(path, good + ["0.000300 9 x 1"])
    one_line_error(read_txt, path, match="line 6: 'x' is not a number")
    write_lines(path, good + ["0.000100 9 9 1"])
    one_line_error(read_txt, path, match="line 6|not sorted")
    write_lines(path, good + ["0.000300 400 9 1"])
    one_line_error(read_txt, path, order="txyp", match="line 6|x=400|outside the 346x260")
    write_lines(path, good + ["0.000300 9 9 3"])
    one_line_error(read_txt, path, match="line 6|polarity 3")
    write_lines(path, ["346 260", "# nothing"])
    one_line_error(read_txt, path, match="no events")
    write_lines(path, ["5 6 100 1"])
    one_line_error(read_txt, path, match="pass order=")
    one_line_error(read_txt, tmp_path / "none.txt", match="file not found")


# ---------------------------------------------------------------------------- dispatch, info


def test_load_any(tmp_path, random_stream, scene_config, test_views):
    scene = make_scene(tmp_path, random_stream, scene_config, test_views, n_test=0)
    assert isinstance(load_any(tmp_path / "native"), Scene)
    out = export_eventnerf(scene, tmp_path / "en", n_views=10)
    assert isinstance(load_any(out), Scene)
    their = load_any(out / "train" / "events" / "events.npz")  # float seconds, no size
    assert isinstance(their, EventStream) and their.width == scene.events.x.max() + 1
    np.testing.assert_array_equal(their.t, scene.events.t - 1)
    native = load_any(tmp_path / "native" / "events.npz")  # size stored by write_events
    assert_same_events(native, scene.events)
    one_line_error(load_any, tmp_path / "missing", match="no such file or folder")
    one_line_error(load_any, tmp_path, match="not a scene folder")
    (tmp_path / "e.csv").write_text("1,2,3,4\n")
    one_line_error(load_any, tmp_path / "e.csv", match="unknown events format")


def test_load_any_aedat4():
    if not AEDAT.exists():
        pytest.skip("shared AEDAT4 recordings not present")
    try:
        import fastenerf.data.formats.aedat  # noqa: F401
    except ImportError:
        one_line_error(load_any, AEDAT, match="AEDAT4 reader|not available yet")
        return
    ev = load_any(AEDAT)
    assert isinstance(ev, EventStream) and len(ev) > 0


def test_info_on_a_good_folder(tmp_path, random_stream, scene_config, test_views, capsys):
    scene = make_scene(tmp_path, random_stream, scene_config, test_views, timed=True)
    assert main(["info", str(tmp_path / "native")]) == 0
    out = capsys.readouterr().out
    for words in (
        "events         30,000",
        "sensor         346x260, bayer rggb",
        "poses          60 timed",
        "test views     5 (5 with ground-truth images)",
        "active pixels",
        "busiest pixel",
        "polarity",
        "rate",
        "aabb [-1.0, -1.0, -1.0, 1.0, 1.0, 1.0]",
    ):
        assert words in out, (words, out)
    assert main(["info", "--json", str(tmp_path / "native")]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["events"]["count"] == 30_000 and d["trajectory"]["poses"] == 60
    assert d["events"]["positive"] + d["events"]["negative"] == 30_000
    export_eventnerf(scene, tmp_path / "en", n_views=20)
    assert main(["info", str(tmp_path / "en")]) == 0
    assert "EventNeRF scene folder" in capsys.readouterr().out
    assert main(["info", "--sensor", "400x300", str(tmp_path / "native" / "events.npz")]) == 0
    assert "400x300" in capsys.readouterr().out


def test_info_on_bad_input_is_one_line_and_exit_2(tmp_path, random_stream, scene_config, capsys):
    save_scene(tmp_path / "s", scene_config(16, 12), random_stream())
    truncate(tmp_path / "s" / "events.npz")
    cases = [tmp_path / "s", tmp_path / "nothing", tmp_path]
    d = scene_config(16, 12).to_dict()
    del d["trajectory"]
    (tmp_path / "j").mkdir()
    (tmp_path / "j" / "scene.json").write_text(json.dumps(d))
    cases.append(tmp_path / "j")
    for path in cases:
        assert main(["info", str(path)]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "Traceback" not in err and str(path) in err, err
    assert main(["info", "--sensor", "big", str(tmp_path)]) == 2
    assert "--sensor" in capsys.readouterr().err


def test_poses_file_helpers(tmp_path):
    t = np.array([0, 10, 20])
    c2w = Turntable(TrajectoryConfig())(t)
    save_poses(tmp_path / "p.npz", t, c2w)
    t2, c2 = load_poses(tmp_path / "p.npz")
    np.testing.assert_array_equal(t2, t)
    np.testing.assert_array_equal(c2, c2w)
    TimedPoses(t2, c2)
