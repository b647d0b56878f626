"""Viewer: camera maths, exposure, auto resolution, the GL path (EGL) and a real window (Xvfb)."""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from fastenerf.data.rig import Intrinsics, look_at
from fastenerf.fields.base import Field
from fastenerf.render import render_image
from fastenerf.viewer.autoscale import AutoScale
from fastenerf.viewer.camera import (
    OrbitCamera,
    intrinsics_for_fov,
    load_camera_path,
    save_camera_path,
    scene_up,
)
from fastenerf.viewer.tonemap import Exposure, apply_exposure, invert_exposure

TESTS = Path(__file__).parent


class SphereField(Field):
    """An analytic field for viewer tests: a dense ball of radius `r` whose colour varies
    with position; rendered by uniform sampling inside the box, composited front to back."""

    backend = "sphere"

    def __init__(self, r: float = 0.6, sigma: float = 40.0, n_samples: int = 48):
        super().__init__()
        self.r, self.sigma, self.n = r, sigma, n_samples
        self.register_buffer("aabb", torch.tensor([-1.0, -1.0, -1.0, 1.0, 1.0, 1.0]))

    def density(self, x):
        return self.sigma * torch.sigmoid((self.r - x.norm(dim=-1)) * 40.0)

    def color(self, x, d):
        return (0.5 + 0.45 * torch.tanh(2.0 * x)).clamp(0, 1)

    def render(self, rays_o, rays_d, *, near, background, train):
        inv = 1.0 / torch.where(rays_d.abs() < 1e-9, torch.full_like(rays_d, 1e-9), rays_d)
        t0, t1 = (self.aabb[:3] - rays_o) * inv, (self.aabb[3:] - rays_o) * inv
        tn = torch.minimum(t0, t1).amax(-1).clamp_min(near)
        tf = torch.maximum(t0, t1).amin(-1).clamp_min(tn)
        u = (torch.arange(self.n, dtype=torch.float32, device=rays_o.device) + 0.5) / self.n
        t = tn[:, None] + (tf - tn)[:, None] * u  # (R, S)
        delta = ((tf - tn) / self.n)[:, None].expand_as(t)
        x = rays_o[:, None] + t[..., None] * rays_d[:, None]
        sigma = self.density(x.reshape(-1, 3)).reshape(t.shape)
        rgb = self.color(x.reshape(-1, 3), None).reshape(*t.shape, 3)
        alpha = -torch.expm1(-sigma * delta)
        trans = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1 - alpha[:, :-1]], 1), 1)
        w = alpha * trans
        out_rgb = (w[..., None] * rgb).sum(1)
        acc = w.sum(1)
        if background is not None:
            out_rgb = out_rgb + (1 - acc)[:, None] * background
        return {"rgb": out_rgb, "depth": (w * t).sum(1), "opacity": acc}

    def config_dict(self):
        return {"r": self.r, "sigma": self.sigma, "n_samples": self.n}


# ---- camera ---------------------------------------------------------------------------------


def _cam(up=(0.0, 1.0, 0.0)):
    up = np.asarray(up, float) / np.linalg.norm(up)
    # a start position that is not in the plane of any axis
    return OrbitCamera.looking_at(np.array([0.7, 0.9, 3.1]) + 0.2, [0.2, 0.1, -0.1], up)


@pytest.mark.parametrize("up", [(0, 1, 0), (0, math.cos(0.3), math.sin(0.3))])
def test_orbit_keeps_target_distance_and_level(up):
    cam = _cam(up)
    target, dist = cam.target.copy(), cam.distance
    rng = np.random.default_rng(0)
    for yaw, pitch in rng.uniform(-0.7, 0.7, (50, 2)):
        cam.orbit(yaw, pitch)
        np.testing.assert_allclose(cam.target, target, atol=1e-9)
        assert abs(np.linalg.norm(cam.eye - target) - dist) < 1e-9
        R = cam.c2w[:3, :3]
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
        assert abs(R[:, 0] @ cam.up) < 1e-9  # image x stays level: no roll about the view
        assert R[:, 1] @ cam.up < 0  # image y (down) points against up: never upside down
    # pitch stops short of the pole, the target still fixed
    cam.orbit(0.0, 10.0)
    assert -cam.forward @ cam.up < 1.0 - 1e-5
    np.testing.assert_allclose(cam.target, target, atol=1e-9)


