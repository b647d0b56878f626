"""The camera rig: distortion, rays, turntable and timed poses, Bayer channels."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from fastenerf.config import TrajectoryConfig
from fastenerf.data.rig import Intrinsics, Rig, TimedPoses, Turntable, look_at
from fastenerf.errors import InputError


def sensor_pixels(intr: Intrinsics, step: int = 7) -> tuple[np.ndarray, np.ndarray]:
    """Pixel centres on a grid over the whole sensor, corners included."""
    u = np.r_[np.arange(0, intr.width, step), intr.width - 1] + 0.5
    v = np.r_[np.arange(0, intr.height, step), intr.height - 1] + 0.5
    uu, vv = np.meshgrid(u, v)
    return uu.ravel(), vv.ravel()


@pytest.mark.parametrize("model", ["opencv", "eventnerf"])
@pytest.mark.parametrize("k1,k2", [(-0.35, 0.15), (0.08, 0.01), (-0.1, 0.0)])
def test_distortion_round_trip(model, k1, k2):
    intr = Intrinsics(300.0, 310.0, 170.0, 133.0, 346, 260, k1, k2, model)
    u, v = sensor_pixels(intr)
    d = intr.pixel_to_camera(u, v)  # undistorts
    uv = intr.project(d * np.linspace(0.5, 3.0, len(d))[:, None])  # any depth along the ray
    np.testing.assert_allclose(uv, np.stack([u, v], -1), atol=1e-6)
    # distortion really bends the corner rays: a pinhole camera sees them elsewhere
    pin = Intrinsics(300.0, 310.0, 170.0, 133.0, 346, 260)
    assert np.abs(pin.project(d) - np.stack([u, v], -1)).max() > 1.0


def test_eventnerf_model_is_their_closed_form():
    """x_u = x_d / (1 + k1 r_d² + k2 r_d⁴), from the distorted pixel, in one step."""
    intr = Intrinsics(300.0, 300.0, 173.0, 130.0, 346, 260, -0.3, 0.1, "eventnerf")
    u, v = np.array([0.5, 345.5, 100.5]), np.array([0.5, 259.5, 30.5])
    x, y = (u - 173.0) / 300.0, (v - 130.0) / 300.0
    r2 = x * x + y * y
    f = 1 - 0.3 * r2 + 0.1 * r2 * r2
    np.testing.assert_allclose(intr.pixel_to_camera(u, v)[:, :2], np.stack([x / f, y / f], -1))


def test_models_differ_for_the_same_coefficients():
    a = Intrinsics(300.0, 300.0, 173.0, 130.0, 346, 260, -0.35, 0.15, "opencv")
    b = Intrinsics(300.0, 300.0, 173.0, 130.0, 346, 260, -0.35, 0.15, "eventnerf")
    d = a.pixel_to_camera(np.array([0.5]), np.array([0.5]))
    assert np.abs(b.project(d) - [[0.5, 0.5]]).max() > 1.0  # pixels apart at the corner


def test_principal_point_ray_is_the_optical_axis():
    intr = Intrinsics(50.0, 60.0, 10.5, 7.5, 21, 15, -0.2, 0.05)  # pixel (10, 7) is centred
    c2w = look_at(np.array([1.0, 2.0, 3.0]), np.zeros(3), np.array([0.0, 1.0, 0.0]))[0]
    rig = Rig(intr, None, None)
    o, d = rig.rays(np.array([7 * 21 + 10]), c2w)
    np.testing.assert_allclose(d[0], c2w[:3, 2], atol=1e-6)
    np.testing.assert_allclose(o[0], [1, 2, 3], atol=1e-6)
    # x right, y down: the pixel right of / below the centre tilts toward +x_cam / +y_cam
    _, d2 = rig.rays(np.array([7 * 21 + 11, 8 * 21 + 10]), np.stack([c2w, c2w]))
    cam = d2 @ c2w[:3, :3]
    assert cam[0, 0] > 0 and abs(cam[0, 1]) < 1e-6 and cam[1, 1] > 0 and abs(cam[1, 0]) < 1e-6
    np.testing.assert_allclose(np.linalg.norm(d2, axis=-1), 1.0, atol=1e-6)


def test_look_at_is_a_rotation():
    eye = np.array([[0.0, 0.0, 4.0], [2.0, 1.0, -1.0]])
    c2w = look_at(eye, np.zeros_like(eye), np.array([0.0, 1.0, 0.0]))
    R = c2w[:, :3, :3]
    np.testing.assert_allclose(
        R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-12
    )
    np.testing.assert_allclose(np.linalg.det(R), 1.0)
    np.testing.assert_allclose(c2w[0, :3, :3], np.diag([1.0, -1.0, -1.0]), atol=1e-12)


@pytest.mark.parametrize("tilt,elev", [(0.0, 0.0), (2.85, 0.0), (0.24, 20.0)])
def test_turntable_geometry(tilt, elev):
    cfg = TrajectoryConfig(
        kind="turntable",
        radius=2.5,
        center=[0.1, -0.2, 0.3],
        tilt_deg=tilt,
        elevation_deg=elev,
        period_us=400_000,
        phase_deg=30.0,
        t0_us=1000,
    )
    tt = Turntable(cfg)
    t = np.linspace(0, 800_000, 37)
    c2w = tt(t)
    c = np.array(cfg.center)
    eye = c2w[:, :3, 3]
    np.testing.assert_allclose(np.linalg.norm(eye - c, axis=-1), 2.5, atol=1e-9)  # radius
    to_c = (c - eye) / np.linalg.norm(c - eye, axis=-1, keepdims=True)
    np.testing.assert_allclose(c2w[:, :3, 2], to_c, atol=1e-9)  # looks at the centre
    np.testing.assert_allclose(tt(t + 400_000), c2w, atol=1e-9)  # one turn per period
    axis = Rotation.from_euler("x", tilt, degrees=True).apply([0.0, 1.0, 0.0])  # tilted +y
    height = (eye - c) @ axis
    np.testing.assert_allclose(height, 2.5 * np.sin(np.deg2rad(elev)), atol=1e-9)  # plane
    if elev == 0.0:  # the image's "up" (-y_cam) is the turntable axis
        np.testing.assert_allclose(-c2w[:, :3, 1], np.broadcast_to(axis, eye.shape), atol=1e-9)
    # phase: at t0 the camera sits at angle 30° from +z toward +x (tilt 0, elevation 0)
    if tilt == 0.0 and elev == 0.0:
        e0 = tt([1000])[0, :3, 3] - c
        np.testing.assert_allclose(
            e0, 2.5 * np.array([np.sin(np.pi / 6), 0, np.cos(np.pi / 6)]), atol=1e-9
        )
        # counter-clockwise about +y (right-hand rule) unless `clockwise`
        a1 = tt([101_000])[0, :3, 3] - c  # a quarter turn later
        assert np.cross(e0, a1) @ [0, 1, 0] > 0
        cfg.clockwise = True
        assert np.cross(e0, Turntable(cfg)([101_000])[0, :3, 3] - c) @ [0, 1, 0] < 0


def rot_y(deg):
    c2w = np.eye(4)
    c2w[:3, :3] = Rotation.from_euler("y", deg, degrees=True).as_matrix()
    return c2w


def test_timed_poses_interpolation():
    a, b = rot_y(0.0), rot_y(90.0)
    a[:3, 3], b[:3, 3] = [0.0, 0.0, 0.0], [2.0, 4.0, -2.0]
    tp = TimedPoses(np.array([1000, 3000]), np.stack([a, b]))
    np.testing.assert_allclose(tp([1000, 3000]), np.stack([a, b]), atol=1e-12)  # exact at samples
    mid = tp([2000])[0]
    np.testing.assert_allclose(mid[:3, :3], rot_y(45.0)[:3, :3], atol=1e-12)  # slerp midpoint
    np.testing.assert_allclose(mid[:3, 3], [1.0, 2.0, -1.0], atol=1e-12)  # lerp
    q = tp([1500])[0]  # a quarter of the way: 22.5°, not a normalised matrix average
    np.testing.assert_allclose(q[:3, :3], rot_y(22.5)[:3, :3], atol=1e-12)
    np.testing.assert_allclose(tp([0, 9000]), np.stack([a, b]), atol=1e-12)  # clamped
    # the short way round when the quaternions have opposite signs (350° -> 10°), all along
    # a trajectory that wraps several times (each sample 100° from the previous one)
    tp2 = TimedPoses(np.array([0, 10]), np.stack([rot_y(350.0), rot_y(10.0)]))
    np.testing.assert_allclose(tp2([5])[0, :3, :3], np.eye(3), atol=1e-12)
    angles = np.arange(12) * 100.0
    tp3 = TimedPoses(np.arange(12) * 10, np.stack([rot_y(a) for a in angles]))
    mids = tp3(np.arange(11) * 10 + 5)
    np.testing.assert_allclose(mids, np.stack([rot_y(a + 50.0) for a in angles[:-1]]), atol=1e-12)


@pytest.mark.parametrize(
    "t,c2w,words",
    [
        ([0, 1], np.where(np.arange(32).reshape(2, 4, 4) == 19, np.nan, np.eye(4)), "pose 1"),
        ([0, 1], np.tile(np.eye(4), (2, 1, 1))[:, :3, :3], "(M, 4, 4)"),
        ([0, 1, 2], np.tile(np.eye(4), (2, 1, 1)), "timestamps of shape"),
        ([0, 0], np.tile(np.eye(4), (2, 1, 1)), "increase strictly"),
        ([0.0, np.inf], np.tile(np.eye(4), (2, 1, 1)), "finite"),
        ([0, 1], np.tile(np.diag([1.0, 1.0, -1.0, 1.0]), (2, 1, 1)), "not a rotation"),
        ([0, 1], np.tile(np.diag([2.0, 1.0, 1.0, 1.0]), (2, 1, 1)), "not a rotation"),
        ([], np.zeros((0, 4, 4)), "no poses"),
    ],
)
def test_timed_poses_reject_bad_input(t, c2w, words):
    with pytest.raises(InputError, match="cams.npz") as e:
        TimedPoses(np.array(t), np.array(c2w), source="cams.npz")
    assert words in str(e.value) and "\n" not in str(e.value)


def test_loop_rig_wraps_times_before_the_start(scene_config):
    cfg = scene_config(
        8,
        6,
        trajectory=TrajectoryConfig(kind="timed", poses_file="p.npz"),
        t_start_us=100,
        t_end_us=1100,
        loop=True,
    )
    t = np.array([100, 600, 1100])
    c2w = np.stack([rot_y(0.0), rot_y(90.0), rot_y(180.0)])
    rig = Rig.from_scene(cfg, poses=(t, c2w))
    np.testing.assert_allclose(rig.pose([-150]), rig.pose([850]), atol=1e-12)
    np.testing.assert_allclose(rig.pose([100, 1100]), c2w[[0, 2]], atol=1e-12)
    cfg.loop = False
    np.testing.assert_allclose(Rig.from_scene(cfg, poses=(t, c2w)).pose([-150])[0], c2w[0])


def test_bayer_rggb_channels():
    rig = Rig(Intrinsics(10.0, 10.0, 3.0, 2.0, 6, 4), None, "rggb")
    pix = np.arange(24)
    ch = rig.channel(pix).reshape(4, 6)
    want = np.array([[0, 1] * 3, [1, 2] * 3] * 2)  # R G / G B
    np.testing.assert_array_equal(ch, want)
    t = rig.channel(torch.arange(24))
    assert isinstance(t, torch.Tensor) and t.reshape(4, 6).tolist() == want.tolist()
    assert rig.channel([0, 1, 6, 7]).tolist() == [0, 1, 1, 2]
    assert Rig(rig.intrinsics, None, None).channel(pix) is None  # mono sensor


def test_scaled_intrinsics_keep_the_field_of_view():
    intr = Intrinsics(300.0, 300.0, 173.0, 130.0, 346, 260, -0.2, 0.05, "eventnerf")
    half = intr.scaled(0.5)
    assert (half.width, half.height, half.model, half.k1) == (173, 130, "eventnerf", -0.2)
    a = intr.pixel_to_camera(np.array([0.0, 346.0]), np.array([0.0, 260.0]))
    b = half.pixel_to_camera(np.array([0.0, 173.0]), np.array([0.0, 130.0]))
    np.testing.assert_allclose(a, b, atol=1e-12)  # the sensor's edges see the same rays
