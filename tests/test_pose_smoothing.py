"""The motion prior (fastenerf/pose_smoothing.py, #20): fitting the training poses to a smooth
path removes pose-to-pose jitter, keeps an exact path and a shared (mount) error, and the
trainer records what it did."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fastenerf.config import PerturbConfig, TrainConfig
from fastenerf.data.formats.native import load_scene
from fastenerf.data.rig import Intrinsics, Rig, TimedPoses
from fastenerf.errors import InputError
from fastenerf.perturb import perturb_mount, perturb_poses, pose_grid_times, rotation_angles_deg
from fastenerf.pose_smoothing import nearest_rotations, smooth_poses, smoothed_rig
from fastenerf.train import Trainer


def angles(a, b):
    return rotation_angles_deg(a[:, :3, :3], b[:, :3, :3])


def orbit_rig(scene_config, n_views=400, **kw):
    cfg = scene_config(64, 48, n_views=n_views, **kw)
    return cfg, Rig.from_scene(cfg), pose_grid_times(cfg)


def wobbly_timed(n=300):
    """A path that is not a turn about one axis: yaw, a slow nod and a roll, a moving centre."""
    t = np.linspace(0, 1_000_000, n).astype(np.int64)
    s = t * 1e-6
    R = Rotation.from_euler("yxz", np.stack([2 * s, 0.3 * np.sin(3 * s), 0.2 * s], 1))
    c2w = np.tile(np.eye(4), (n, 1, 1))
    c2w[:, :3, :3] = R.as_matrix()
    c2w[:, :3, 3] = np.stack([np.cos(s), 0.1 * s, np.sin(s)], 1)
    return t, c2w


def test_a_turntable_orbit_comes_out_exact(scene_config):
    """A tilted turntable turns about one fixed axis at a constant rate: the logs about a pose
    are linear along the grid, so the fit is exact for any window (three quarters of the loop
    too) and either order."""
    _, rig, grid_t = orbit_rig(scene_config)
    c2w = rig.pose(grid_t)
    for window, order in ((5, 2), (51, 2), (201, 2), (51, 1), (301, 1), (301, 2)):
        out = smooth_poses(c2w, window, loop=True, order=order)
        assert angles(c2w, out).max() < 1e-6
        assert np.array_equal(out[:, :3, 3], c2w[:, :3, 3])  # centres stay as given
        assert np.array_equal(out[-1, :3, :3], out[0, :3, :3])


def test_a_curved_path_is_kept_where_the_window_fits_it():
    """A path with its own curvature (not a turntable): a window short against its changes
    keeps it to a few thousandths of a degree, ends included (no wrap)."""
    t, c2w = wobbly_timed()
    out = smooth_poses(c2w, 21, loop=False)
    assert angles(c2w, out).max() < 0.01


@pytest.mark.parametrize("deg", [1.0, 2.0])
def test_jitter_is_removed(scene_config, deg):
    """An independent turn of every pose (the pose study's) is mostly high-frequency: a
    101-pose window leaves under a fifth of it, and what it leaves is proper rotations."""
    _, rig, grid_t = orbit_rig(scene_config)
    bad, _ = perturb_poses(rig, deg, seed=3, grid_t=grid_t)
    exact, given = rig.pose(grid_t), bad.pose(grid_t)
    out = smooth_poses(given, 101, loop=True)
    before, after = angles(exact, given).mean(), angles(exact, out).mean()
    assert before == pytest.approx(deg, rel=1e-6)
    assert after < 0.2 * before
    R = out[:, :3, :3]
    assert np.allclose(R @ R.transpose(0, 2, 1), np.eye(3), atol=1e-12)
    assert np.all(np.linalg.det(R) > 0)
    # on a constant-rate turn the straight-line fit averages the jitter with less left, and a
    # long window leaves less again (entries fitted instead would amplify it there)
    first = angles(exact, smooth_poses(given, 101, loop=True, order=1)).mean()
    assert first < 0.85 * after
    assert angles(exact, smooth_poses(given, 301, loop=True, order=1)).mean() < 0.75 * first


def test_a_shared_mount_turn_stays(scene_config):
    """A turn shared by every pose is smooth: the prior cannot see it (the refinement's job)."""
    _, rig, grid_t = orbit_rig(scene_config)
    bad, _ = perturb_mount(rig, 2.0, seed=1, grid_t=grid_t)
    exact, given = rig.pose(grid_t), bad.pose(grid_t)
    out = smooth_poses(given, 101, loop=True)
    assert angles(exact, out).mean() == pytest.approx(2.0, abs=1e-6)


def test_smoothed_rig_reports_and_keeps_the_rest(scene_config):
    cfg, rig, grid_t = orbit_rig(scene_config)
    bad, _ = perturb_poses(rig, 2.0, seed=0, grid_t=grid_t)
    new, report = smoothed_rig(bad, grid_t, 51, exact_c2w=rig.pose(grid_t))
    assert isinstance(new.trajectory, TimedPoses)
    assert new.intrinsics == bad.intrinsics and new.bayer == bad.bayer
    assert new.loop_period_us == bad.loop_period_us and report["loop"]
    assert report["window"] == 51 and report["poses"] == len(grid_t)
    assert report["error_before_deg"] == pytest.approx(2.0, rel=1e-6)
    assert report["error_after_deg"] < 0.5 * report["error_before_deg"]
    assert report["mean_turn_deg"] > 1.0  # the jitter it took out
    assert np.allclose(new.pose(grid_t), smooth_poses(bad.pose(grid_t), 51, loop=True))


def test_an_open_path_is_not_wrapped():
    t, c2w = wobbly_timed(60)
    rig = Rig(Intrinsics(50.0, 50.0, 32.0, 24.0, 64, 48), TimedPoses(t, c2w), None)
    new, report = smoothed_rig(rig, t, 7)
    assert not report["loop"]
    assert "error_before_deg" not in report
    assert np.allclose(new.pose(t), smooth_poses(c2w, 7, loop=False))


def test_nearest_rotation_of_a_reflection_is_a_rotation():
    M = np.diag([1.0, 1.0, -1.0])[None] @ Rotation.random(4, random_state=0).as_matrix()
    R = nearest_rotations(M)
    assert np.all(np.linalg.det(R) > 0)


@pytest.mark.parametrize("window", [2, 3, 4, 6, 100, -1])
def test_bad_windows_are_refused(window):
    _, c2w = wobbly_timed(60)
    if window < 0:
        with pytest.raises(InputError, match="smooth_poses"):
            TrainConfig(smooth_poses=window).validate()
        return
    with pytest.raises(InputError, match="smooth_poses"):
        smooth_poses(c2w, window, loop=False)
    if window < 60:
        with pytest.raises(InputError, match="smooth_poses"):
            TrainConfig(smooth_poses=window).validate()


def test_a_window_longer_than_the_poses_names_one_that_fits():
    _, c2w = wobbly_timed(60)
    with pytest.raises(InputError, match=r"longer than the 60 .* 40 % of them: 25\)$"):
        smooth_poses(c2w, 101, loop=False)
    with pytest.raises(InputError, match=r"longer than the 4 .*\(at least 5 are needed\)$"):
        smooth_poses(c2w[:4], 5, loop=False)  # no window fits: none is suggested


def test_a_window_spanning_half_a_turn_is_refused(scene_config):
    """On a 400-pose orbit, a 351-pose window reaches ±157° about a pose: near 180° a log's
    sign is arbitrary and the fit would average opposite turns, so it is one clear error;
    301 poses (±135°) is still exact."""
    _, rig, grid_t = orbit_rig(scene_config)
    c2w = rig.pose(grid_t)
    assert angles(c2w, smooth_poses(c2w, 301, loop=True, order=1)).max() < 1e-6
    with pytest.raises(InputError, match="turns 158° within half a window of 351"):
        smooth_poses(c2w, 351, loop=True)


def test_bad_orders_are_refused():
    _, c2w = wobbly_timed(60)
    for order in (0, 3):
        with pytest.raises(InputError, match="order must be 1 or 2"):
            smooth_poses(c2w, 7, loop=False, order=order)
        with pytest.raises(InputError, match="smooth_order"):
            TrainConfig(smooth_order=order).validate()


def prior_cfg(error_deg: float = 2.0, **kw) -> TrainConfig:
    """One tiny vanilla step of a pose study (error_deg) with the prior over 21 grid poses."""
    from fastenerf.config import train_preset

    tiny = {"depth": 2, "width": 16, "n_coarse": 8, "n_fine": 8}
    perturb = PerturbConfig(pose_error_deg=error_deg)
    batch = {"rays_per_step": 16, "windows_per_step": 2}
    return train_preset(
        "fast",
        "vanilla",
        steps=1,
        smooth_poses=21,
        perturb=perturb,
        backend_options=tiny,
        **batch,
        **kw,
    )


def test_the_trainer_smooths_and_records(tiny_scene, tmp_path):
    """A pose study's run with the prior: the sampler's grid poses are the smoothed ones, and
    config.json says how far they were from the truth before and after."""
    scene = load_scene(tiny_scene)
    cfg = prior_cfg()
    tr = Trainer(scene, cfg, tmp_path / "run")
    grid_t = tr.windows.grid_times(np.arange(tr.windows.n_views + 1))
    assert np.allclose(tr.sampler.grid_c2w.cpu().numpy(), tr.rig.pose(grid_t), atol=1e-6)
    tr.write_config()
    conf = json.loads((tmp_path / "run" / "config.json").read_text())
    sm = conf["pose_smoothing"]
    assert conf["built"]["pose_smoothing"] and sm["window"] == 21 and sm["order"] == 2
    assert sm["error_before_deg"] == pytest.approx(2.0, rel=1e-3)
    assert sm["error_after_deg"] < 0.6 * sm["error_before_deg"]
    with pytest.raises(InputError, match="smooth_poses 201 is longer"):
        Trainer(scene, dataclasses.replace(cfg, smooth_poses=201), tmp_path / "x")


def test_the_gate_eases_only_where_the_prior_found_the_poses_off():
    """refine_gate_prior_deg: the gate is off where the prior turned the given poses by more
    than that on average; it holds where they were right, without the prior, and by default."""
    from fastenerf.pose_calibration import row_gate

    cfg = TrainConfig(refine_poses=True, refine_gate=1.5, refine_gate_prior_deg=0.05)
    assert row_gate(cfg, 2.0) == 0.0  # a 2° study: the prior turned the poses by ~2°
    assert row_gate(cfg, 1e-12) == 1.5  # exact turntable poses: the prior moves none
    assert row_gate(cfg, None) == 1.5  # no prior
    assert row_gate(dataclasses.replace(cfg, refine_gate_prior_deg=None), 2.0) == 1.5
    with pytest.raises(InputError, match="refine_gate_prior_deg"):
        dataclasses.replace(cfg, refine_gate_prior_deg=-1.0).validate()


@pytest.mark.parametrize("error_deg, gate", [(2.0, 0.0), (0.0, 1.5)])
def test_the_trainer_eases_the_gate_after_the_prior(tiny_scene, tmp_path, error_deg, gate):
    """The run's row Adam takes the eased gate, and config.json records the one it took."""
    kw = {"smooth_order": 1, "refine_poses": True, "refine_gate_prior_deg": 0.05}
    cfg = prior_cfg(error_deg, **kw)
    tr = Trainer(load_scene(tiny_scene), cfg, tmp_path / "run")
    assert tr.selfcal.pose_optimizer.gate == gate
    tr.write_config()
    conf = json.loads((tmp_path / "run" / "config.json").read_text())
    assert conf["self_calibration"]["poses"]["gate"] == gate
    assert (conf["pose_smoothing"]["mean_turn_deg"] > 0.05) == (gate == 0.0)