def test_orbit_directions():
    cam = OrbitCamera.looking_at([0, 0, 3], [0, 0, 0])
    cam.orbit(0.0, 0.3)  # positive pitch lifts the eye: it looks down
    assert cam.eye[1] > 0 and cam.forward[1] < 0
    cam = OrbitCamera.looking_at([0, 0, 3], [0, 0, 0])
    cam.orbit(math.pi / 2, 0.0)  # a quarter turn about +y takes the eye from +z to +x
    np.testing.assert_allclose(cam.eye, [3, 0, 0], atol=1e-9)


def test_pan_moves_eye_and_target_together():
    cam = _cam()
    eye, target, R, dist = cam.eye, cam.target, cam.c2w[:3, :3].copy(), cam.distance
    cam.pan(0.1, -0.05)
    shift = cam.eye - eye
    np.testing.assert_allclose(cam.target - target, shift, atol=1e-12)
    np.testing.assert_allclose(cam.c2w[:3, :3], R)
    assert cam.distance == dist
    np.testing.assert_allclose(shift, -dist * (0.1 * R[:, 0] - 0.05 * R[:, 1]), atol=1e-12)
    assert abs(shift @ R[:, 2]) < 1e-12  # in the image plane


def test_zoom_changes_distance_only():
    cam = _cam()
    target, R, dist = cam.target, cam.c2w[:3, :3].copy(), cam.distance
    cam.zoom(0.5)
    assert cam.distance == pytest.approx(dist * 0.5)
    np.testing.assert_allclose(cam.target, target, atol=1e-12)
    np.testing.assert_allclose(cam.c2w[:3, :3], R)
    np.testing.assert_allclose(np.linalg.norm(cam.eye - target), dist * 0.5)
    cam.zoom(1e-9)  # never through the target
    assert cam.distance > 0 and np.all(np.isfinite(cam.c2w))


def test_reset_and_scene_up():
    cam = _cam()
    home = cam.c2w.copy()
    cam.orbit(0.4, 0.2)
    cam.pan(0.3, 0.1)
    cam.zoom(2.0)
    cam.reset()
    np.testing.assert_array_equal(cam.c2w, home)

    from fastenerf.config import IntrinsicsConfig, SceneConfig, TrajectoryConfig
    from fastenerf.data.rig import Turntable

    tr = TrajectoryConfig(kind="turntable", radius=2.0, tilt_deg=25.0, elevation_deg=10.0)
    cfg = SceneConfig("t", 32, 24, IntrinsicsConfig(30, 30, 16, 12), tr)
    up = scene_up(cfg)
    # the turntable's cameras circle in the plane orthogonal to the tilted up axis
    eyes = Turntable(tr)(np.linspace(0, 1e6, 7))[:, :3, 3]
    assert np.ptp(eyes @ up) < 1e-9
    # orbiting about that axis from a turntable pose stays on the turntable's circle
    cam = OrbitCamera(Turntable(tr)(0)[0], 2.0, up)
    cam.set_pose(Turntable(tr)(0)[0], np.zeros(3))
    cam.orbit(1.0, 0.0)
    assert abs(cam.eye @ up - eyes[0] @ up) < 1e-9
    assert abs(np.linalg.norm(cam.eye) - 2.0) < 1e-9


def test_snap_gives_the_pose_exactly():
    poses = look_at(
        np.array([[0, 0, 3.0], [3, 0, 0], [0, 0, -3], [-3, 0.5, 0]]), np.zeros((4, 3)), [0, 1, 0]
    )
    # a pose with roll: snapping must reproduce it exactly anyway
    roll = np.eye(4)
    c, s = math.cos(0.2), math.sin(0.2)
    roll[:2, :2] = [[c, -s], [s, c]]
    poses[1] = poses[1] @ roll
    cam = OrbitCamera.looking_at([2.5, 0.3, 0.4], [0, 0, 0])
    assert cam.snap(poses, pivot=np.zeros(3)) == 1
    np.testing.assert_array_equal(cam.c2w, poses[1])
    np.testing.assert_allclose(cam.target, [0, 0, 0], atol=1e-9)
    cam.orbit(0.1, 0.0)
    np.testing.assert_allclose(cam.target, [0, 0, 0], atol=1e-9)

    f = SphereField()
    intr = Intrinsics(40, 40, 24, 16, 48, 32)
    ref = render_image(f, poses[1], intr, near=1e-4, background=None)
    cam.snap(poses, pivot=np.zeros(3))
    got = render_image(f, cam.c2w, intr, near=1e-4, background=None)
    assert torch.equal(got["rgb"], ref["rgb"])


