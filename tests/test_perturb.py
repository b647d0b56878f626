"""Perturbations for the robustness studies do what they say (fastenerf/perturb.py, issue 15):
the angle applied is the angle asked, about spread axes, centres and test views stay; the noise
is the fraction asked, uniform, balanced and merged into a valid stream; zero is the identity;
the command writes copies that read back."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy import stats
from scipy.spatial.transform import Rotation

from fastenerf.cli import main
from fastenerf.config import PerturbConfig, TrajectoryConfig
from fastenerf.data.events import EventStream
from fastenerf.data.formats import load_any
from fastenerf.data.formats.native import Scene, load_scene, save_scene, write_events
from fastenerf.data.rig import Intrinsics, Rig, TimedPoses, Turntable
from fastenerf.errors import InputError
from fastenerf.perturb import (
    add_noise_events,
    merge_events,
    perturb_poses,
    perturb_training_data,
    pose_grid_times,
    rotation_angles_deg,
)
from fastenerf.sampling import WindowSampler


def arccos_angles_deg(R_a, R_b):
    """Independent measure: arccos((tr(R_aᵀ R_b) − 1) / 2), fine away from 0."""
    tr = np.einsum("nji,nji->n", R_a, R_b)
    return np.rad2deg(np.arccos(np.clip((tr - 1) / 2, -1, 1)))


def turntable_rig(scene_config, **kw):
    cfg = scene_config(64, 48, **kw)
    return cfg, Rig.from_scene(cfg)


def timed_rig(n=40, loop=False):
    """A wobbly timed trajectory: n poses over 1 s, rotations well apart."""
    t = np.linspace(0, 1_000_000, n).astype(np.int64)
    R = Rotation.from_euler("yxz", np.stack([t * 3e-6, np.sin(t * 1e-5), t * 1e-6], 1)).as_matrix()
    c2w = np.tile(np.eye(4), (n, 1, 1))
    c2w[:, :3, :3], c2w[:, :3, 3] = R, np.stack([np.cos(t * 1e-6), t * 1e-7, np.sin(t * 1e-6)], 1)
    intr = Intrinsics(50.0, 50.0, 32.0, 24.0, 64, 48)
    return Rig(intr, TimedPoses(t, c2w), "rggb", *((0, 1_000_000) if loop else (None, None)))


# ------------------------------------------------------------------------------ pose error


def test_pose_grid_is_the_window_samplers(scene_config):
    cfg = scene_config(64, 48, n_views=77, t_start_us=13, t_end_us=1_000_003)
    ws = WindowSampler(cfg.n_views, cfg.t_start_us, cfg.t_end_us, 1, 5)
    np.testing.assert_array_equal(pose_grid_times(cfg), ws.grid_times(np.arange(78)))


@pytest.mark.parametrize("deg", [0.01, 0.5, 2.0, 30.0])
def test_turntable_angle_is_exact_and_centres_stay(scene_config, deg):
    cfg, rig = turntable_rig(scene_config)
    grid = pose_grid_times(cfg)
    new, rep = perturb_poses(rig, deg, seed=3, grid_t=grid)
    assert isinstance(rig.trajectory, Turntable) and isinstance(new.trajectory, TimedPoses)
    np.testing.assert_array_equal(new.trajectory.t, grid)
    before, after = rig.pose(grid), new.pose(grid)
    measured = arccos_angles_deg(before[:, :3, :3], after[:, :3, :3])
    np.testing.assert_allclose(measured, deg, atol=1e-6)
    for key in ("measured_mean_deg", "measured_max_deg", "measured_min_deg"):
        assert abs(rep[key] - deg) < 1e-6, (key, rep[key])
    assert abs(rep["grid"]["measured_max_deg"] - deg) < 1e-6
    np.testing.assert_allclose(after[:, :3, 3], before[:, :3, 3], atol=1e-12)
    assert rep["centre_shift_max"] < 1e-12
    # A loop's two ends are one view (the same pose, the same turn); the rest are distinct.
    assert rep["poses"] == cfg.n_views
    np.testing.assert_allclose(after[-1], after[0], atol=1e-9)
    assert new.intrinsics == rig.intrinsics and new.bayer == rig.bayer
    assert (new.loop_start_us, new.loop_period_us) == (rig.loop_start_us, rig.loop_period_us)


def test_axes_are_spread_over_the_sphere(scene_config):
    cfg, rig = turntable_rig(scene_config, n_views=400)
    grid = pose_grid_times(cfg)
    new, _ = perturb_poses(rig, 1.0, seed=0, grid_t=grid)
    before, after = rig.pose(grid)[:-1, :3, :3], new.pose(grid)[:-1, :3, :3]
    delta = np.einsum("nji,njk->nik", before, after)  # Rᵀ R' = Δ, axis in the camera frame
    axes = Rotation.from_matrix(delta).as_rotvec()
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    assert np.linalg.norm(axes.mean(0)) < 0.15  # uniform: ~1/sqrt(n); one axis would give 1
    for k in range(3):  # each coordinate of a uniform unit vector is uniform on [-1, 1]
        assert stats.kstest(axes[:, k], stats.uniform(-1, 2).cdf).pvalue > 1e-3
    assert len(np.unique(np.round(axes, 6), axis=0)) == len(axes)


def test_timed_rig_each_sample_turned(scene_config):
    rig = timed_rig(40)
    grid = np.linspace(0, 1_000_000, 101).astype(np.int64)
    new, rep = perturb_poses(rig, 0.3, seed=1, grid_t=grid)
    t = rig.trajectory.t
    np.testing.assert_array_equal(new.trajectory.t, t)
    before, after = rig.pose(t), new.pose(t)
    np.testing.assert_allclose(
        arccos_angles_deg(before[:, :3, :3], after[:, :3, :3]), 0.3, atol=1e-6
    )
    np.testing.assert_allclose(after[:, :3, 3], before[:, :3, 3], atol=1e-12)
    assert rep["poses"] == 40 and abs(rep["measured_mean_deg"] - 0.3) < 1e-6
    # Between samples slerp mixes two turns about different axes: mostly less than asked.
    assert rep["grid"]["poses"] == 101 and rep["grid"]["measured_max_deg"] < 0.3 * 1.01
    assert rep["grid"]["measured_mean_deg"] < 0.3
    # A timed rig needs no grid.
    assert perturb_poses(rig, 0.3, seed=1)[1]["measured_max_deg"] == rep["measured_max_deg"]


def test_turntable_needs_the_grid(scene_config):
    _, rig = turntable_rig(scene_config)
    with pytest.raises(InputError, match="grid"):
        perturb_poses(rig, 1.0)


def test_seeds(scene_config):
    cfg, rig = turntable_rig(scene_config)
    grid = pose_grid_times(cfg)
    a = perturb_poses(rig, 0.5, seed=7, grid_t=grid)[0].pose(grid)
    b = perturb_poses(rig, 0.5, seed=7, grid_t=grid)[0].pose(grid)
    c = perturb_poses(rig, 0.5, seed=8, grid_t=grid)[0].pose(grid)
    np.testing.assert_array_equal(a, b)
    assert np.abs(a - c).max() > 1e-4


def test_tiny_angles_are_measured_to_full_precision():
    """Stability: the measured angle of a 1e-5° turn is exact to 1e-9°; the arccos of the
    trace (which the measure avoids) is off by more than that at this angle."""
    rig = timed_rig(200)
    new, rep = perturb_poses(rig, 1e-5, seed=0)
    assert abs(rep["measured_max_deg"] - 1e-5) < 1e-9
    assert abs(rep["measured_min_deg"] - 1e-5) < 1e-9
    t = rig.trajectory.t
    naive = arccos_angles_deg(rig.pose(t)[:, :3, :3], new.pose(t)[:, :3, :3])
    assert np.abs(naive - 1e-5).max() > 1e-9


def test_rotation_angles_deg_against_known_rotations():
    rng = np.random.default_rng(0)
    R = Rotation.random(50, random_state=1).as_matrix()
    ang = rng.uniform(0, 179, 50)
    axes = Rotation.random(50, random_state=2).apply([0, 0, 1])
    R2 = R @ Rotation.from_rotvec(axes * np.deg2rad(ang)[:, None]).as_matrix()
    np.testing.assert_allclose(rotation_angles_deg(R, R2), ang, atol=1e-9)


# ------------------------------------------------------------------------------ noise events


def test_noise_fraction_count_and_valid_stream(random_stream):
    clean = random_stream(n=3001, width=20, height=10, t_max=50_000, t_min=100)
    for frac in (0.01, 0.05, 0.15, 0.3, 2.5):
        noisy, rep = add_noise_events(clean, frac, seed=0)
        k = len(noisy) - len(clean)
        assert abs(k - frac * len(clean)) <= 1
        assert rep["added_events"] == k and rep["clean_events"] == len(clean)
        assert abs(rep["measured_fraction"] - frac) <= 1 / len(clean)
        # Valid and sorted: re-validating the arrays raises on anything wrong.
        again = EventStream.from_arrays(noisy.x, noisy.y, noisy.t, noisy.p, 20, 10)
        assert np.all(np.diff(again.t) >= 0)
        assert noisy.t[0] >= clean.t[0] and noisy.t[-1] <= clean.t[-1]
        assert noisy.x.dtype == np.uint16 and noisy.t.dtype == np.int64 and noisy.p.dtype == np.int8
        # Every clean event is still there (multiset of rows).
        rows = lambda e: np.stack([e.t, e.x, e.y, e.p], 1).astype(np.int64)  # noqa: E731
        u_all, c_all = np.unique(rows(noisy), axis=0, return_counts=True)
        u_cl, c_cl = np.unique(rows(clean), axis=0, return_counts=True)
        idx = [np.flatnonzero((u_all == r).all(1))[0] for r in u_cl[:200]]
        assert np.all(c_all[idx] >= c_cl[:200])


def test_noise_is_uniform_and_balanced():
    """Clean events all sit in column 0, so noise in columns 1.. is identified exactly; x, y,
    t of those are tested against uniform (chi-square, KS) and polarity against 1/2."""
    rng = np.random.default_rng(5)
    n, w, h = 40_000, 32, 24
    t = np.sort(rng.integers(1000, 2_001_000, n))
    t[0], t[-1] = 1000, 2_001_000
    clean = EventStream.from_arrays(
        np.zeros(n), rng.integers(0, h, n), t, rng.choice([-1, 1], n), w, h
    )
    noisy, rep = add_noise_events(clean, 1.0, seed=11)
    sel = noisy.x > 0
    x, y, tt, p = noisy.x[sel], noisy.y[sel], noisy.t[sel], noisy.p[sel]
    assert abs(sel.sum() - n * (w - 1) / w) < 5 * np.sqrt(n / w)
    assert stats.chisquare(np.bincount(x, minlength=w)[1:]).pvalue > 1e-3
    assert stats.chisquare(np.bincount(y, minlength=h)).pvalue > 1e-3
    assert stats.kstest(tt, stats.uniform(1000, 2_000_000).cdf).pvalue > 1e-3
    assert set(np.unique(p)) == {-1, 1}
    assert stats.binomtest(int((p > 0).sum()), len(p), 0.5).pvalue > 1e-3
    assert abs(rep["noise_positive_fraction"] - 0.5) < 0.02


def test_noise_seeds(random_stream):
    clean = random_stream(n=2000)
    a, _ = add_noise_events(clean, 0.2, seed=1)
    b, _ = add_noise_events(clean, 0.2, seed=1)
    c, _ = add_noise_events(clean, 0.2, seed=2)
    for k in ("x", "y", "t", "p"):
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k))
    assert any(not np.array_equal(getattr(a, k), getattr(c, k)) for k in ("x", "y", "t"))


def test_merge_keeps_both_orders():
    a = EventStream.from_arrays([0, 1, 2, 3], [0, 0, 0, 0], [5, 5, 7, 9], [1, -1, 1, 1], 8, 8)
    b = EventStream.from_arrays([4, 5, 6], [1, 1, 1], [1, 5, 12], [-1, -1, 1], 8, 8)
    m, from_b = merge_events(a, b)
    np.testing.assert_array_equal(m.t, [1, 5, 5, 5, 7, 9, 12])
    np.testing.assert_array_equal(m.x, [4, 0, 1, 5, 2, 3, 6])  # at t=5: a's first, in order
    np.testing.assert_array_equal(from_b, [1, 0, 0, 1, 0, 0, 1])
    with pytest.raises(InputError, match="sensors differ"):
        merge_events(a, EventStream.from_arrays([0], [0], [0], [1], 9, 8))


# ------------------------------------------------------------------------------ config, apply


def small_scene(tmp_path, random_stream, scene_config, timed=False, loop=True) -> Scene:
    traj = TrajectoryConfig(radius=3.0, tilt_deg=2.0, elevation_deg=10.0, period_us=100_000)
    cfg = scene_config(16, 12, n_views=50, t_end_us=100_000, loop=loop, trajectory=traj)
    ev = random_stream(n=3000, width=16, height=12, t_max=99_999, t_min=0)
    rng = np.random.default_rng(1)
    test_t = np.array([0, 30_000, 70_000])
    test_c2w = Turntable(cfg.trajectory)(test_t)
    rgb = rng.uniform(0, 1, (3, 12, 16, 3))
    poses = None
    if timed:
        t = np.linspace(0, 100_000, 26).astype(np.int64)
        poses = (t, Turntable(cfg.trajectory)(t))
        cfg.trajectory = TrajectoryConfig(kind="timed", poses_file="poses.npz")
    save_scene(tmp_path / "scene", cfg, ev, test_t, test_c2w, rgb, poses=poses)
    return load_scene(tmp_path / "scene")


def test_perturb_config_validation():
    assert not PerturbConfig().validate().active
    assert PerturbConfig(noise_fraction=0.05).active and PerturbConfig(mount_error_deg=1).active
    c = PerturbConfig.from_dict({"pose_error_deg": 0.5, "noise_fraction": 0.15, "seed": 3})
    assert PerturbConfig.from_dict(json.loads(json.dumps(c.to_dict()))) == c
    PerturbConfig(np.float32(0.5), np.float64(0.1), np.int64(3)).validate()  # levels from arrays
    bad = [
        ({"pose_error_deg": -0.1}, "pose_error_deg"),
        ({"pose_error_deg": 180}, "pose_error_deg"),
        ({"mount_error_deg": 180}, "mount_error_deg"),
        ({"mount_error_deg": -1.0}, "mount_error_deg"),
        ({"mount_error_deg": "2"}, "mount_error_deg"),
        ({"noise_fraction": 10.5}, "noise_fraction"),
        ({"noise_fraction": -0.01}, "noise_fraction"),
        ({"seed": -1}, "seed"),
        ({"seed": 1.5}, "seed"),
        ({"pose_error_deg": "1"}, "pose_error_deg"),
        ({"pose_err": 1}, "unknown key"),
    ]
    for d, words in bad:
        with pytest.raises(InputError, match=words) as e:
            PerturbConfig.from_dict(d)
        assert "\n" not in str(e.value)
    for v in (float("nan"), float("inf")):
        with pytest.raises(InputError, match="finite"):
            PerturbConfig(pose_error_deg=v).validate()


@pytest.mark.parametrize("timed", [False, True])
def test_apply_to_a_scene(tmp_path, random_stream, scene_config, timed):
    scene = small_scene(tmp_path, random_stream, scene_config, timed=timed)
    test_c2w, events = scene.test_c2w.copy(), scene.events
    rig0 = scene.rig()
    # zero levels: the inputs themselves
    rig, ev, rep = perturb_training_data(scene, PerturbConfig(seed=4), rig=rig0)
    assert rig is rig0 and ev is events and rep["pose"] is None and rep["noise"] is None
    # noise only: the rig is untouched; pose only: the events are
    rig, ev, rep = perturb_training_data(scene, PerturbConfig(noise_fraction=0.1), rig=rig0)
    assert rig is rig0 and len(ev) == len(events) + 300 and rep["noise"]["added_events"] == 300
    rig, ev, rep = perturb_training_data(scene, PerturbConfig(pose_error_deg=0.2), rig=rig0)
    assert ev is events and rep["pose"]["poses"] == (25 if timed else 50)
    # both
    cfg = PerturbConfig(pose_error_deg=1.0, noise_fraction=0.05, seed=2)
    rig, ev, rep = perturb_training_data(scene, cfg)
    assert abs(rep["pose"]["measured_max_deg"] - 1.0) < 1e-6
    assert abs(rep["pose"]["measured_mean_deg"] - 1.0) < 1e-6
    assert rep["noise"]["added_events"] == 150 and rep["config"] == cfg.to_dict()
    json.dumps(rep)  # goes into the run's config.json as it is
    # test views and the scene's own data are untouched
    np.testing.assert_array_equal(scene.test_c2w, test_c2w)
    assert scene.events is events and len(scene.events) == 3000
    # pose and noise draw from separate streams: the pose turn does not depend on the noise
    alone = perturb_training_data(scene, PerturbConfig(pose_error_deg=1.0, seed=2))[0]
    grid = pose_grid_times(scene.config)
    np.testing.assert_array_equal(alone.pose(grid), rig.pose(grid))


@pytest.mark.parametrize("timed", [False, True])
def test_mount_error_is_one_camera_frame_turn(tmp_path, random_stream, scene_config, timed):
    """Every training pose turned by exactly mount_error_deg about ONE camera-frame axis,
    c2w · M, centres kept; with the pose error too, c2w · M · Δ_i (Δ_i as without the mount)."""
    scene = small_scene(tmp_path, random_stream, scene_config, timed=timed)
    grid, test_c2w = pose_grid_times(scene.config), scene.test_c2w.copy()
    exact = scene.rig().pose(grid)
    rig, _, rep = perturb_training_data(scene, PerturbConfig(mount_error_deg=2.0, seed=3))
    bad = rig.pose(grid)
    rel = np.einsum("nji,njk->nik", exact[:, :3, :3], bad[:, :3, :3])  # R_exactᵀ R'
    np.testing.assert_allclose(rel, np.broadcast_to(rel[0], rel.shape), atol=1e-12)
    ang = rotation_angles_deg(exact[:, :3, :3], bad[:, :3, :3])
    np.testing.assert_allclose(ang, 2.0, rtol=1e-9)
    axis = Rotation.from_matrix(rel[0]).as_rotvec()
    np.testing.assert_allclose(axis / np.linalg.norm(axis), rep["mount"]["axis"], atol=1e-9)
    np.testing.assert_allclose(bad[:, :3, 3], exact[:, :3, 3], atol=1e-12)
    assert rep["pose"] is None and abs(rep["mount"]["grid"]["measured_max_deg"] - 2.0) < 1e-9
    other = perturb_training_data(scene, PerturbConfig(mount_error_deg=2.0, seed=4))[0]
    assert not np.allclose(other.pose(grid), bad)  # the axis comes from the seed
    both = perturb_training_data(scene, PerturbConfig(0.5, seed=3, mount_error_deg=2.0))[0]
    alone = perturb_training_data(scene, PerturbConfig(0.5, seed=3))[0]
    ts = alone.trajectory.t  # the samples turned (between them slerp blends two Δ)
    ex = scene.rig().pose(ts)[:, :3, :3]
    delta = np.einsum("nji,njk->nik", ex, alone.pose(ts)[:, :3, :3])
    np.testing.assert_allclose(both.pose(ts)[:, :3, :3], ex @ rel[0] @ delta, atol=1e-12)
    np.testing.assert_array_equal(scene.test_c2w, test_c2w)  # test views stay exact


# ------------------------------------------------------------------------------ the command


def test_command_noise_round_trip(tmp_path, random_stream, capsys):
    clean = random_stream(n=4000, width=20, height=10)
    src = write_events(tmp_path / "clean.h5", clean)
    out = tmp_path / "noisy.npz"
    assert main(["perturb", "noise", str(src), "--fraction", "0.05", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "added 200 uniform noise events" in text and f"wrote {out}" in text
    noisy = load_any(out)
    assert len(noisy) == 4200 and (noisy.width, noisy.height) == (20, 10)
    assert main(["info", str(out)]) == 0
    # the same command again replaces its own output (same kind), with the same result
    assert main(["perturb", "noise", str(src), "--fraction", "0.05", "--out", str(out)]) == 0
    np.testing.assert_array_equal(load_any(out).t, noisy.t)
    # text input, JSON report
    txt = tmp_path / "ev.txt"
    txt.write_text(
        "".join(
            f"{t} {x} {y} {int(p > 0)}\n"
            for t, x, y, p in zip(clean.t, clean.x, clean.y, clean.p, strict=True)
        )
    )
    out2 = tmp_path / "noisy2.npz"
    capsys.readouterr()
    args = ["perturb", "noise", str(txt), "--fraction", "0.5", "--seed", "3", "--sensor", "20x10"]
    assert main([*args, "--out", str(out2), "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert rep["added_events"] == 2000 and rep["sensor"] == "20x10"
    assert len(load_any(out2)) == 6000


def test_command_poses_round_trip(tmp_path, random_stream, scene_config, capsys):
    scene = small_scene(tmp_path, random_stream, scene_config)
    out = tmp_path / "perturbed"
    assert main(["perturb", "poses", str(scene.root), "--deg", "0.5", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "50 training poses" in text and "mean 0.500000°" in text and f"wrote {out}" in text
    new = load_scene(out)
    assert new.config.trajectory.kind == "timed"
    grid = pose_grid_times(scene.config)
    np.testing.assert_array_equal(new.poses[0], grid)
    R0, R1 = scene.rig().pose(grid)[:, :3, :3], new.rig().pose(grid)[:, :3, :3]
    np.testing.assert_allclose(arccos_angles_deg(R0, R1), 0.5, atol=1e-6)
    np.testing.assert_array_equal(new.test_c2w, scene.test_c2w)
    np.testing.assert_array_equal(new.test_t, scene.test_t)
    for a, b in zip(scene.test_rgb_paths, new.test_rgb_paths, strict=True):
        assert a.read_bytes() == b.read_bytes()
    np.testing.assert_array_equal(new.events.t, scene.events.t)
    rep = json.loads((out / "perturb.json").read_text())
    assert rep["angle_deg"] == 0.5 and abs(rep["measured_max_deg"] - 0.5) < 1e-6
    assert main(["info", str(out)]) == 0
    # a perturbed scene can be perturbed again (timed input), replacing its own kind
    assert main(["perturb", "poses", str(out), "--deg", "0.1", "--out", str(out)]) == 2
    out2 = tmp_path / "again"
    assert main(["perturb", "poses", str(out), "--deg", "0.1", "--out", str(out2)]) == 0
    assert main(["perturb", "poses", str(out), "--deg", "0.2", "--out", str(out2)]) == 0
    assert json.loads((out2 / "perturb.json").read_text())["angle_deg"] == 0.2


def test_command_poses_from_an_eventnerf_folder(tmp_path, random_stream, scene_config):
    from fastenerf.data.formats.eventnerf import load_eventnerf
    from fastenerf.data.formats.eventnerf_export import export_eventnerf

    scene = small_scene(tmp_path, random_stream, scene_config)
    with pytest.warns(UserWarning, match="346x260"):  # small sensor: fine for us, not for them
        export_eventnerf(scene, tmp_path / "en")
    theirs = load_eventnerf(tmp_path / "en")
    out = tmp_path / "en_perturbed"
    assert main(["perturb", "poses", str(tmp_path / "en"), "--deg", "1", "--out", str(out)]) == 0
    new = load_scene(out)
    t = theirs.poses[0]
    np.testing.assert_array_equal(new.poses[0], t)
    ang = arccos_angles_deg(theirs.rig().pose(t)[:, :3, :3], new.rig().pose(t)[:, :3, :3])
    np.testing.assert_allclose(ang, 1.0, atol=1e-6)
    np.testing.assert_array_equal(new.test_c2w, theirs.test_c2w)
    assert len(new.test_rgb_paths) == len(theirs.test_rgb_paths) == 3
    np.testing.assert_array_equal(new.load_test_images(), theirs.load_test_images())
    np.testing.assert_array_equal(new.events.t, theirs.events.t)


@pytest.mark.parametrize(
    "argv, words",
    [
        (["noise", "{ev}", "--fraction", "-1", "--out", "{tmp}/o.npz"], "--fraction"),
        (["noise", "{ev}", "--fraction", "nan", "--out", "{tmp}/o.npz"], "--fraction"),
        (["noise", "{ev}", "--fraction", "0.1", "--seed", "-2", "--out", "{tmp}/o.npz"], "--seed"),
        (["noise", "{ev}", "--fraction", "0.1", "--out", "{tmp}/o.h5"], ".npz"),
        (["noise", "{tmp}/missing.npz", "--fraction", "0.1", "--out", "{tmp}/o.npz"], "no such"),
        (["noise", "{ev}", "--fraction", "0.1", "--out", "{ev}"], "input itself"),
        (["noise", "{ev}", "--fraction", "0.1", "--out", "{tmp}/keep.npz"], "not an events"),
        (
            ["noise", "{ev}", "--fraction", "0.1", "--sensor", "20by10", "--out", "{tmp}/o.npz"],
            "--sensor",
        ),
        (["poses", "{scene}", "--deg", "180", "--out", "{tmp}/s2"], "--deg"),
        (["poses", "{scene}", "--deg", "inf", "--out", "{tmp}/s2"], "--deg"),
        (["poses", "{ev}", "--deg", "1", "--out", "{tmp}/s2"], "not a scene folder"),
        (["poses", "{scene}", "--deg", "1", "--out", "{tmp}/keep.npz"], "not a native scene"),
        (["poses", "{scene}", "--deg", "1", "--out", "{tmp}/full"], "not a native scene"),
        (["poses", "{scene}", "--deg", "1", "--out", "{scene}"], "input itself"),
    ],
)
def test_command_bad_input(tmp_path, random_stream, scene_config, capsys, argv, words):
    scene = small_scene(tmp_path, random_stream, scene_config)
    ev = scene.root / "events.npz"
    (tmp_path / "keep.npz").write_bytes(b"precious, not events")
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "notes.txt").write_text("mine")
    subs = {"{ev}": str(ev), "{scene}": str(scene.root), "{tmp}": str(tmp_path)}
    args = [a for a in argv]
    for k, v in subs.items():
        args = [a.replace(k, v) for a in args]
    before = ev.read_bytes()
    assert main(["perturb", *args]) == 2
    err = capsys.readouterr().err.strip()
    assert words in err and len(err.splitlines()) == 1, err
    assert (tmp_path / "keep.npz").read_bytes() == b"precious, not events"
    assert (tmp_path / "full" / "notes.txt").read_text() == "mine"
    assert ev.read_bytes() == before
    assert not (tmp_path / "o.npz").exists() and not (tmp_path / "s2").exists()
