"""Pose refinement's optimiser and schedules (issue #20): the lazy row Adam moves only the
rows a batch saw and is Adam on them; the coarse-to-fine "gradient" mode leaves the field's
value and its parameters' gradients as without the schedule and weights only the gradient
w.r.t. positions; the pose lr waits for refine_start; the recovery of a known perturbation
holds with the row Adam too."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from test_self_calibration import ball, calibration_run  # noqa: F401  (ball is a fixture)

from fastenerf.coarse_to_fine import set_encoding_window
from fastenerf.config import TrainConfig
from fastenerf.errors import InputError
from fastenerf.perturb import perturb_poses
from fastenerf.pose_calibration import pose_lr
from fastenerf.pose_refine import RowAdam
from fastenerf.sampling import WindowSampler


def test_row_adam_moves_only_the_rows_seen_and_is_adam_on_them():
    torch.manual_seed(0)
    p = torch.nn.Parameter(torch.zeros(5, 6))
    ref = torch.nn.Parameter(torch.zeros(1, 6))  # row 2 under plain Adam, stepped when seen
    opt, ref_opt = RowAdam([p], lr=1e-2), torch.optim.Adam([ref], lr=1e-2, eps=1e-12)
    seen_steps = 0
    for step in range(12):
        g = torch.randn(5, 6)
        rows = torch.zeros(5, dtype=torch.bool)
        rows[2] = True
        rows[4] = step % 3 == 0
        p.grad = g.clone()  # every row has a gradient (a gauge fix gives all rows one)
        opt.step(rows)
        if rows[2]:
            ref.grad = g[2:3].clone()
            ref_opt.step()
            seen_steps += 1
    assert torch.equal(p[[0, 1, 3]].detach(), torch.zeros(3, 6))  # never seen: never moved
    torch.testing.assert_close(p[2:3].detach(), ref.detach(), rtol=1e-5, atol=1e-7)
    assert opt.state[p]["row_steps"][:, 0].tolist() == [0, 0, 12, 0, 4]
    # plain Adam moves the unseen rows on their momentum after one visit
    q = torch.nn.Parameter(torch.zeros(5, 6))
    adam = torch.optim.Adam([q], lr=1e-2, eps=1e-12)
    q.grad = torch.zeros(5, 6)
    q.grad[0] = 1.0
    adam.step()
    q.grad = torch.zeros(5, 6)
    before = q[0].detach().clone()
    adam.step()
    assert (q[0] - before).abs().max() > 0.5e-2  # a full-size step with a zero gradient


@pytest.mark.parametrize("fused", [True, False])
def test_row_adam_gate_holds_noise_and_passes_a_consistent_gradient(fused):
    """refine_gate: rows whose gradient is zero-mean noise (a pose already right) walk far less
    than under plain row Adam, whose m̂/√v̂ is ±1 on a row's first visits and ~0.23 on noise
    after (measured: ÷5.5 at gate 1.5); rows with a steady gradient under the same noise (SNR
    1) move nearly as far (90 %)."""
    gen = torch.Generator().manual_seed(3)
    rows, visits = 64, 300
    mean = torch.zeros(rows, 6)
    mean[rows // 2 :] = 1.0  # the second half: a consistent pull
    grads = [mean + torch.randn(rows, 6, generator=gen) for _ in range(visits)]
    moved = {}
    for gate in (0.0, 1.5):
        p = torch.nn.Parameter(torch.zeros(rows, 6))
        opt = RowAdam([p], lr=1e-3, fused=fused, gate=gate)
        for g in grads:
            p.grad = g.clone()
            opt.step(torch.ones(rows, dtype=torch.bool))
        moved[gate] = p.detach().abs()
    noise_plain, noise_gated = (m[: rows // 2].mean() for m in moved.values())
    signal_plain, signal_gated = (m[rows // 2 :].mean() for m in moved.values())
    assert noise_gated < 0.3 * noise_plain, (noise_gated, noise_plain)
    assert signal_gated > 0.8 * signal_plain, (signal_gated, signal_plain)


def test_row_adam_state_round_trips():
    p = torch.nn.Parameter(torch.zeros(3, 2))
    opt = RowAdam([p], lr=1e-2)
    p.grad = torch.ones(3, 2)
    opt.step(torch.tensor([True, False, True]))
    again = RowAdam([p], lr=1e-2)
    again.load_state_dict(opt.state_dict())
    torch.testing.assert_close(again.state[p]["exp_avg_sq"], opt.state[p]["exp_avg_sq"])


def test_pose_lr_waits_for_refine_start_then_decays():
    c = TrainConfig(refine_lr=1e-2, refine_lr_final=1e-4, refine_start=0.2, refine_warmup=0)
    assert pose_lr(c, 0.0) == 0.0 and pose_lr(c, 0.19) == 0.0
    assert pose_lr(c, 0.2) == pytest.approx(1e-2)
    assert pose_lr(c, 0.6) == pytest.approx(1e-3)
    assert pose_lr(c, 1.0) == pytest.approx(1e-4)
    w = TrainConfig(refine_lr=1e-2, refine_lr_final=1e-2, refine_start=0.2, refine_warmup=0.5)
    assert pose_lr(w, 0.2) == 0.0 and pose_lr(w, 0.4) == pytest.approx(0.5e-2)
    assert pose_lr(w, 0.6) == pytest.approx(1e-2) == pose_lr(w, 1.0)
    with pytest.raises(InputError, match="refine_start"):
        TrainConfig(refine_start=1.0).validate()
    with pytest.raises(InputError, match="refine_c2f_mode"):
        TrainConfig(refine_c2f_mode="both").validate()
    with pytest.raises(InputError, match="refine_optimizer"):
        TrainConfig(refine_optimizer="sgd").validate()


def _grads(field, backend, x):
    """(value, d value / d x, d value / d parameters) of a fixed function of the density."""
    x = x.clone().requires_grad_(True)
    field.zero_grad()
    v = field.density(x)
    (v * torch.linspace(0.5, 1.5, len(v))).sum().backward()
    net = None if backend == "ngp" else (field.fine or field.coarse)
    params = field.table if backend == "ngp" else next(net.parameters())
    return v.detach(), x.grad.clone(), params.grad.clone()


@pytest.mark.parametrize("backend", ["ngp", "vanilla"])
def test_gradient_mode_weights_only_the_position_gradient(backend, scene_config):
    from fastenerf.fields import make_field

    sc = scene_config(32, 24)
    opts = {"ngp": {"n_levels": 4, "log2_table_size": 10, "max_resolution": 32}, "vanilla": {}}
    field = make_field(backend, sc, TrainConfig(backend=backend, backend_options=opts[backend]))
    with torch.no_grad():  # a non-trivial table (it starts near zero)
        for prm in field.parameters():
            prm.add_(0.3 * torch.randn_like(prm))
    x = torch.rand(64, 3) * 1.2 - 0.6
    set_encoding_window(field, 1.0, 0.1, 0.5)  # every level on: no weights
    v_all, gx_all, gp_all = _grads(field, backend, x)
    set_encoding_window(field, 0.2, 0.1, 0.5, "field")  # BARF: value and all gradients weighted
    v_barf, gx_barf, _ = _grads(field, backend, x)
    set_encoding_window(field, 0.2, 0.1, 0.5, "gradient")
    v_g, gx_g, gp_g = _grads(field, backend, x)
    torch.testing.assert_close(v_g, v_all)  # the field sees every level
    torch.testing.assert_close(gp_g, gp_all)  # and learns every level
    assert not torch.allclose(v_barf, v_all)
    assert not torch.allclose(gx_g, gx_all)  # the position gradient is weighted ...
    # ... and with the field's weights only in the gradient, it is BARF's position gradient
    # of a field whose value had every level: not equal to BARF's, but the same fine-level cut
    assert gx_g.norm() < gx_all.norm()
    with torch.no_grad():  # outside training (no position gradient) the value is the full one
        torch.testing.assert_close(field.density(x), v_all)
    assert gx_barf.shape == gx_g.shape


@pytest.mark.slow
def test_row_adam_recovers_a_known_perturbation(ball):  # noqa: F811
    cfg, rig, events = ball
    grid_t = WindowSampler(cfg.n_views, 0, cfg.t_end_us, 1, 4).grid_times(np.arange(41))
    bad_rig, _ = perturb_poses(rig, 2.0, seed=5, grid_t=grid_t)
    true_c2w = torch.as_tensor(rig.pose(grid_t))
    tc = TrainConfig(
        refine_poses=True,
        refine_optimizer="row-adam",
        refine_lr=1e-2,
        refine_lr_final=1e-3,
        refine_start=0.1,
        refine_warmup=0.1,
        refine_gauge="none",
        refine_translation=True,
        refine_decay=0.0,
    )
    cal, _ = calibration_run(cfg, tc, events, bad_rig, 120, true_c2w)
    st = cal.stats()
    assert st["pose_error_deg"] < 0.8, st
    assert st["pose_centre_error"] < 0.05, st


def _pose_calibration(**cfg):
    from test_self_calibration import BallField, ball_scene

    from fastenerf.data.events import EventIndex, EventStream
    from fastenerf.data.rig import Rig
    from fastenerf.sampling import RaySampler
    from fastenerf.self_calibration import SelfCalibration

    scene = ball_scene(n_views=6)
    stream = EventStream.from_arrays([1, 2], [1, 2], [1000, 2000], [1, -1], 48, 36)
    index = EventIndex(stream, 0.25, 0.25, t_start=0, t_end=6000, loop=True)
    windows = WindowSampler(6, 0, 6000, 1, 2)
    s = RaySampler(
        index, Rig.from_scene(scene), windows, rays_per_step=8, windows_per_step=2,
        neg_ratio=0.5, use_kernel=False, with_poses=True,
    )  # fmt: skip
    return SelfCalibration(TrainConfig(refine_poses=True, **cfg), s, (0.25, 0.25), BallField())


@pytest.mark.parametrize("optimizer", ["row-adam", "adam"])
def test_decay_pulls_only_the_rows_seen_back_and_skips_with_the_step(optimizer):
    """refine_decay shrinks the corrections of the rows the batch saw by lr x decay (a row's
    gradient is zero here, so Adam moves nothing), leaves the others, and a non-finite step
    (found_inf) shrinks nothing; with the row Adam (its step's decay) and with plain Adam
    (`_decay`; fused, as a device-paced step has it, to skip on found_inf)."""
    cal = _pose_calibration(
        refine_decay=40.0, refine_lr=1e-2, refine_warmup=0.0, refine_optimizer=optimizer,
        step_mode="device",
    )  # fmt: skip
    cal.before_step(progress=0.5, field_lr_scale=1.0)
    lr = pose_lr(cal.cfg, 0.5)
    start = torch.randn_like(cal.poses.delta) * 0.01
    cal.poses.delta.data.copy_(start)
    seen = torch.zeros(len(start), dtype=torch.bool)
    seen[[1, 3]] = True
    cal.pose_cal.seen = seen
    cal.poses.delta.grad = torch.zeros_like(start)
    assert cal.step(found_inf=torch.tensor(1.0))
    assert torch.equal(cal.poses.delta.detach(), start)  # skipped: nothing moves
    cal.poses.delta.grad = torch.zeros_like(start)
    assert cal.step()
    want = torch.where(seen[:, None], start * (1 - lr * 40.0), start)
    torch.testing.assert_close(cal.poses.delta.detach(), want, rtol=1e-6, atol=0)
    off = _pose_calibration(refine_decay=0.0)
    off.before_step(progress=0.5, field_lr_scale=1.0)
    off.poses.delta.data.copy_(start)
    off.pose_cal.seen, off.poses.delta.grad = seen, torch.zeros_like(start)
    off.step()
    assert torch.equal(off.poses.delta.detach(), start)


def test_refining_raises_the_windows_per_step(scene_config):
    """With refine_poses a run draws at least refine_windows_per_step windows (no more than
    its rays); without it, the preset's."""
    from fastenerf.config import train_preset

    sc = scene_config(64, 48)
    plain = train_preset("fast", "ngp", rays_per_step=512).resolved(sc)
    assert plain.windows_per_step == 16
    ref = train_preset("fast", "ngp", rays_per_step=512, refine_poses=True).resolved(sc)
    assert ref.windows_per_step == 64
    few = train_preset("fast", "ngp", rays_per_step=32, refine_poses=True).resolved(sc)
    assert few.windows_per_step == 32
    more = train_preset("fast", "ngp", windows_per_step=128, refine_poses=True).resolved(sc)
    assert more.windows_per_step == 128


def test_the_motion_prior_sets_the_refinement_batch_and_decay(scene_config):
    """Unset, refine_windows_per_step and refine_decay are 64 and 30 alone and 16 and 0 after
    smooth_poses, in the resolved config (what a run records) and in SelfCalibration's decay
    (tests build it unresolved); a value given is kept either way."""
    from fastenerf.config import train_preset

    sc, kw = scene_config(64, 48), {"rays_per_step": 512, "refine_poses": True}
    alone = train_preset("fast", "ngp", **kw).resolved(sc)
    assert (alone.refine_windows_per_step, alone.refine_decay) == (64, 30.0)
    prior = train_preset("fast", "ngp", smooth_poses=5, **kw).resolved(sc)
    assert (prior.refine_windows_per_step, prior.refine_decay) == (16, 0.0)
    assert prior.windows_per_step == 16
    given = dict(refine_windows_per_step=32, refine_decay=5.0, smooth_poses=5, **kw)
    kept = train_preset("fast", "ngp", **given).resolved(sc)
    assert (kept.refine_windows_per_step, kept.refine_decay, kept.windows_per_step) == (32, 5, 32)
    assert _pose_calibration().pose_cal.decay == 30.0
    assert _pose_calibration(smooth_poses=5).pose_cal.decay == 0.0
    assert _pose_calibration(smooth_poses=5, refine_decay=7.0).pose_cal.decay == 7.0


def _old_step(cal, found_inf):
    """SelfCalibration.step's pose part as it was: the row Adam's step, then `_decay`."""
    cal.pose_optimizer.step(cal.pose_cal.seen, found_inf=found_inf)
    cal.pose_cal._decay(found_inf)


@pytest.mark.parametrize("fused", [True, False])
def test_row_adam_decay_is_the_old_step_then_decay(fused, monkeypatch):
    """The row Adam's decay (one launch) gives the corrections of its step followed by the
    separate `_decay` ops, over steps with changing lr, rows and a skipped one; the
    hot path runs no `_decay`. The decay matters here: without it they differ."""
    kw = {"refine_decay": 40.0, "refine_lr": 2e-2, "refine_warmup": 0.0, "step_mode": "device"}
    new, old, plain = (_pose_calibration(**kw) for _ in range(3))
    gen = torch.Generator().manual_seed(3)
    start = torch.randn(new.poses.delta.shape, generator=gen) * 0.01
    for cal in (new, old, plain):
        cal.pose_optimizer.fused = fused
        cal.poses.delta.data.copy_(start)
    monkeypatch.setattr(new.pose_cal, "_decay", lambda *_: pytest.fail("decay outside the step"))
    for step in range(6):
        grad = torch.randn(start.shape, generator=gen) * 1e-3
        seen = torch.rand(len(start), generator=gen) < 0.5
        found_inf = torch.tensor(float(step == 2))
        for cal in (new, old, plain):
            cal.before_step(progress=0.3 + 0.1 * step, field_lr_scale=1.0)
            cal.pose_cal.seen, cal.poses.delta.grad = seen, grad.clone()
        assert new.step(found_inf=found_inf)
        _old_step(old, found_inf)
        plain.pose_optimizer.step(seen, found_inf=found_inf)  # no decay at all
        torch.testing.assert_close(new.poses.delta, old.poses.delta, rtol=1e-6, atol=1e-10)
    assert (new.poses.delta - plain.poses.delta).abs().max() > 1e-4
    steps = new.pose_optimizer.state[new.poses.delta]["row_steps"]
    assert torch.equal(steps, old.pose_optimizer.state[old.poses.delta]["row_steps"])
    assert 0 < steps.max() <= 5  # the skipped step counted for no row


def test_decay_without_a_row_adam_step_still_happens():
    """No pose gradient (the row Adam skips the parameter): `_decay` still shrinks the
    rows seen; a pose lr of 0 (before refine_start) leaves every bit."""
    cal = _pose_calibration(refine_decay=40.0, refine_lr=1e-2, refine_warmup=0.0)
    start = torch.randn_like(cal.poses.delta) * 0.01
    cal.poses.delta.data.copy_(start)
    cal.pose_cal.seen = torch.arange(len(start)) % 2 == 0
    cal.before_step(progress=0.0, field_lr_scale=1.0)  # lr 0
    cal.poses.delta.grad = torch.ones_like(start)
    assert cal.step() and torch.equal(cal.poses.delta.detach(), start)
    cal.before_step(progress=0.5, field_lr_scale=1.0)
    cal.zero_grad()
    assert cal.step()
    rate = pose_lr(cal.cfg, 0.5) * 40.0
    want = torch.where(cal.pose_cal.seen[:, None], start * (1 - rate), start)
    torch.testing.assert_close(cal.poses.delta.detach(), want, rtol=1e-6, atol=0)


@pytest.mark.slow
def test_shared_row_recovers_a_mount_error(ball):  # noqa: F811
    """A camera mis-mounted by 2° (one camera-frame turn of every pose): refine_shared learns
    it as one row (no gauge, whatever refine_gauge says) and every pose ends well below 2°;
    per-pose rows on the same run leave some poses far off."""
    from fastenerf.perturb import perturb_mount

    cfg, rig, events = ball
    grid_t = WindowSampler(cfg.n_views, 0, cfg.t_end_us, 1, 4).grid_times(np.arange(41))
    bad_rig, report = perturb_mount(rig, 2.0, seed=5, grid_t=grid_t)
    true_c2w = torch.as_tensor(rig.pose(grid_t))
    assert abs(report["measured_min_deg"] - 2.0) < 1e-9 and report["grid"]["poses"] == 41
    knobs = dict(refine_poses=True, refine_lr=5e-3, refine_lr_final=5e-4, refine_start=0.0)
    knobs.update(refine_warmup=0.0, refine_decay=0.0)
    tc = TrainConfig(refine_shared=True, refine_gauge="mean", **knobs)
    cal, _ = calibration_run(cfg, tc, events, bad_rig, 60, true_c2w)
    assert cal.poses.delta.shape == (1, 6) and cal.poses.gauge == "none"
    assert cal.report()["poses"]["shared"] and cal.report()["poses"]["rows"] == 1
    st = cal.stats()
    assert st["pose_error_max_deg"] < 0.5, st  # from 2° at every pose
    assert abs(st["pose_correction_deg"] - st["pose_correction_max_deg"]) < 1e-5  # one turn
    per_pose, _ = calibration_run(
        cfg, TrainConfig(refine_gauge="none", **knobs), events, bad_rig, 60, true_c2w
    )
    assert per_pose.stats()["pose_error_max_deg"] > 2 * st["pose_error_max_deg"], st


def _grid_poses(n: int, seed: int = 0) -> torch.Tensor:
    """(n + 1, 4, 4) float64 camera-to-world poses on an orbit (a loop: last = first)."""
    from scipy.spatial.transform import Rotation

    a = np.linspace(0.0, 360.0, n + 1)
    R = Rotation.from_euler("zx", np.stack([a, np.full(n + 1, -110.0)], 1), degrees=True)
    c2w = np.tile(np.eye(4), (n + 1, 1, 1))
    c2w[:, :3, :3] = R.as_matrix()
    c2w[:, :3, 3] = 4.0 * np.stack([np.sin(np.radians(a)), -np.cos(np.radians(a)), 0 * a], 1)
    return torch.from_numpy(c2w)


def test_mean_world_rotation_is_the_shared_turn_not_the_jitter():
    """R_a = W · R_b · (own small turn): Procrustes gives W back to well under the jitter
    (which averages out), ignores rows of weight 0, and is a proper rotation."""
    from scipy.spatial.transform import Rotation

    from fastenerf.se3 import mean_world_rotation, relative_angle_deg

    gen = np.random.default_rng(3)
    R_b = torch.from_numpy(Rotation.random(400, random_state=4).as_matrix())
    W = torch.from_numpy(Rotation.from_rotvec([0.01, -0.02, 0.005]).as_matrix())
    jitter = torch.from_numpy(Rotation.from_rotvec(gen.normal(0, 0.01, (400, 3))).as_matrix())
    R_a = W @ R_b @ jitter
    R_a[:10] = torch.from_numpy(Rotation.random(10, random_state=5).as_matrix())  # outliers
    w = torch.ones(400, dtype=torch.float64)
    w[:10] = 0
    est = mean_world_rotation(R_a, R_b, w)
    assert float(relative_angle_deg(est, W)) < 0.1  # the jitter is 0.57° per axis
    assert float(relative_angle_deg(mean_world_rotation(R_a, R_b), W)) > 0.1  # outliers in
    assert torch.allclose(est @ est.T, torch.eye(3, dtype=est.dtype), atol=1e-12)
    assert float(torch.linalg.det(est)) == pytest.approx(1.0)


def test_refiner_stats_on_device_call_no_solver_that_waits(monkeypatch):
    """With true poses, the device-paced step's stats must not wait for the device: on CUDA
    torch's SVD, eigen-solvers and determinant check their errors on the host, and that wait
    was not charged to the training clock (a "60 s" run at 1° trained 361 s). The stats are
    the same with those solvers barred."""
    from scipy.spatial.transform import Rotation

    from fastenerf.pose_refine import PoseRefiner

    true = _grid_poses(40)
    given = true.clone()
    turn = Rotation.from_rotvec(np.random.default_rng(0).normal(0, 0.01, (41, 3))).as_matrix()
    given[:, :3, :3] = true[:, :3, :3] @ torch.from_numpy(turn)
    pr = PoseRefiner(given, torch.ones(41, dtype=torch.bool), "none", true_c2w=true)
    before = pr.stats()

    def barred(*a, **k):
        raise AssertionError("a solver that waits for the device")

    for name in ("svd", "eigh", "eig", "det", "slogdet", "inv", "solve"):
        monkeypatch.setattr(torch.linalg, name, barred)
    on_device = pr.stats(on_device=True)
    assert all(torch.is_tensor(v) for v in on_device.values())
    for k, v in before.items():
        assert float(on_device[k]) == pytest.approx(v, rel=1e-5, abs=1e-6), k


def test_refiner_reports_the_shared_turn_and_the_error_without_it():
    """Poses given as W · truth (one world turn about every centre) and not corrected: the
    error is all shared (pose_gauge_deg = the turn, nothing left aligned); a per-pose error
    on top is what is left aligned."""
    from scipy.spatial.transform import Rotation

    from fastenerf.pose_refine import PoseRefiner

    true = _grid_poses(60)
    used = torch.tensor([True] * 60 + [False])
    W = torch.from_numpy(Rotation.from_rotvec(np.radians([0.3, 0.0, -0.4])).as_matrix())
    given = true.clone()
    given[:, :3, :3] = W @ true[:, :3, :3]
    st = PoseRefiner(given, used, "mean", true_c2w=true).stats()
    assert st["pose_error_deg"] == pytest.approx(0.5, abs=1e-4)
    assert st["pose_gauge_deg"] == pytest.approx(0.5, abs=1e-4)
    assert st["pose_error_aligned_deg"] < 1e-4
    # W itself, as a rotation vector (radians): what a study turns its test views by
    got = [st[f"pose_gauge_w{a}"] for a in "xyz"]
    np.testing.assert_allclose(got, np.radians([0.3, 0.0, -0.4]), atol=1e-7)
    assert "pose_gauge_wx" not in PoseRefiner(given, used, "mean").stats()  # no truth, no W
    jit = torch.from_numpy(
        Rotation.from_rotvec(np.radians(np.tile([0.2, 0, 0], (61, 1)))).as_matrix()
    )
    jit[::2] = jit[::2].transpose(-1, -2)  # ±0.2° about the camera x axis, alternating
    given[:, :3, :3] = given[:, :3, :3] @ jit
    pr = PoseRefiner(given, used, "mean", true_c2w=true)
    with torch.no_grad():
        pr.delta.copy_(torch.randn(61, 6) * 1e-3)
    st = pr.stats()
    assert st["pose_error_aligned_deg"] < st["pose_error_deg"]


def test_jitter_is_the_pose_to_pose_part_of_the_error():
    """pose_jitter_deg: ~0 for an error smooth along the path (a world turn shared by every
    pose, or one growing slowly along it), about the error itself for an error each pose has
    on its own (random axes), and unused rows (a loop's twin) are no neighbours."""
    from scipy.spatial.transform import Rotation

    from fastenerf.pose_refine import PoseRefiner

    n = 200
    true = _grid_poses(n)
    used = torch.tensor([True] * n + [False])

    def turned(rotvecs_deg):
        given = true.clone()
        R = torch.from_numpy(Rotation.from_rotvec(np.radians(rotvecs_deg)).as_matrix())
        given[:, :3, :3] = R @ true[:, :3, :3]
        return PoseRefiner(given, used, "none", true_c2w=true, translation=False).stats()

    smooth = np.outer(np.sin(np.linspace(0, np.pi, n + 1)), [0.3, -0.2, 0.1])
    st = turned(smooth)
    assert st["pose_error_deg"] > 0.2 and st["pose_jitter_deg"] < 0.01
    axes = np.random.default_rng(0).normal(size=(n + 1, 3))
    per_pose = 0.05 * axes / np.linalg.norm(axes, axis=1, keepdims=True)
    st = turned(per_pose)
    assert st["pose_error_deg"] == pytest.approx(0.05, rel=1e-3)
    assert 0.035 < st["pose_jitter_deg"] < 0.065  # √(2 - 2 cos) of two random axes, over √2
    far = per_pose.copy()
    far[-1] = [30.0, 0, 0]  # the unused twin row: no neighbour of the last used one
    assert turned(far)["pose_jitter_deg"] == pytest.approx(st["pose_jitter_deg"], rel=1e-6)


def test_smooth_turns_take_out_each_rows_own_noise_and_keep_a_smooth_correction():
    """Rows whose corrections are a smooth turn along the path plus each row's own noise:
    smooth_turns(21) leaves the smooth part (its error against the smooth-only corrections a
    fraction of the noise), the jitter a fraction of what it was; the loop's unused twin row
    and the shifts stay as they were; knots are refused."""
    from scipy.spatial.transform import Rotation

    from fastenerf.pose_refine import PoseRefiner

    n = 200
    true = _grid_poses(n).float()
    used = torch.tensor([True] * n + [False])
    t = np.linspace(0, 2 * np.pi, n + 1)
    smooth = np.radians(0.2) * np.stack([np.sin(t), np.cos(2 * t), 0.5 * np.sin(3 * t)], 1)
    noise = np.random.default_rng(1).normal(0, np.radians(0.03), (n + 1, 3))
    given = true.clone()  # the truth turned back by the smooth error
    back = torch.from_numpy(Rotation.from_rotvec(-smooth).as_matrix()).float()
    given[:, :3, :3] = back @ true[:, :3, :3]

    def refiner(turns):
        pr = PoseRefiner(given, used, "none", true_c2w=true, translation=True)
        R = given[:, :3, :3].double()
        with torch.no_grad():  # camera-frame rows whose world-frame turns are `turns`
            pr.delta[:, :3] = torch.einsum("gji,gj->gi", R, torch.from_numpy(turns)).float()
            pr.delta[:, 3:] = 0.01
            pr.delta[-1] = 0.0
        return pr

    clean, noisy = refiner(smooth), refiner(smooth + noise)
    before = noisy.stats()
    assert clean.stats()["pose_error_deg"] < 1e-3 and before["pose_jitter_deg"] > 0.03
    noisy.smooth_turns(21)
    after = noisy.stats()
    assert after["pose_jitter_deg"] < 0.2 * before["pose_jitter_deg"]
    assert after["pose_error_deg"] < 0.35 * before["pose_error_deg"]
    assert torch.equal(noisy.delta[:n, 3:], torch.full((n, 3), 0.01))
    assert torch.equal(noisy.delta[-1], torch.zeros(6))
    knots = PoseRefiner(given, used, "none", knots=8)
    with pytest.raises(ValueError, match="a correction per row"):
        knots.smooth_turns(21)


@pytest.mark.parametrize("loop", [True, False])
def test_knot_matrix_interpolates_linearly_between_neighbouring_knots(loop):
    from fastenerf.pose_refine import knot_matrix

    rows, knots = 41, 8
    B = knot_matrix(rows, knots, loop).double()
    assert B.shape == (rows, knots) and torch.allclose(B.sum(1), torch.ones(rows, dtype=B.dtype))
    assert ((B > 0).sum(1) <= 2).all()
    values = torch.randn(knots, dtype=torch.float64)
    path = B @ values
    span = (rows - 1) / (knots if loop else knots - 1)
    x = torch.arange(rows, dtype=torch.float64) / span
    ends = torch.cat([values, values[:1]]) if loop else values
    want = torch.from_numpy(np.interp(x.numpy(), np.arange(len(ends)), ends.numpy()))
    torch.testing.assert_close(path, want)
    assert (path[0] == path[-1]) == loop or not loop  # a loop's twin row is its first
    with pytest.raises(ValueError, match="knots"):
        knot_matrix(rows, 1, loop)
    with pytest.raises(ValueError, match="knots"):
        knot_matrix(rows, rows + 1 - int(loop), loop)


def _same_rays_and_grads(refiner, rows, gen, fused):
    """Rays of windows 2→3 and 3→4 through `refiner` and the per-row `rows` holding the same
    corrections: asserts they are the same rays; returns each one's (rays_o, rays_d, rows
    seen, gradient of delta) for one scalar of both."""
    dirs = torch.nn.functional.normalize(torch.randn(6, 3, generator=gen), dim=-1)
    idx = torch.tensor([2] * 3 + [3] * 3 + [3] * 3 + [4] * 3)
    out = []
    for pr in (refiner, rows):
        o, d, seen = pr.rays_and_rows(dirs, idx, fused=fused)
        (o.sum() + (d * torch.arange(3.0)).sum()).backward()
        out.append((o.detach(), d.detach(), seen, pr.delta.grad))
    torch.testing.assert_close(out[0][0], out[1][0])
    torch.testing.assert_close(out[0][1], out[1][1])
    return out


@pytest.mark.parametrize("fused", [True, False])
def test_knots_give_the_rays_and_gradients_of_their_interpolated_rows(fused):
    """A refiner with knots is the per-row refiner whose rows are B · knots: same rays, the
    knots' gradient is Bᵀ times the rows', and the rows a batch sees step their knots only."""
    from fastenerf.pose_refine import PoseRefiner, knot_matrix

    G, K = 21, 5
    c2w = _grid_poses(G - 1).float()
    used = torch.ones(G, dtype=torch.bool)
    used[-1] = False
    gen = torch.Generator().manual_seed(3)
    knotted = PoseRefiner(c2w, used, "none", knots=K)
    rows = PoseRefiner(c2w, used, "none")
    B = knot_matrix(G, K, loop=True)
    with torch.no_grad():
        knotted.delta.copy_(0.02 * torch.randn(K, 6, generator=gen))
        rows.delta.copy_(B @ knotted.delta)
    out = _same_rays_and_grads(knotted, rows, gen, fused)
    torch.testing.assert_close(out[0][3], B.T @ out[1][3], rtol=1e-5, atol=1e-7)
    assert out[0][2].shape == (K,) and out[0][2].tolist() == [True, True, False, False, False]
    assert torch.equal(knotted.row_delta()[-1], knotted.row_delta()[0])  # the loop's twin


@pytest.mark.parametrize("fused", [True, False])
def test_knot_rows_add_each_rows_own_correction_to_the_knots(fused):
    """knot_rows: the grid's rows and then the knots in one (G + K, 6) parameter; the rays are
    those of rows B · knots + own; the rows' part of the gradient is the per-row refiner's and
    the knots' Bᵀ times it; a batch steps the rows it sees and their knots."""
    from fastenerf.pose_refine import PoseRefiner, knot_matrix

    G, K = 21, 5
    c2w = _grid_poses(G - 1).float()
    used = torch.ones(G, dtype=torch.bool)
    used[-1] = False
    gen = torch.Generator().manual_seed(4)
    both = PoseRefiner(c2w, used, "none", knots=K, knot_rows=True)
    rows = PoseRefiner(c2w, used, "none")
    B = knot_matrix(G, K, loop=True)
    assert both.delta.shape == (G + K, 6) and not both.delta.detach().any()
    with torch.no_grad():
        both.delta.copy_(0.02 * torch.randn(G + K, 6, generator=gen))
        rows.delta.copy_(both.delta[:G] + B @ both.delta[G:])
    out = _same_rays_and_grads(both, rows, gen, fused)
    torch.testing.assert_close(out[0][3][:G], out[1][3], rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(out[0][3][G:], B.T @ out[1][3], rtol=1e-5, atol=1e-7)
    assert out[0][2].shape == (G + K,)
    assert out[0][2][:G].tolist() == [i in (2, 3, 4) for i in range(G)]
    assert out[0][2][G:].tolist() == [True, True, False, False, False]
    with pytest.raises(ValueError, match="knot_rows"):
        PoseRefiner(c2w, used, "none", knot_rows=True)
    with pytest.raises(InputError, match="refine_knot_rows"):
        TrainConfig(refine_poses=True, refine_knot_rows=True).validate("train")


def test_knots_are_checked_against_the_grid_and_the_shared_row(scene_config):
    from fastenerf.pose_calibration import check_knots

    with pytest.raises(InputError, match="refine_knots"):
        check_knots(41, 41)
    check_knots(40, 41)
    with pytest.raises(InputError, match="refine_knots"):
        TrainConfig(refine_poses=True, refine_knots=1).validate("train")
    with pytest.raises(InputError, match="refine_knots"):
        TrainConfig(refine_poses=True, refine_shared=True, refine_knots=4).validate("train")


@pytest.mark.slow
def test_knots_recover_a_smooth_error_that_rows_leave(ball):  # noqa: F811
    """A 2° mount error is the smoothest error along the path: 5 knots learn it from pooled
    gradients, per-pose rows on the same run leave some poses far off (as for the shared
    row above)."""
    from fastenerf.perturb import perturb_mount

    cfg, rig, events = ball
    grid_t = WindowSampler(cfg.n_views, 0, cfg.t_end_us, 1, 4).grid_times(np.arange(41))
    bad_rig, _ = perturb_mount(rig, 2.0, seed=5, grid_t=grid_t)
    true_c2w = torch.as_tensor(rig.pose(grid_t))
    knobs = dict(refine_poses=True, refine_lr=5e-3, refine_lr_final=5e-4, refine_start=0.0)
    knobs.update(refine_warmup=0.0, refine_decay=0.0, refine_gauge="none")
    cal, _ = calibration_run(
        cfg, TrainConfig(refine_knots=5, **knobs), events, bad_rig, 60, true_c2w
    )
    assert cal.poses.delta.shape == (5, 6) and cal.report()["poses"]["knots"] == 5
    st = cal.stats()
    assert st["pose_error_max_deg"] < 0.6, st  # from 2° at every pose
    per_pose, _ = calibration_run(cfg, TrainConfig(**knobs), events, bad_rig, 60, true_c2w)
    assert per_pose.stats()["pose_error_max_deg"] > 2 * st["pose_error_max_deg"], st