def test_camera_path_roundtrip(tmp_path):
    frames = [
        (
            look_at(np.array([0, 0, 3.0 + i]), np.zeros(3), [0, 1, 0])[0],
            intrinsics_for_fov(64, 48, 40 + i),
        )
        for i in range(3)
    ]
    p = save_camera_path(tmp_path / "p.json", frames, fps=24)
    back = load_camera_path(p)
    assert len(back) == 3
    for (c, k), (c2, k2) in zip(frames, back, strict=True):
        np.testing.assert_array_equal(c, c2)
        assert k == k2
    (tmp_path / "one.json").write_text(json.dumps(frames[0][0].tolist()))
    assert load_camera_path(tmp_path / "one.json")[0][1] is None
    from fastenerf.errors import InputError

    (tmp_path / "bad.json").write_text(json.dumps([[1, 2], [3, 4]]))
    with pytest.raises(InputError, match="bad.json"):
        load_camera_path(tmp_path / "bad.json")


# ---- exposure and resolution ------------------------------------------------------------------


def test_exposure_identity_monotone_invertible():
    c = torch.linspace(0.0, 1.0, 1001)[:, None].expand(-1, 3)
    assert torch.allclose(apply_exposure(c, Exposure()), c)
    for e in (
        Exposure(ev=1.0),
        Exposure(ev=-2.0, gain=0.7),
        Exposure(gain=1.6, gamma=1.8),
        Exposure(ev=0.5, gain=0.5, gamma=0.6),
    ):
        out = apply_exposure(c, e)
        assert torch.all(out[1:] >= out[:-1])  # monotone
        inside = (out > 1e-3) & (out < 1 - 1e-3)
        assert torch.all(out[1:][inside[1:]] > out[:-1][inside[1:]])  # strictly, where unclipped
        back = invert_exposure(out, e)
        assert torch.allclose(back[inside], c[inside], atol=1e-4)
    # +1 EV doubles linear intensity (display value ** 2.2) where nothing clips
    c = torch.tensor([[0.1, 0.3, 0.5]])
    lin = apply_exposure(c, Exposure(ev=1.0, eps=1e-8)) ** 2.2
    assert torch.allclose(lin, 2 * c**2.2, rtol=1e-4)


def test_autoscale_drops_when_slow_and_recovers_when_still():
    a = AutoScale(target_fps=30.0)
    budget = a.budget_s
    s = a.update(None, moving=True)
    assert s == 0.25  # a cautious start, before any frame was timed
    a.scale = a.moving_scale = 1.0
    for _ in range(20):  # frames cost 16x the budget at full scale: cost ∝ scale²
        s = a.update(16 * budget * a.scale**2, moving=True)
    assert 0.2 < s < 0.3  # ≈ 1/4 holds the budget
    assert a.update(16 * budget * a.scale**2, moving=False) == 1.0  # still: full quality
    s2 = a.update(16 * budget, moving=True)  # remembers what held the rate
    assert abs(s2 - s) < 0.05
    for _ in range(30):  # cheap frames: back up to full scale while moving
        s2 = a.update(0.1 * budget * a.scale**2, moving=True)
    assert s2 == 1.0
    for _ in range(50):  # hopelessly slow: clamp at min_scale
        s2 = a.update(1e3, moving=True)
    assert s2 == a.min_scale


# ---- the GL path -------------------------------------------------------------------------------


def _scene_cfg(width=64, height=48):
    from fastenerf.config import IntrinsicsConfig, SceneConfig, TrajectoryConfig

    tr = TrajectoryConfig(kind="turntable", radius=2.6, elevation_deg=20.0, tilt_deg=10.0)
    f = 0.9 * width
    return SceneConfig(
        "sphere",
        width,
        height,
        IntrinsicsConfig(f, f, width / 2, height / 2),
        tr,
        n_views=36,
        background=None,
    )


def _egl_or_skip():
    from fastenerf.viewer.blit import headless_context

    try:
        return headless_context()
    except Exception as e:  # pragma: no cover - depends on the machine's GL
        pytest.skip(f"no EGL context on this machine ({e})")


