"""Turntable calibration (supplement A.1) from noisy synthetic chequerboard poses.

Noise model (per pose): camera centre N(0, 1 mm²) per axis at a 0.6 m circle, orientation a
random rotation with N(0, 0.05°²) per rotation-vector component — a good chequerboard
detection. Over 30 seeds the least-squares fit's tilt error had σ ≈ 0.012° (max 0.025°); the
tolerances below are ~4σ.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from fastenerf.cli import main as cli
from fastenerf.config import TrajectoryConfig
from fastenerf.data.calibrate import (
    compare_solvers,
    fit_turntable,
    load_calibration,
    synthetic_poses,
)
from fastenerf.data.formats.native import save_scene
from fastenerf.data.rig import Turntable
from fastenerf.errors import InputError
from fastenerf.io import savez

PERIOD = 1_333_333  # 45 RPM


def truth(tilt_deg: float, **kw) -> TrajectoryConfig:
    d = dict(
        radius=0.6,
        center=[0.02, -0.05, 0.03],
        tilt_deg=tilt_deg,
        elevation_deg=15.0,
        period_us=PERIOD,
        phase_deg=30.0,
        clockwise=True,
    )
    d.update(kw)
    return TrajectoryConfig(**d)


def rot_err_deg(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Angle (degrees) of A_i^T B_i for rotation stacks (N, 3, 3)."""
    c = (np.einsum("nij,nij->n", A, B) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


@pytest.mark.parametrize("tilt", [2.85, 0.2388])  # the paper's two values
def test_recovers_the_papers_tilts(tilt):
    tr = truth(tilt)
    t, c2w = synthetic_poses(tr, 60, pos_noise=1e-3, rot_noise_deg=0.05, seed=7)
    fit = fit_turntable(c2w, t)
    f = fit.trajectory
    assert abs(f.tilt_deg - tilt) < 0.05
    assert abs(f.radius - tr.radius) < 2e-3
    assert abs(f.elevation_deg - tr.elevation_deg) < 0.05
    center_poses = fit.world_from_poses[:3, :3].T @ np.asarray(f.center)
    assert np.abs(center_poses - tr.center).max() < 3e-3
    assert fit.period_fitted and f.clockwise and abs(f.period_us / PERIOD - 1) < 1e-3
    # The fitted model reproduces the noise-free poses (mapped back into the poses' world).
    pred = np.linalg.inv(fit.world_from_poses) @ Turntable(f)(t)
    exact = Turntable(tr)(t)
    assert rot_err_deg(pred[:, :3, :3], exact[:, :3, :3]).max() < 0.1
    assert np.linalg.norm(pred[:, :3, 3] - exact[:, :3, 3], axis=1).max() < 3e-3
    # Residuals at the noise floor: optical axes pass within a few mm of the centre.
    r = fit.residuals
    assert r["axis_rms"] < 3e-3 and r["angle_rms_deg"] < 0.3 and r["roll_rms_deg"] < 0.1
    assert fit.iterations < 20


def test_exact_poses_fit_exactly():
    tr = truth(2.85, clockwise=False)
    t, c2w = synthetic_poses(tr, 12, seed=1)
    fit = fit_turntable(c2w, t)
    f = fit.trajectory
    assert abs(f.tilt_deg - 2.85) < 1e-6 and abs(f.radius - 0.6) < 1e-9
    assert np.allclose(f.center, tr.center, atol=1e-9) and abs(fit.world_yaw_deg) < 1e-6
    assert not f.clockwise and abs(f.period_us - PERIOD) <= 1
    assert fit.residuals["axis_rms"] < 1e-9 and fit.residuals["time_rms_deg"] < 1e-6
    np.testing.assert_allclose(Turntable(f)(t), c2w, atol=1e-7)


def test_axis_leaning_sideways_gives_a_world_yaw():
    """An axis with an x component: TrajectoryConfig tilts about x only, so the fit turns the
    world about +y and reports that rotation; the model reproduces the poses through it."""
    tr = truth(2.85)
    t, c2w = synthetic_poses(tr, 40, pos_noise=1e-3, rot_noise_deg=0.05, seed=2)
    a = math.radians(30.0)
    Ry = np.eye(4)
    Ry[[0, 0, 2, 2], [0, 2, 0, 2]] = [math.cos(a), math.sin(a), -math.sin(a), math.cos(a)]
    fit = fit_turntable(Ry @ c2w, t)
    assert abs(fit.world_yaw_deg + 30.0) < 1.0 and abs(fit.tilt_deg - 2.85) < 0.05
    pred = np.linalg.inv(fit.world_from_poses) @ Turntable(fit.trajectory)(t)
    exact = Ry @ Turntable(tr)(t)
    assert rot_err_deg(pred[:, :3, :3], exact[:, :3, :3]).max() < 0.1


def test_without_times_and_on_a_partial_arc():
    """A chequerboard is seen only from the front: poses over 120°, order = capture order."""
    tr = truth(2.85)
    t, c2w = synthetic_poses(
        tr, 40, t_span_us=PERIOD // 3, pos_noise=1e-3, rot_noise_deg=0.05, seed=4
    )
    fit = fit_turntable(c2w)
    assert not fit.period_fitted and fit.trajectory.clockwise
    assert 100 < fit.extras["arc_deg"] < 125
    assert abs(fit.tilt_deg - 2.85) < 0.1 and abs(fit.trajectory.radius - 0.6) < 5e-3
    steps = np.angle(np.exp(1j * np.radians(np.diff(fit.angles_deg))))
    assert np.all(steps < 0)  # clockwise: the angle decreases pose after pose


def test_compare_adam_and_least_squares(capsys):
    """The paper's Adam (+ lr on plateau) against closed form + least squares, same residuals.

    Measured here: both reach the same loss (to 1e-6 relative); least squares in ~4 iterations
    and tens of ms, Adam in ~1500 steps and seconds. Least squares is the default.
    """
    t, c2w = synthetic_poses(truth(2.85), 20, pos_noise=1e-3, rot_noise_deg=0.05, seed=5)
    fits = compare_solvers(c2w, t)
    lm, adam = fits["lm"], fits["adam"]
    with capsys.disabled():
        print()
        for name, f in fits.items():
            print(
                f"  {name:>24}: {f.iterations:5d} it {f.time_s:7.3f} s  loss "
                f"{f.loss_history[-1]:.6e}  tilt {f.tilt_deg:.4f}°  axis rms "
                f"{f.residuals['axis_rms']:.3e}"
            )
    assert lm.iterations <= 10 and adam.iterations >= 100 * lm.iterations
    assert adam.loss_history[-1] <= lm.loss_history[-1] * 1.01  # Adam does get there
    assert lm.loss_history[-1] <= adam.loss_history[-1] * (1 + 1e-6)  # and LM is the optimum
    assert abs(adam.tilt_deg - lm.tilt_deg) < 1e-3
    assert lm.time_s < adam.time_s
    assert np.all(np.diff(lm.loss_history[1:]) <= 1e-15)  # trust region: never goes up


def test_bad_poses_are_rejected():
    t, c2w = synthetic_poses(truth(1.0), 10, seed=0)
    with pytest.raises(InputError, match="at least 5"):
        fit_turntable(c2w[:4])
    bad = c2w.copy()
    bad[3, 0, 0] = np.nan
    with pytest.raises(InputError, match="pose 3 contains NaN"):
        fit_turntable(bad)
    bad = c2w.copy()
    bad[2, :3, :3] *= 2.0
    with pytest.raises(InputError, match="pose 2's rotation"):
        fit_turntable(bad)
    line = c2w.copy()
    line[:, :3, 3] = np.linspace(0, 1, 10)[:, None] * [1.0, 0.0, 0.0]
    with pytest.raises(InputError, match="on a line"):
        fit_turntable(line)
    with pytest.raises(InputError, match="increase strictly"):
        fit_turntable(c2w, t[::-1])


def test_calibrate_cli_writes_json_plot_and_scene(tmp_path, scene_config, random_stream):
    t, c2w = synthetic_poses(truth(2.85), 40, pos_noise=1e-3, rot_noise_deg=0.05, seed=6)
    savez(tmp_path / "poses.npz", c2w=c2w, t=t)
    scene = tmp_path / "scene"
    cfg = scene_config(width=16, height=12)
    save_scene(scene, cfg, random_stream(width=16, height=12))
    (scene / "import.json").write_text(json.dumps({"t_origin_us": 1000}))
    rc = cli(
        [
            "calibrate",
            str(tmp_path / "poses.npz"),
            "--out",
            str(tmp_path / "calib.json"),
            "--plot",
            str(tmp_path / "fit.png"),
            "--scene",
            str(scene),
        ]
    )
    assert rc == 0
    traj, d = load_calibration(tmp_path / "calib.json", frame="poses")
    assert abs(traj.tilt_deg - 2.85) < 0.05 and d["period_fitted"]
    assert (tmp_path / "fit.png").stat().st_size > 10_000
    import imageio.v3 as iio

    assert iio.imread(tmp_path / "fit.png").ndim == 3
    new = json.loads((scene / "scene.json").read_text())["trajectory"]
    assert new["tilt_deg"] == 0.0 and new["center"] == [0.0, 0.0, 0.0]  # turntable frame
    assert abs(new["radius"] - 0.6) < 2e-3 and new["clockwise"]
    assert new["t0_us"] == (traj.t0_us - 1000) % traj.period_us  # onto the scene's clock
    # Same angle at every time after the shift.
    a = Turntable(TrajectoryConfig(**{**new}))
    b = Turntable(traj)
    ts = np.array([1000, 500_000, 2_000_000])
    np.testing.assert_allclose(np.cos(a.angle(ts - 1000)), np.cos(b.angle(ts)), atol=1e-9)
    assert cli(["calibrate", str(tmp_path / "missing.npz"), "--out", str(tmp_path / "x.json")]) == 2


def test_tilt_convention_matches_the_rig():
    """α is the angle of the fitted axis from world +y toward +z, as `Turntable` applies it."""
    a = math.radians(2.85)
    axis = np.array([0.0, math.cos(a), math.sin(a)])  # R_x(α) applied to +y
    t, c2w = synthetic_poses(truth(2.85), 20, seed=9)
    fit = fit_turntable(c2w, t)
    np.testing.assert_allclose(fit.axis, axis, atol=1e-9)