@pytest.mark.parametrize("mode", ["rgb", "depth"])
def test_snapshot_matches_render_image(mode):
    from fastenerf.viewer.blit import snapshot
    from fastenerf.viewer.frame import ViewSettings
    from fastenerf.viewer.source import ViewSource

    ctx = _egl_or_skip()
    f = SphereField()
    src = ViewSource.from_field(f, _scene_cfg(61, 47))  # odd sizes: rows not 4-byte aligned
    c2w, intr = src.views[5], src.intrinsics
    s = ViewSettings(mode=mode, near=src.near)
    got = snapshot(f, c2w, intr, s, ctx=ctx)
    ref = render_image(f, c2w, intr, near=src.near, background=None)
    assert got.shape == (47, 61, 3) and got.dtype == np.uint8
    if mode == "rgb":
        want = ref["rgb"].numpy()
    else:
        from fastenerf.viewer.tonemap import depth_range, depth_to_rgb

        want = depth_to_rgb(
            ref["depth"], ref["opacity"], *depth_range(ref["depth"], ref["opacity"])
        ).numpy()
    assert np.abs(got / 255.0 - want).max() <= 0.5 / 255 + 1e-6  # 8-bit rounding only
    assert got.std() > 10  # an image, not a blank
    ctx.release()


def test_occupancy_mode_hits_the_ball():
    from fastenerf.viewer.frame import ViewSettings, render_raw, shade

    f = SphereField()
    c2w = look_at(np.array([0, 0, 3.0]), np.zeros(3), [0, 1, 0])[0]
    intr = intrinsics_for_fov(40, 30, 40.0)
    raw = render_raw(f, c2w, intr, ViewSettings(mode="occupancy"))
    hit = raw["opacity"] > 0
    assert hit[15, 20] and not hit[0, 0]
    # the first occupied sample is where the density test (1% alpha over a 1/128 cell)
    # starts to pass along the axis, to within the half-cell marching step
    cell = 2.0 / 128
    z = torch.linspace(1.0, 0.0, 100001)
    occ = f.density(torch.stack([torch.zeros_like(z), torch.zeros_like(z), z], -1)) * cell > 0.01
    r_occ = float(z[occ.nonzero()[0, 0]])
    assert abs(float(raw["depth"][15, 20]) - (3.0 - r_occ)) <= cell / 2 + 1e-4
    img = shade(raw, ViewSettings(mode="occupancy"))
    assert img.shape == (30, 40, 3) and img[15, 20].sum() > 0 and img[0, 0].sum() == 0


def _start_xvfb():
    """Start Xvfb on a display number it picks itself; (process, ':N') or skip."""
    exe = shutil.which("Xvfb")
    if exe is None:
        pytest.skip("Xvfb is not installed (Debian package xvfb): no X server for a window")
    r, w = os.pipe()
    proc = subprocess.Popen(
        [exe, "-displayfd", str(w), "-screen", "0", "1280x1024x24", "-nolisten", "tcp"],
        pass_fds=(w,),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    os.close(w)
    with os.fdopen(r) as fd:
        line = fd.readline().strip()  # Xvfb writes the display number once it is ready
    if not line:
        proc.kill()
        proc.wait()
        pytest.skip("Xvfb did not start: no X server for a window")
    return proc, f":{line}"


WINDOW_SCRIPT = """
import json, sys
sys.path.insert(0, {tests!r})
from test_viewer import SphereField, _scene_cfg
from fastenerf.viewer.app import Viewer
from fastenerf.viewer.source import ViewSource

log = []

class Scripted(Viewer):
    # after the first frame, moves the camera every frame (as a mouse drag does) until a
    # reduced-resolution frame is shown, then holds still until the full-resolution refine
    def _gui(self):
        super()._gui()
        if self.raw is None:
            return
        if not log or log[-1] != self.raw_scale:
            log.append(self.raw_scale)
        if min(log) == 1.0:
            self.cam.orbit(0.02, 0.005)
            self._camera_moved()
        elif log[-1] == 1.0:
            from imgui_bundle import hello_imgui
            hello_imgui.get_runner_params().app_shall_exit = True

src = ViewSource.from_field(SphereField(), _scene_cfg(346, 260))
v = Scripted(src, window_size=(800, 480), window_shot={shot!r})
v.run()
print(json.dumps(log))
"""


def test_window_under_xvfb(tmp_path):
    import imageio.v3 as iio

    proc, display = _start_xvfb()
    try:
        shot = tmp_path / "viewer.png"
        env = dict(os.environ, DISPLAY=display)
        r = subprocess.run(
            [sys.executable, "-c", WINDOW_SCRIPT.format(tests=str(TESTS), shot=str(shot))],
            env=env,
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert r.returncode == 0, r.stderr[-2000:]
    finally:
        proc.kill()
        proc.wait()
    scales = json.loads(r.stdout.strip().splitlines()[-1])
    # the first frame is full resolution; moving drops it (a CPU render of ~450x440 pixels is
    # far over the 33 ms budget); once still it refines back to full resolution
    assert scales[0] == 1.0 and min(scales) < 0.7 and scales[-1] == 1.0, scales
    img = iio.imread(shot)
    assert img.shape[:2] == (480, 800)
    assert img.std() > 10  # not blank
    view = img[40:-40, 360:-40, :3].astype(int)  # the view, right of the panel
    # the ball's colours are in the view: saturated, not just the UI's greys
    assert (np.ptp(view, axis=-1) > 60).mean() > 0.05


def test_screenshot_and_camera_path(tmp_path):
    import imageio.v3 as iio

    from fastenerf.viewer.app import Viewer
    from fastenerf.viewer.source import ViewSource

    src = ViewSource.from_field(SphereField(), _scene_cfg(40, 30), out_dir=tmp_path)
    v = Viewer(src)
    v.snap()
    np.testing.assert_array_equal(v.cam.c2w, src.snap_poses[v.snapped])
    p = v.screenshot(size=(40, 30))
    assert p.parent == tmp_path / "screenshots" and p.suffix == ".png"
    img = iio.imread(p)
    # the snapped view with the scene camera's field of view is the scene camera's image
    ref = render_image(
        src.field, src.snap_poses[v.snapped], src.intrinsics, near=src.near, background=None
    )["rgb"].numpy()
    assert np.abs(img / 255.0 - ref).max() <= 0.5 / 255 + 1e-6
    assert v.screenshot(size=(40, 30)) != p  # never overwrites
    v.recording = True
    for _ in range(4):
        v.cam.orbit(0.1, 0.0)
        v._record()
    frames = load_camera_path(v.save_path())
    assert len(frames) == 4 and frames[-1][1].width > 0
    np.testing.assert_array_equal(frames[-1][0], v.cam.c2w)


def test_view_command_errors_are_one_line(tmp_path, capsys):
    from fastenerf.cli import main

    assert main(["view"]) == 2
    assert main(["view", str(tmp_path / "nope"), "--snapshot", "x.png"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and all(line.startswith("fastenerf view: error:") for line in err)


# ---- live training and runs on disk --------------------------------------------------------------


def _tiny_scene(root: Path) -> Path:
    """A 32x24 turntable scene with random events: enough for real training steps."""
    from fastenerf.data.events import EventStream
    from fastenerf.data.formats.native import save_scene

    cfg = _scene_cfg(32, 24)
    cfg.n_views = 20
    rng = np.random.default_rng(0)
    n = 4000
    ev = EventStream.from_arrays(
        rng.integers(0, 32, n),
        rng.integers(0, 24, n),
        np.sort(rng.integers(0, 1_000_000, n)),
        rng.choice([-1, 1], n),
        width=32,
        height=24,
    )
    return save_scene(root, cfg, ev)


TINY_VANILLA = dict(depth=2, width=32, skip=8, pos_freqs=4, dir_freqs=2, n_coarse=16, n_fine=0)


def test_train_while_viewing_then_view_the_run(tmp_path):
    import imageio.v3 as iio

    from fastenerf.cli import main
    from fastenerf.viewer.frame import ViewSettings, render_raw
    from fastenerf.viewer.source import ViewSource

    scene = _tiny_scene(tmp_path / "scene")
    run = tmp_path / "run"
    src = ViewSource.from_training(
        scene,
        "vanilla",
        out_dir=run,
        steps=100_000,
        rays_per_step=64,
        backend_options=TINY_VANILLA,
        eval_every_s=0.0,
    )
    cam = src.default_camera()
    intr = intrinsics_for_fov(24, 18, 40.0)
    s = ViewSettings(near=src.near, background=src.background)
    first = render_raw(src.field, cam.c2w, intr, s, src.lock)["rgb"].clone()
    src.start_training()
    try:
        t = time.perf_counter()
        while time.perf_counter() - t < 20:  # render under the lock while the trainer steps
            img = render_raw(src.field, cam.c2w, intr, s, src.lock)["rgb"]
            src.poll()
            if src.stats.steps and src.stats.steps[-1] >= 5:
                break
        assert src.stats.steps and src.stats.steps[-1] >= 5, "training did not advance"
        assert not torch.equal(img, first)  # the frame shows the weights as they train
        th = src.train_thread
        th.pause()  # the GUI thread holds the trainer's lock: no step can run
        src.poll()
        step = src.stats.steps[-1]
        time.sleep(0.3)
        render_raw(src.field, cam.c2w, intr, s, src.lock)  # no deadlock while paused
        src.poll()
        assert src.stats.steps[-1] == step
        th.resume()
    finally:
        src.close()  # stops the loop, which checkpoints
    assert src.stats.error is None and src.stats.done
    assert (run / "checkpoint.pt").is_file()

    out = tmp_path / "snap.png"
    assert main(["view", str(run), "--snapshot", str(out), "--view-index", "3"]) == 0
    got = iio.imread(out)
    viewed = ViewSource.from_run(run)
    assert viewed.stats is not None and len(viewed.stats.losses) >= 5  # from metrics.jsonl
    ref = render_image(
        viewed.field,
        viewed.views[3],
        viewed.intrinsics,
        near=viewed.near,
        background=viewed.background,
    )["rgb"].numpy()
    assert got.shape == (24, 32, 3)
    assert np.abs(got / 255.0 - ref).max() <= 0.5 / 255 + 1e-6
    # a recorded camera path as --pose: its first frame, at its own intrinsics
    path = save_camera_path(
        tmp_path / "path.json", [(viewed.views[1], intrinsics_for_fov(20, 10, 30))]
    )
    assert main(["view", str(run), "--snapshot", str(out), "--pose", str(path)]) == 0
    assert iio.imread(out).shape == (10, 20, 3)


def test_occupancy_mode_reads_the_ngp_grid():
    from fastenerf.backends import parse_options
    from fastenerf.fields.ngp import NGPField
    from fastenerf.viewer.frame import ViewSettings, render_raw

    opts = parse_options("ngp", {"log2_table_size": 12, "grid_resolution": 16})
    f = NGPField([-1, -1, -1, 1, 1, 1], opts)
    g = f.grid
    # one grid update with a density that is non-zero in one cell only, [0, 1/8]^3
    centre = torch.tensor([[0.0625, 0.0625, 0.0625]])
    g.update(0, lambda x: 1e3 * ((x > 0) & (x < 0.125)).all(-1).float())
    assert bool(g.occupied(centre)[0]) and not bool(g.occupied(-centre)[0])
    c2w = look_at(np.array([0.0625, 0.0625, 3.0]), centre.numpy()[0], [0, 1, 0])[0]
    raw = render_raw(f, c2w, intrinsics_for_fov(21, 21, 10.0), ViewSettings(mode="occupancy"))
    hit = raw["opacity"] > 0
    assert hit[10, 10] and hit.sum() < 21 * 21 / 2
    # the first sample inside the cell: its front face is at z = 0.125, 2.875 from the eye
    assert abs(float(raw["depth"][10, 10]) - 2.875) <= 1 / 16 / 2 + 1e-4


def test_bench_viewer_render_only_and_through_gl(tmp_path):
    from fastenerf.viewer.bench import bench_viewer

    f = SphereField(n_samples=8)
    res = bench_viewer(f, size=(40, 30), frames=2, warmup=1, chunk=300, gl=False)
    assert res["chunk"] == 300 and res["render_fps"] > 0 and "full_fps" not in res
    assert res["view_cone_angle"] == 1 / 256  # the viewer's default floor
    res = bench_viewer(f, size=(40, 30), frames=2, warmup=1, gl=False, cone_angle=None)
    assert res["view_cone_angle"] is None
    _egl_or_skip().release()
    res = bench_viewer(f, size=(40, 30), frames=2, warmup=1)
    assert res["full_fps"] > 0 and res["upload_exact"], res


def test_interop_texture_takes_the_host_path_for_cpu_frames():
    from fastenerf.viewer.blit import InteropTexture, Offscreen

    ctx = _egl_or_skip()
    img = torch.randint(0, 256, (30, 40, 3), dtype=torch.uint8)
    tex, off = InteropTexture(ctx, filter="nearest"), Offscreen(ctx, (40, 30))
    tex.upload(img)
    off.draw(tex)
    ctx.finish()
    assert np.array_equal(off.read(), img.numpy()) and tex.interop is None
    tex.release()
    off.release()
    ctx.release()


def test_bench_refuses_a_bad_cone_angle_in_one_line(tmp_path, capsys):
    from fastenerf.viewer.bench import main

    out = tmp_path / "fps.json"
    out.write_text("kept")
    with pytest.raises(SystemExit) as e:
        main([str(tmp_path), "--cone-angle", "-0.5", "--no-gl", "--out", str(out)])
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert e.value.code == 2 and err == [
        "viewer.bench: error: --cone-angle must be in [0, 1], got -0.5"
    ]
    assert out.read_text() == "kept"
