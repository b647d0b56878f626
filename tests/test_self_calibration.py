"""Self-calibration (issue #20): pose refinement recovers a known perturbation, thresholds stay
positive and finite, the ratio of biased thresholds is estimated, both options are recorded
and checkpointed, and with both off a training step is what it was before.

The pose and ratio tests train only the calibration against a frozen field: a smooth textured
ball evaluated in closed form (`BallField`), whose events come from the real simulator on the
real sampler's pose grid, so the only unknowns are the ones being learnt."""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from fastenerf.coarse_to_fine import cosine_window, set_encoding_window
from fastenerf.config import (
    IntrinsicsConfig,
    PerturbConfig,
    SceneConfig,
    TrainConfig,
    TrajectoryConfig,
)
from fastenerf.data.events import EventIndex
from fastenerf.data.formats.native import load_scene
from fastenerf.data.rig import Rig
from fastenerf.data.synth.simulator import EventSimulator, SimulatorConfig
from fastenerf.errors import InputError
from fastenerf.fields.base import Field
from fastenerf.losses import event_loss, total_loss
from fastenerf.perturb import perturb_poses
from fastenerf.pose_calibration import used_rows
from fastenerf.pose_refine import PoseRefiner
from fastenerf.render import camera_directions, generate_rays
from fastenerf.sampling import RaySampler, WindowSampler
from fastenerf.se3 import relative_angle_deg, so3_exp
from fastenerf.self_calibration import SelfCalibration
from fastenerf.threshold import C_MAX, C_MIN, ThresholdEstimator
from fastenerf.train import Trainer

# ---------------------------------------------------------------------------------- rotations


def test_so3_exp_matches_scipy_from_tiny_to_large_angles():
    rng = np.random.default_rng(0)
    axes = rng.normal(size=(40, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    w = axes * np.geomspace(1e-9, 3.0, 40)[:, None]
    got = so3_exp(torch.from_numpy(w)).numpy()
    np.testing.assert_allclose(got, Rotation.from_rotvec(w).as_matrix(), atol=1e-14)
    ang = relative_angle_deg(torch.eye(3, dtype=torch.float64), torch.from_numpy(got)).numpy()
    np.testing.assert_allclose(ang, np.rad2deg(np.geomspace(1e-9, 3.0, 40)), rtol=1e-9)


def test_so3_log_inverts_so3_exp_from_zero_to_large_angles():
    from fastenerf.se3 import so3_log

    rng = np.random.default_rng(1)
    axes = rng.normal(size=(40, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    w = axes * np.concatenate([[0.0], np.geomspace(1e-12, 3.0, 39)])[:, None]
    got = so3_log(so3_exp(torch.from_numpy(w))).numpy()
    np.testing.assert_allclose(got, w, atol=1e-12, rtol=1e-9)
    np.testing.assert_allclose(
        got, Rotation.from_matrix(so3_exp(torch.from_numpy(w)).numpy()).as_rotvec(), atol=1e-12
    )
    assert np.isfinite(got).all()


def test_so3_exp_gradient_is_finite_at_zero():
    """Every correction starts at ω = 0, where the textbook sin θ / θ has a NaN gradient."""
    w = torch.zeros(4, 3, dtype=torch.float64, requires_grad=True)
    (so3_exp(w) * torch.arange(36.0, dtype=torch.float64).reshape(4, 3, 3)).sum().backward()
    assert torch.isfinite(w.grad).all() and w.grad.abs().sum() > 0
    # the guard is what makes it finite: the unguarded formula's gradient at 0 is NaN
    v = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    th = v.norm()
    (torch.sin(th) / th).backward()
    assert torch.isnan(v.grad).all()


# ---------------------------------------------------------------------------- a frozen field


class BallField(Field):
    """Three textured balls (radius 0.45) around the origin, in closed form: density a steep
    sigmoid of the distance to the nearest centre, colour smooth sinusoids of the position;
    rendered with 48 uniform samples over t in [1, 4] (the camera is 2.5 away).
    Differentiable w.r.t. the rays. Off-centre silhouettes make every rotation axis of the
    camera observable (a single centred ball would leave the roll to its texture)."""

    backend = "ball"
    centres = torch.tensor([[0.7, 0.1, 0.0], [-0.6, 0.3, 0.5], [0.0, -0.45, -0.6]])

    def density(self, x):
        r = (x[:, None] - self.centres.to(x.dtype)).norm(dim=-1).min(-1).values
        return 40.0 * torch.sigmoid(25.0 * (0.45 - r))

    def color(self, x, d=None):
        ph = torch.tensor([0.0, 1.0, 2.0], dtype=x.dtype)
        return 0.5 + 0.35 * torch.sin(4.0 * x[:, :1] + ph) * torch.cos(3.0 * x[:, 1:2] - ph)

    def render(self, rays_o, rays_d, *, near, background, train, grad_rays=None):
        t = torch.linspace(1.0, 4.0, 48, dtype=rays_o.dtype)
        x = rays_o[:, None] + rays_d[:, None] * t[None, :, None]  # (R, S, 3)
        sigma = self.density(x.reshape(-1, 3)).reshape(x.shape[:2])
        rgb = self.color(x.reshape(-1, 3)).reshape(*x.shape[:2], 3)
        alpha = 1 - torch.exp(-sigma * (t[1] - t[0]))
        trans = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1 - alpha[:, :-1]], 1), 1)
        w = alpha * trans
        return {"rgb": (w[..., None] * rgb).sum(1), "opacity": w.sum(1)}


def ball_scene(n_views=40, **kw) -> SceneConfig:
    return SceneConfig(
        name="ball",
        width=48,
        height=36,
        intrinsics=IntrinsicsConfig(fx=45.0, fy=45.0, cx=24.0, cy=18.0),
        trajectory=TrajectoryConfig(
            kind="turntable", radius=2.5, elevation_deg=15.0, period_us=n_views * 1000
        ),
        t_start_us=0,
        t_end_us=n_views * 1000,
        n_views=n_views,
        loop=True,
        background=None,
        sim_log_eps=1e-3,
        **kw,
    ).validate()


def ball_events(cfg: SceneConfig, field: Field, sim: SimulatorConfig):
    """The simulator's events of the field's frames at the grid times (a closed loop)."""
    rig = Rig.from_scene(cfg)
    t = np.arange(cfg.n_views, dtype=np.int64) * 1000
    dirs = camera_directions(rig.intrinsics)
    frames = []
    with torch.no_grad():
        for c2w in rig.pose(t):
            o, d = generate_rays(dirs.double(), torch.from_numpy(c2w))
            frames.append(field.render(o, d, near=0, background=None, train=False)["rgb"])
    linear = torch.stack(frames).reshape(len(t), 36, 48, 3).numpy() ** 2.2
    simulator = EventSimulator(48, 36, sim)
    simulator.add_frames(linear, t)
    simulator.close_loop(cfg.t_end_us)
    return rig, simulator.finish((0, cfg.t_end_us))


def calibration_run(cfg, train_cfg, events, rig, steps, true_c2w=None, seed=0):
    """Train only the calibration against the frozen BallField; returns it."""
    index = EventIndex(
        events, cfg.pos_threshold, cfg.neg_threshold, t_start=0, t_end=cfg.t_end_us, loop=True
    )
    windows = WindowSampler(cfg.n_views, 0, cfg.t_end_us, 1, 4, seed=seed)
    sampler = RaySampler(
        index,
        rig,
        windows,
        rays_per_step=192,
        windows_per_step=8,
        neg_ratio=0.1,
        seed=seed,
        use_kernel=False,
        with_poses=train_cfg.refine_poses,
        with_parts=train_cfg.estimate_threshold,
    )
    field = BallField()
    cal = SelfCalibration(
        train_cfg, sampler, (cfg.pos_threshold, cfg.neg_threshold), field, true_c2w
    )
    for step in range(steps):
        cal.before_step(step / steps, 1.0)
        batch = sampler.sample()
        rays_o, rays_d, target, _ = cal.apply(batch)
        rgb = field.render(rays_o, rays_d, near=0, background=None, train=True)["rgb"]
        b = len(target)
        loss = event_loss(rgb[:b], rgb[b:], target, batch.channel, eps=cfg.sim_log_eps)
        cal.zero_grad()
        loss.backward()
        assert cal.step()
    return cal, sampler


@pytest.fixture(scope="module")
def ball():
    cfg = ball_scene()
    field = BallField()
    rig, events = ball_events(cfg, field, SimulatorConfig(pos_threshold=0.25))
    return cfg, rig, events


@pytest.mark.slow
def test_refinement_recovers_a_known_perturbation(ball):
    cfg, rig, events = ball
    grid_t = WindowSampler(cfg.n_views, 0, cfg.t_end_us, 1, 4).grid_times(np.arange(41))
    bad_rig, report = perturb_poses(rig, 2.0, seed=5, grid_t=grid_t)
    true_c2w = torch.as_tensor(rig.pose(grid_t))
    # the frozen field fixes the gauge: the corrections can (and must) find the truth itself
    tc = TrainConfig(  # plain Adam over every row, from the first step (the row Adam and
        # the delayed start: tests/test_pose_refine.py)
        refine_poses=True,
        refine_lr=5e-3,
        refine_lr_final=5e-4,
        refine_gauge="none",
        refine_optimizer="adam",
        refine_start=0.0,
        refine_warmup=0.0,
        refine_translation=True,
        refine_decay=0.0,
    )
    cal, _ = calibration_run(cfg, tc, events, bad_rig, 120, true_c2w)
    st = cal.stats()
    # poses start 2° off (exactly: the perturbation is a rotation by 2° about each centre);
    # rotations and shifts are both learnt, and trade off a little (lateral shift ≈ pan)
    assert abs(report["grid"]["measured_mean_deg"] - 2.0) < 1e-6
    assert st["pose_error_deg"] < 0.8, st
    assert st["pose_centre_error"] < 0.05, st


def test_gauges():
    """mean: the corrections sum to zero over the used rows; first: the first row stays; the
    loop's last row (the first's twin) is never corrected."""
    cfg = ball_scene(n_views=6)
    rig = Rig.from_scene(cfg)
    grid = torch.as_tensor(rig.pose(np.arange(7) * 1000), dtype=torch.float32)
    used = torch.tensor([True] * 6 + [False])
    for gauge in ("mean", "first", "none"):
        pr = PoseRefiner(grid, used, gauge)
        with torch.no_grad():
            pr.delta.copy_(torch.randn(7, 6))
        d = pr.corrections()
        assert torch.equal(d[6], torch.zeros(6))
        if gauge == "mean":
            assert d[:6].sum(0).abs().max() < 1e-6
        if gauge == "first":
            assert torch.equal(d[0], torch.zeros(6)) and d[1:6].abs().min() > 0
    with pytest.raises(ValueError, match="gauge"):
        PoseRefiner(grid, used, "median")


def test_auto_gauge_is_none_for_turns_about_the_given_centres():
    """refine_gauge "auto" (the default): no gauge when only turns are learnt (the fixed
    centres pin the frame), the mean gauge when the centres move too; a shared row has none;
    an explicit choice stays."""
    from fastenerf.pose_calibration import pose_gauge

    assert TrainConfig().refine_gauge == "auto" and pose_gauge(TrainConfig()) == "none"
    assert pose_gauge(TrainConfig(refine_translation=True)) == "mean"
    assert pose_gauge(TrainConfig(refine_gauge="first")) == "first"
    shared = TrainConfig(refine_poses=True, refine_shared=True, refine_gauge="mean")
    assert pose_gauge(shared) == "none"


def test_zero_corrections_give_the_samplers_rays_bit_for_bit(ball):
    cfg, rig, events = ball
    index = EventIndex(events, 0.25, 0.25, t_start=0, t_end=cfg.t_end_us, loop=True)
    windows = WindowSampler(cfg.n_views, 0, cfg.t_end_us, 1, 4)
    sampler = RaySampler(
        index, rig, windows, rays_per_step=64, windows_per_step=4, neg_ratio=0.1, with_poses=True
    )
    batch = sampler.sample()
    pr = PoseRefiner(sampler.grid_c2w, used_rows(sampler), "mean")
    o, d = pr.rays(batch.dirs, batch.pose_idx)
    assert torch.equal(o, batch.rays_o) and torch.equal(d, batch.rays_d)
    assert not used_rows(sampler)[-1]  # a loop's last grid row is its first


def test_refine_win_max_takes_the_pose_gradient_from_short_windows_only(ball):
    """Rows only long windows touched get no gradient and are not stepped; the rays' values and
    the gradient of rows only short windows touched are what they are without the option."""
    from fastenerf.pose_calibration import PoseCalibration

    def gen(seed):
        return torch.Generator().manual_seed(seed)

    cfg, rig, events = ball
    index = EventIndex(events, 0.25, 0.25, t_start=0, t_end=cfg.t_end_us, loop=True)
    windows = WindowSampler(cfg.n_views, 0, cfg.t_end_us, 1, 4, seed=3)
    sampler = RaySampler(
        index,
        rig,
        windows,
        rays_per_step=256,
        windows_per_step=16,
        neg_ratio=0.1,
        seed=3,
        with_poses=True,
        use_kernel=False,
    )
    batch = sampler.sample()
    b, g = len(batch.target), len(sampler.grid_c2w)
    length = torch.remainder(batch.pose_idx[b:] - batch.pose_idx[:b], g - 1)  # loop: g - 1 views
    assert (length <= 2).any() and (length > 2).any()  # both kinds in the batch
    touched = {
        kind: torch.zeros(g, dtype=torch.bool).index_fill_(0, batch.pose_idx[m.repeat(2)], True)
        for kind, m in (("short", length <= 2), ("long", length > 2))
    }
    only_short = touched["short"] & ~touched["long"]
    only_long = touched["long"] & ~touched["short"]
    assert only_short.any() and only_long.any()
    weights = torch.randn(2, len(batch.pose_idx), 3, generator=gen(0))
    out = {}
    for win in (None, 2):
        pc = PoseCalibration(
            TrainConfig(refine_poses=True, refine_win_max=win), sampler, BallField()
        )
        with torch.no_grad():
            pc.refiner.delta.copy_(0.01 * torch.randn(pc.refiner.delta.shape, generator=gen(1)))
        o, d = pc.rays(batch)
        ((o * weights[0]).sum() + (torch.sin(d) * weights[1]).sum()).backward()
        out[win] = (o.detach(), d.detach(), pc.refiner.delta.grad.clone(), pc.seen.clone())
    (o0, d0, g0, seen0), (o1, d1, g1, seen1) = out[None], out[2]
    assert torch.equal(o0, o1) and torch.equal(d0, d1)
    assert torch.equal(seen0, touched["short"] | touched["long"])
    assert torch.equal(seen1, touched["short"])
    assert g1[only_long].abs().max() == 0 and g0[only_long, :3].abs().min() > 0  # turns only
    assert torch.equal(g1[only_short], g0[only_short]) and g1[only_short, :3].abs().min() > 0
    assert torch.equal(pc.grad_rays, (length <= 2).repeat(2))  # for the field to skip the rest


def test_refine_win_max_counts_a_wrapped_windows_views(ball):
    """On a loop a window's t0 row wraps to the end of the grid: (n - 2 -> 2) spans 4 views."""
    from fastenerf.pose_calibration import PoseCalibration

    cfg, rig, events = ball
    index = EventIndex(events, 0.25, 0.25, t_start=0, t_end=cfg.t_end_us, loop=True)
    windows = WindowSampler(cfg.n_views, 0, cfg.t_end_us, 1, 4)
    kw = {"rays_per_step": 64, "windows_per_step": 4, "neg_ratio": 0.1}
    sampler = RaySampler(index, rig, windows, **kw, with_poses=True, use_kernel=False)
    n = len(sampler.grid_c2w) - 1
    pc = PoseCalibration(TrainConfig(refine_poses=True, refine_win_max=2), sampler, BallField())
    pose_idx = torch.tensor([n - 2, n - 1, 2, 1])  # windows (n-2 -> 2): 4 views, (n-1 -> 1): 2
    rays = torch.zeros(4, 3, requires_grad=True)
    o, _ = pc._short_windows_only(pose_idx, rays, rays)
    assert [r.item() for r in torch.nonzero(pc.seen)[:, 0]] == [1, n - 1]
    o.sum().backward()
    assert rays.grad[:, 0].tolist() == [0.0, 1.0, 0.0, 1.0]


def test_pose_settle_lengthens_the_windows_once_the_turns_stop_moving():
    """No look before the pose lr's warm-up ends, one per CHECK_EVERY of the budget after it;
    the windows lengthen at the first look whose RMS movement (pixels at fx) is below the
    tolerance, and never again after."""
    from fastenerf.pose_settle import CHECK_EVERY, PoseSettle

    windows = WindowSampler(100, 0, 100_000, 1, 5, seed=0)
    cfg = TrainConfig(refine_poses=True, refine_settle_px=0.5, settle_win_max=20)
    settle = PoseSettle(cfg, windows, fx=100.0, start=0.1)
    turns = torch.zeros(30, 3)
    assert not settle.due(0.05)  # still in the warm-up
    assert settle.due(0.1) and not settle.look(0.1, turns)  # the first look only remembers
    assert not settle.due(0.1 + CHECK_EVERY / 2)
    turns[:, 0] += 0.01  # 0.01 rad at fx 100: one pixel
    assert settle.due(0.15) and not settle.look(0.15, turns)
    assert settle.moved_px == pytest.approx(1.0) and windows.win_max == 5
    turns[::2, 1] += 0.002 * 2**0.5  # RMS over the rows: 0.2 px
    assert settle.due(0.2) and settle.look(0.2, turns)
    assert settle.moved_px == pytest.approx(0.2) and settle.settled_at == 0.2
    assert windows.win_max == 20 and not settle.due(0.9)
    assert settle.stats() == {"field_win_max": 20.0, "pose_settle_px": settle.moved_px}
    again = PoseSettle(cfg, windows, fx=100.0, start=0.1)
    again.load_state_dict(settle.state_dict())
    assert again.settled_at == 0.2 and not again.due(0.5)


@pytest.mark.parametrize("steps_before", [1, 5])
def test_a_run_whose_poses_settle_lengthens_its_windows_and_resumes_exactly(
    scene, tmp_path, steps_before
):
    """A 40-step run that looks every other step: with a tolerance no movement is under, the
    windows stay; with one every movement is under, they lengthen at the second look (step
    2), recorded in config.json and metrics.jsonl. A checkpoint taken between the two looks
    (step 1), or after the switch but inside the sampler's block drawn before it (step 5),
    resumes bit for bit."""
    cfg = dict(refine_poses=True, refine_start=0.0, refine_warmup=0.0, steps=40)
    cfg.update(perturb=PerturbConfig(pose_error_deg=1.0), refine_gate=0.0)  # every row moves
    never = Trainer(scene, tiny(**cfg, refine_settle_px=1e-6), tmp_path / "never")
    never.run(progress=False)
    c = never.cfg
    assert c.win_max < c.settle_win_max and c.refine_win_max == c.win_max
    assert never.windows.win_max == c.win_max
    settle = {**cfg, "refine_settle_px": 1e3}
    whole, resumed = whole_and_resumed(scene, settle, tmp_path, steps_before)
    for tr in (whole, resumed):
        assert tr.windows.win_max == tr.cfg.settle_win_max
        assert tr.selfcal.pose_cal.settle.settled_at == pytest.approx(0.05)
    assert torch.equal(whole.selfcal.poses.delta, resumed.selfcal.poses.delta)
    a, r = field_state(whole), field_state(resumed)
    assert all(torch.equal(a[k], r[k]) for k in a)
    conf = json.loads((tmp_path / "whole" / "config.json").read_text())
    assert conf["self_calibration"]["poses"]["settled_at"] == pytest.approx(0.05)
    lines = (tmp_path / "whole" / "metrics.jsonl").read_text().splitlines()
    lengths = [json.loads(line)["field_win_max"] for line in lines]
    assert lengths[0] == c.win_max and lengths[-1] == c.settle_win_max


@pytest.mark.parametrize("freeze", [False, True])
def test_refine_freeze_stops_the_pose_learning_once_the_poses_settle(scene, tmp_path, freeze):
    """refine_freeze: from the step after the poses settled (here the second look, step 2 of
    40) the corrections stay exactly as they were, the rays reach the field without a
    gradient, the field still learns and the graph key says so; without it the corrections
    go on moving. A run checkpointed after the switch resumes frozen, bit for bit."""
    cfg = dict(refine_poses=True, refine_start=0.0, refine_warmup=0.0, steps=40)
    cfg.update(perturb=PerturbConfig(pose_error_deg=1.0), refine_gate=0.0, refine_settle_px=1e3)
    tr = Trainer(scene, tiny(**cfg, refine_freeze=freeze), tmp_path / "r")
    grads, render = [], tr.field.render

    def spy(rays_o, *args, **kw):
        grads.append(rays_o.requires_grad)
        return render(rays_o, *args, **kw)

    tr.field.render = spy
    deltas, fields = [], []
    for _ in range(8):
        tr.step()
        deltas.append(tr.selfcal.poses.delta.detach().clone())
        fields.append(field_state(tr))
    pc = tr.selfcal.pose_cal
    assert pc.settle.settled_at == pytest.approx(0.05) and pc.frozen is freeze
    moved = [not torch.equal(a, b) for a, b in zip(deltas[2:-1], deltas[3:], strict=True)]
    assert moved == [not freeze] * 5
    assert grads[:3] == [True] * 3 and grads[3:] == [not freeze] * 5
    assert tr.selfcal.graph_key() == (not freeze, False, freeze)
    w = [k for k in fields[0] if fields[0][k].is_floating_point()]
    assert any(not torch.equal(fields[-2][k], fields[-1][k]) for k in w)  # the field learns
    if not freeze:
        return
    whole, resumed = whole_and_resumed(scene, {**cfg, "refine_freeze": True}, tmp_path, 5)
    assert resumed.selfcal.pose_cal.frozen
    assert torch.equal(whole.selfcal.poses.delta, deltas[-1])
    assert torch.equal(whole.selfcal.poses.delta, resumed.selfcal.poses.delta)
    a, r = field_state(whole), field_state(resumed)
    assert all(torch.equal(a[k], r[k]) for k in a)
    conf = json.loads((tmp_path / "whole" / "config.json").read_text())
    assert conf["self_calibration"]["poses"]["frozen"] is True
    lines = (tmp_path / "whole" / "metrics.jsonl").read_text().splitlines()
    frozen = [json.loads(line)["poses_frozen"] for line in lines]
    assert frozen[0] == 0.0 and frozen[-1] == 1.0  # the viewer's stats say so


def test_refine_freeze_needs_the_poses_refined_and_a_settle_tolerance(scene):
    """One-line errors naming the key: without refine_poses (the config's own check) and
    where nothing says when the poses settled (a CPU run leaves refine_settle_px off)."""
    with pytest.raises(InputError, match="'refine_freeze' needs refine_poses"):
        tiny(refine_freeze=True).validate()
    with pytest.raises(InputError, match="'refine_freeze' needs refine_settle_px"):
        tiny(refine_poses=True, refine_freeze=True).resolved(scene.config, "cpu")
    c = tiny(refine_poses=True, refine_freeze=True, refine_settle_px=0.3)
    assert c.resolved(scene.config, "cpu").refine_freeze


def test_refine_settle_smooth_smooths_the_turns_once_where_the_poses_settle(scene, tmp_path):
    """refine_settle_smooth 5: at the settle (the second look, step 2 of 40) the corrected
    turns are fitted to a smooth path once (the refiner's own smooth_turns, its effect: the
    rows' pose-to-pose noise falls) and never again; a run checkpointed after it resumes
    without smoothing again, bit for bit; bad values are one-line errors."""
    cfg = dict(refine_poses=True, refine_start=0.0, refine_warmup=0.0, steps=40)
    cfg.update(perturb=PerturbConfig(pose_error_deg=1.0), refine_gate=0.0, refine_settle_px=1e3)
    cfg.update(refine_settle_smooth=5)
    tr = Trainer(scene, tiny(**cfg), tmp_path / "r")
    pr, calls = tr.selfcal.pose_cal.refiner, []
    smooth = pr.smooth_turns

    def counted(*a, **kw):
        calls.append((tr.step_count, pr.stats()["pose_jitter_deg"]))
        smooth(*a, **kw)
        calls[-1] += (pr.stats()["pose_jitter_deg"],)

    pr.smooth_turns = counted
    for _ in range(8):
        tr.step()
    assert [c[0] for c in calls] == [2] and tr.selfcal.pose_cal.settled
    assert calls[0][2] < 0.5 * calls[0][1]  # the rows' own noise went
    whole, resumed = whole_and_resumed(scene, cfg, tmp_path, 5)
    assert torch.equal(whole.selfcal.poses.delta, resumed.selfcal.poses.delta)
    a, r = field_state(whole), field_state(resumed)
    assert all(torch.equal(a[k], r[k]) for k in a)
    for bad, words in (
        (dict(refine_settle_smooth=4), "must be 0 (off) or odd and >= 5"),
        (dict(refine_settle_smooth=5, refine_knots=8), "a correction per pose"),
    ):
        with pytest.raises(InputError, match=re.escape(words)):
            tiny(**{**cfg, **bad}).validate()
    with pytest.raises(InputError, match="'refine_settle_smooth' needs refine_poses"):
        tiny(refine_settle_smooth=5).validate()
    with pytest.raises(InputError, match="'refine_settle_smooth' needs refine_settle_px"):
        tiny(refine_poses=True, refine_settle_smooth=5).resolved(scene.config, "cpu")
    with pytest.raises(InputError, match="refine_settle_smooth 100001 is longer than the"):
        Trainer(scene, tiny(**{**cfg, "refine_settle_smooth": 100001}), tmp_path / "long")
    assert not (tmp_path / "long").exists()


@pytest.mark.parametrize("refine_win_max", [None, 2])
def test_the_trainer_hands_the_field_the_rays_poses_learn_from(scene, tmp_path, refine_win_max):
    """Every training render gets the calibration's grad_rays: with refine_win_max the short
    windows' rays (some, not all, of a batch of windows up to win_max), else None."""
    cfg = dict(refine_poses=True, refine_start=0.0, refine_warmup=0.0, win_max=8)
    tr = Trainer(scene, tiny(**cfg, refine_win_max=refine_win_max), tmp_path / "r")
    seen, render = [], tr.field.render

    def spy(*args, grad_rays=None, **kw):
        seen.append(None if grad_rays is None else grad_rays.clone())
        return render(*args, grad_rays=grad_rays, **kw)

    tr.field.render = spy
    tr.run(progress=False)
    assert len(seen) == tr.cfg.steps
    if refine_win_max is None:
        assert all(m is None for m in seen)
        return
    assert torch.equal(seen[-1], tr.selfcal.grad_rays)
    both = torch.stack(seen)
    assert both.dtype == torch.bool and both.any() and not both.all()


def test_the_x_gradient_mask_changes_nothing_a_refined_ngp_run_learns(scene, tmp_path, monkeypatch):
    """An ngp run refining its poses from the short windows only ends with the same field and
    corrections, bit for bit, whether its encoding skips the long windows' position gradient
    (grad_rays) or computes it for nothing (None)."""
    from fastenerf.config import train_preset

    ngp = {"n_levels": 4, "log2_table_size": 10, "max_resolution": 32}
    cfg = dict(
        TINY, steps=6, refine_poses=True, refine_start=0.0, refine_warmup=0.0, refine_gate=0.0
    )
    cfg.update(win_max=8, refine_win_max=2, perturb=PerturbConfig(pose_error_deg=1.0))
    runs = {}
    for name in ("mask", "none"):
        if name == "none":
            monkeypatch.setattr(SelfCalibration, "grad_rays", property(lambda self: None))
        c = train_preset("fast", "ngp", backend_options=ngp, **cfg)
        tr = Trainer(scene, c, tmp_path / name)
        tr.run(progress=False)
        params = {k: v.detach().clone() for k, v in tr.field.named_parameters()}
        runs[name] = (params, tr.selfcal.poses.delta.detach().clone())
    (fa, pa), (fb, pb) = runs["mask"], runs["none"]
    assert pa.abs().max() > 0 and torch.equal(pa, pb)
    assert all(torch.equal(fa[k], fb[k]) for k in fa)


# --------------------------------------------------------------------------------- thresholds


def test_parts_give_the_target_with_any_thresholds(random_stream):
    """E = a·C_pos + b·C_neg for the sampler's windows, wrapped ones included, through both
    the Warp kernel and numpy, with a polarity offset."""
    ev = random_stream(4000, 16, 12, 100_000)
    cfg = SceneConfig(
        name="s",
        width=16,
        height=12,
        intrinsics=IntrinsicsConfig(fx=14.0, fy=14.0, cx=8.0, cy=6.0),
        trajectory=TrajectoryConfig(kind="turntable", radius=3.0, period_us=100_000),
        t_start_us=0,
        t_end_us=100_000,
        n_views=20,
        polarity_offset=-0.2,
    ).validate()
    index = EventIndex(ev, 0.3, 0.2, -0.2, t_start=0, t_end=100_000, loop=True)
    for kernel in (None, False):
        windows = WindowSampler(20, 0, 100_000, 1, 8)
        s = RaySampler(
            index,
            Rig.from_scene(cfg),
            windows,
            rays_per_step=400,
            windows_per_step=8,
            neg_ratio=0.2,
            use_kernel=kernel,
            with_parts=True,
        )
        if kernel is None:
            assert s.target_backend == "warp"
        b = s.sample()
        np.testing.assert_allclose((b.parts * torch.tensor([0.3, 0.2])).sum(1), b.target, atol=1e-5)
        n_pos, n_neg = b.parts[:, 0] / 0.8, -b.parts[:, 1] / 1.2
        assert (n_pos >= 0).all() and (n_neg >= 0).all() and (n_pos + n_neg).sum() > 0
        torch.testing.assert_close(n_pos, n_pos.round(), atol=1e-4, rtol=0)


def test_thresholds_stay_positive_and_finite_under_extreme_gradients():
    def run(guarded: bool):
        tc = TrainConfig(estimate_threshold=True, threshold_lr=0.5, threshold_per_pixel=True)
        est = ThresholdEstimator(0.25, 0.25, 4, per_pixel=True, free_scale=True)
        opt = torch.optim.Adam([p for p in est.parameters()], lr=tc.threshold_lr)
        for g in [1e30, -1e30] * 60 + [math.inf, math.nan, 1e38]:
            opt.zero_grad()
            for p in est.parameters():
                p.grad = torch.full_like(p, g)
            if guarded:
                if all(torch.isfinite(p.grad).all() for p in est.parameters()):
                    opt.step()
                est.project()
            else:
                opt.step()
        return est.thresholds(torch.arange(4)), est

    c, est = run(guarded=True)
    assert torch.isfinite(c).all() and (c >= C_MIN * 0.999).all() and (c <= C_MAX * 1.001).all()
    assert all(torch.isfinite(p).all() for p in est.parameters())
    unguarded, _ = run(guarded=False)
    assert not torch.isfinite(unguarded).all()  # NaN from the inf / NaN gradients


def two_event_sampler(**with_what) -> RaySampler:
    """A 6-view ball loop with two events: a sampler of 8 rays, 2 windows (with_poses=...,
    with_parts=...)."""
    index = EventIndex(
        __import__("fastenerf.data.events", fromlist=["EventStream"]).EventStream.from_arrays(
            [1, 2], [1, 2], [1000, 2000], [1, -1], 48, 36
        ),
        0.25,
        0.25,
        t_start=0,
        t_end=6000,
        loop=True,
    )
    rig = Rig.from_scene(ball_scene(n_views=6))
    windows = WindowSampler(6, 0, 6000, 1, 2)
    kw = dict(rays_per_step=8, windows_per_step=2, neg_ratio=0.5, use_kernel=False)
    return RaySampler(index, rig, windows, **kw, **with_what)


def test_self_calibration_skips_a_non_finite_step():
    s = two_event_sampler(with_parts=True)
    cal = SelfCalibration(TrainConfig(estimate_threshold=True), s, (0.25, 0.25), BallField())
    cal.thresholds.log_ratio.grad = torch.tensor(math.nan)
    assert not cal.step() and cal.stats()["calibration_skipped_steps"] == 1
    assert cal.stats()["threshold_ratio"] == 1.0
    with pytest.raises(InputError, match="start thresholds"):
        ThresholdEstimator(0.0, 0.25, 4)


def test_ratio_of_biased_thresholds_is_estimated(ball):
    """Events made with C+ = 0.3, C- = 0.2; the run starts from 0.25 / 0.25 and learns the
    ratio (1.5) while the product stays at the start's."""
    cfg, rig, _ = ball
    _, events = ball_events(cfg, BallField(), SimulatorConfig(pos_threshold=0.3, neg_threshold=0.2))
    tc = TrainConfig(estimate_threshold=True, threshold_lr=0.02)
    cal, _ = calibration_run(cfg, tc, events, rig, 60)
    st = cal.stats()
    assert abs(st["threshold_ratio"] / 1.5 - 1) < 0.1, st
    assert abs(st["threshold_pos"] * st["threshold_neg"] - 0.0625) < 1e-6


# ---------------------------------------------------------------------------- coarse-to-fine


def test_cosine_window():
    np.testing.assert_allclose(cosine_window(0.0, 4), [0, 0, 0, 0])
    np.testing.assert_allclose(cosine_window(1.5, 4), [1, 0.5, 0, 0], atol=1e-7)
    np.testing.assert_allclose(cosine_window(4.0, 4), [1, 1, 1, 1])


@pytest.mark.parametrize("backend", ["ngp", "vanilla"])
def test_coarse_to_fine_silences_the_fine_levels(backend, scene_config):
    from fastenerf.fields import make_field

    sc = scene_config(32, 24)
    opts = {"ngp": {"n_levels": 4, "log2_table_size": 10, "max_resolution": 32}, "vanilla": {}}
    field = make_field(backend, sc, TrainConfig(backend=backend, backend_options=opts[backend]))
    x = torch.rand(64, 3) * 1.6 - 0.8
    assert set_encoding_window(field, 0.0, 0.1, 0.5) == 0.0  # before the start: coarsest only
    if backend == "ngp":
        assert torch.equal(field.level_weights, torch.tensor([1.0, 0, 0, 0]))
        field.density(x).sum().backward()
        off = field.grid_cfg.level_offsets
        assert field.table.grad[off[1] :].abs().max() == 0
        assert field.table.grad[: off[1]].abs().max() > 0
    else:
        enc = field.pos_enc(x)
        assert enc[:, 3:].abs().max() == 0 and torch.equal(enc[:, :3], x)
    assert 0 < set_encoding_window(field, 0.3, 0.1, 0.5) < 1
    assert set_encoding_window(field, 0.5, 0.1, 0.5) is None  # every level on: no weights
    assert (field.level_weights if backend == "ngp" else field.pos_enc.band_weights) is None


# ------------------------------------------------------------------------------- the trainer

TINY = dict(
    steps=4,
    rays_per_step=16,
    windows_per_step=2,
    eval_every_s=0,
    checkpoint_every_s=0,
    log_every=1,
    device="cpu",
    lr=5e-3,
)
VANILLA_TINY = {"depth": 2, "width": 16, "pos_freqs": 4, "dir_freqs": 2, "n_coarse": 8, "n_fine": 8}


def tiny(**kw):
    from fastenerf.config import train_preset

    return train_preset("fast", "vanilla", backend_options=dict(VANILLA_TINY), **{**TINY, **kw})


@pytest.fixture(scope="module")
def scene(tiny_scene):
    return load_scene(tiny_scene)


def field_state(tr):
    return {k: v.detach().clone() for k, v in tr.field.state_dict().items()}


def test_options_off_step_is_what_it_was(scene, tmp_path):
    """With both options off, Trainer.step is the step it was before self-calibration: the
    sampler's rays and targets, the event loss, one Adam step, bit for bit."""
    tr = Trainer(scene, tiny(), tmp_path / "a")
    assert tr.selfcal is None and tr.sampler.with_poses is False
    ref = Trainer(scene, tiny(), tmp_path / "b")
    # the step as it was: sample, render the sampler's rays, the event loss, Adam
    for _ in range(2):
        rng = torch.get_rng_state()
        lr = ref.lr_at(ref.step_count)
        for g in ref.optimizer.param_groups:
            g["lr"] = lr * g.get("lr_scale", 1.0)
        ref.field.train()
        ref.field.update(ref.step_count)
        b = ref.sampler.sample()
        assert b.dirs is None and b.pose_idx is None and b.parts is None
        out = ref.field.render(
            b.rays_o, b.rays_d, near=scene.config.near, background=ref.background, train=True
        )
        c = ref.cfg
        loss, _ = total_loss(
            out,
            b.target,
            b.channel,
            gamma=c.gamma,
            eps=c.log_eps,
            distortion_weight=c.distortion_weight,
            fused=True,  # the trainer's event loss (kernels/event_loss.py)
        )
        ref.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        ref.optimizer.step()
        ref.step_count += 1
        torch.set_rng_state(rng)  # the same draws (vanilla's jitter) for the trainer's step
        stats = tr.step()
        assert stats["loss"] == float(loss.detach())
        a, r = field_state(tr), field_state(ref)
        assert all(torch.equal(a[k], r[k]) for k in a)
        assert not any(k.startswith(("pose_", "threshold_")) for k in stats)


def whole_and_resumed(scene, cfg: dict, tmp_path, steps_before: int = 2):
    """A whole tiny run, and one checkpointed after `steps_before` steps and resumed."""
    whole = Trainer(scene, tiny(**cfg), tmp_path / "whole")
    whole.run(progress=False)
    part = Trainer(scene, tiny(**cfg), tmp_path / "part")
    for _ in range(steps_before):
        part.step()
    part.save_checkpoint()
    del part
    resumed = Trainer(scene, tiny(**cfg), tmp_path / "part", resume=True)
    resumed.run(progress=False)
    return whole, resumed


def test_both_options_recorded_checkpointed_and_resumed_exactly(scene, tmp_path):
    cfg = dict(
        refine_poses=True,
        estimate_threshold=True,
        threshold_per_pixel=True,
        perturb=PerturbConfig(pose_error_deg=1.0),
        refine_gate=0.5,  # open within these few visits: the gate's state resumes too
    )
    whole, resumed = whole_and_resumed(scene, cfg, tmp_path)
    assert torch.equal(whole.selfcal.poses.delta, resumed.selfcal.poses.delta)
    gate_state = (t.selfcal.pose_optimizer.state[t.selfcal.poses.delta] for t in (whole, resumed))
    assert torch.equal(*(st["gate_m"] for st in gate_state))
    assert torch.equal(whole.selfcal.thresholds.pixel, resumed.selfcal.thresholds.pixel)
    assert whole.selfcal.poses.delta.abs().max() > 0  # it did learn something
    a, r = field_state(whole), field_state(resumed)
    assert all(torch.equal(a[k], r[k]) for k in a)

    conf = json.loads((tmp_path / "whole" / "config.json").read_text())
    assert conf["train"]["refine_poses"] and conf["train"]["estimate_threshold"]
    assert conf["built"]["pose_refinement"] and conf["built"]["threshold_estimation"]
    sc = conf["self_calibration"]
    assert sc["thresholds"]["start"] == {"pos": 0.25, "neg": 0.25}
    est = sc["thresholds"]["estimate"]
    assert est["pos"] == pytest.approx(whole.selfcal.thresholds.thresholds()[0].item())
    assert sc["poses"]["rows"] == scene.config.n_views
    # the study's truth is known: the error stats start near the perturbation
    assert sc["stats"]["pose_error_deg"] == pytest.approx(1.0, abs=0.2)
    last = json.loads((tmp_path / "whole" / "metrics.jsonl").read_text().splitlines()[-1])
    for key in ("threshold_pos", "threshold_neg", "pose_correction_deg", "pose_error_deg"):
        assert math.isfinite(last[key]), key
    progress = json.loads((tmp_path / "whole" / "progress.json").read_text())
    assert "threshold_ratio" in progress["self_calibration"]


def test_knot_rows_run_recorded_checkpointed_and_resumed_exactly(scene, tmp_path):
    """refine_knots with refine_knot_rows trains both parts (rows and knots learn), resumes
    bit for bit (the row Adam's per-row state over G + K rows included) and is recorded."""
    cfg = dict(
        refine_poses=True,
        refine_knots=4,
        refine_knot_rows=True,
        perturb=PerturbConfig(pose_error_deg=1.0),
        refine_gate=0.5,
    )
    whole, resumed = whole_and_resumed(scene, cfg, tmp_path)
    delta = whole.selfcal.poses.delta
    G = len(whole.selfcal.poses.base)
    assert delta.shape == (G + 4, 6) and torch.equal(delta, resumed.selfcal.poses.delta)
    assert delta[:G].abs().max() > 0 and delta[G:].abs().max() > 0  # both parts learnt
    a, r = field_state(whole), field_state(resumed)
    assert all(torch.equal(a[k], r[k]) for k in a)
    conf = json.loads((tmp_path / "whole" / "config.json").read_text())
    assert conf["self_calibration"]["poses"]["knots"] == 4
    assert conf["self_calibration"]["poses"]["knot_rows"] is True


def test_a_run_resumed_in_the_shared_phase_forgets_the_moments_at_the_switch(scene, tmp_path):
    """A checkpoint taken while the poses share one correction, resumed where each takes its
    own (4 steps, the switch at the third): the resumed run zeroes the moments at the switch
    as the whole run does, and ends bit for bit where it does."""
    cfg = dict(refine_poses=True, refine_start=0.0, refine_warmup=0.0, refine_shared_until=0.5)
    cfg.update(perturb=PerturbConfig(pose_error_deg=1.0))
    whole, resumed = whole_and_resumed(scene, cfg, tmp_path)
    assert torch.equal(whole.selfcal.poses.delta, resumed.selfcal.poses.delta)
    a, b = (t.selfcal.pose_optimizer.state[t.selfcal.poses.delta] for t in (whole, resumed))
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert float(a["row_steps"].max()) <= 2  # counted from the switch, not from the start


def test_device_paced_step_reads_the_estimates_at_its_flush_only(scene, tmp_path):
    """On the device-paced step the calibration's estimates join the pending stats as device
    tensors: a host read at the step would wait for every queued step, off the training
    clock (60 s runs with an option trained for minutes). They reach the history as floats."""
    from fastenerf.step_stats import STATS_FLUSH_EVERY

    cfg = dict(refine_poses=True, estimate_threshold=True, step_mode="device")
    tr = Trainer(scene, tiny(**cfg, perturb=PerturbConfig(pose_error_deg=1.0)), tmp_path / "r")
    assert tr.step_mode == "device"
    real, asked = tr.selfcal.stats, []

    def spy(on_device=False):
        out = real(on_device)
        asked.append(on_device)
        assert torch.is_tensor(out["threshold_pos"]) == torch.is_tensor(out["pose_error_deg"])
        assert torch.is_tensor(out["pose_error_deg"]) == on_device
        return out

    tr.selfcal.stats = spy
    for _ in range(2 * STATS_FLUSH_EVERY):
        tr.step()
    tr.flush_stats()
    assert asked and all(asked)
    got = [h for h in tr.history if "pose_error_deg" in h]
    assert got and all(isinstance(h[k], float) for h in got for k in ("threshold_pos", "c2f"))
    assert got[0]["pose_error_deg"] == pytest.approx(1.0, abs=0.2)


def test_cli_flags(tmp_path):
    import argparse

    from fastenerf.commands import train as cmd

    p = argparse.ArgumentParser()
    cmd.add_arguments(p)
    off = cmd.build_config(p.parse_args(["s", "--out", str(tmp_path / "r")]))
    assert not off.refine_poses and not off.estimate_threshold
    on = cmd.build_config(
        p.parse_args(["s", "--out", str(tmp_path / "r"), "--refine-poses", "--estimate-threshold"])
    )
    assert on.refine_poses and on.estimate_threshold
    with pytest.raises(InputError, match="refine_gauge"):
        TrainConfig(refine_gauge="median").validate()
    with pytest.raises(InputError, match="refine_lr"):
        TrainConfig(refine_lr=0.0).validate()


def test_synth_biased_thresholds_and_mismatch(tmp_path):
    """The threshold study's scenes: separate thresholds and per-pixel mismatch, recorded."""
    from fastenerf.cli import main
    from fastenerf.config import SceneConfig as SC

    out = tmp_path / "s"
    argv = ["synth", "--scene", "blocks", "--out", str(out), "--size", "32x24", "--frames", "12"]
    argv += ["--threshold", "0.3", "--neg-threshold", "0.2", "--mismatch", "0.03"]
    assert main(argv) == 0
    sc = SC.load(out)
    assert (sc.pos_threshold, sc.neg_threshold) == (0.3, 0.2)
    bad = ["synth", "--scene", "blocks", "--out", str(tmp_path / "t"), "--neg-threshold", "-1"]
    assert main(bad) == 2


@pytest.mark.parametrize("optimizer", ["row-adam", "adam"])
def test_refine_beta1_is_the_pose_optimisers_momentum(optimizer):
    s = two_event_sampler(with_poses=True)
    tc = TrainConfig(refine_poses=True, refine_beta1=0.98, refine_optimizer=optimizer)
    cal = SelfCalibration(tc, s, (0.25, 0.25), BallField())
    opt = cal.pose_optimizer if optimizer == "row-adam" else cal.optimizer
    (group,) = [g for g in opt.param_groups if g.get("name") == "poses"]
    assert group["betas"] == (0.98, 0.999)


@pytest.mark.parametrize("until", [1.0, 0.0])
def test_shared_until_moves_every_pose_as_one_then_each_its_own(ball, until):
    """refine_shared_until: while progress is below it every used row gets the rows' summed
    gradient and steps, so all corrections stay equal (and move); after it they part. The
    graph key says which, so a captured step is taken again at the switch."""
    cfg, rig, events = ball
    grid_t = WindowSampler(cfg.n_views, 0, cfg.t_end_us, 1, 4).grid_times(np.arange(41))
    bad_rig, _ = perturb_poses(rig, 1.0, seed=2, grid_t=grid_t)
    tc = TrainConfig(
        refine_poses=True, refine_start=0.0, refine_warmup=0.0, refine_shared_until=until
    )
    cal, _ = calibration_run(cfg, tc, events, bad_rig, 6)
    d = cal.poses.delta.detach()[cal.poses.used]
    assert float(d.abs().max()) > 0
    spread = float((d - d[:1]).abs().max())
    assert (spread == 0.0) if until == 1.0 else (spread > 0.0)
    assert cal.graph_key() == (True, until == 1.0, False)


def test_shared_phase_moments_are_forgotten_at_the_switch(ball):
    """The shared phase's Adam moments are of every row's summed gradient: at the switch to
    one correction per pose they are zeroed in place (row step counts too), so each pose's
    own steps start at full size. 6 steps, the switch at the 4th: at most 3 per-row steps."""
    cfg, rig, events = ball
    tc = TrainConfig(
        refine_poses=True, refine_start=0.0, refine_warmup=0.0, refine_shared_until=0.5
    )
    cal, _ = calibration_run(cfg, tc, events, rig, 6)
    st = cal.pose_optimizer.state[cal.poses.delta]
    assert 1 <= float(st["row_steps"].max()) <= 3  # 3 shared steps + visits without the reset
    assert float(st["exp_avg_sq"].max()) > 0
    # and the per-pose phase starts its own lr schedule (ramp, then decay) at the switch
    from fastenerf.pose_calibration import pose_lr

    tc = TrainConfig(refine_poses=True, refine_start=0.0, refine_shared_until=0.5)
    first = pose_lr(tc, 0.0 + 0.1 * tc.refine_warmup)
    assert pose_lr(tc, 0.5) == 0.0
    assert pose_lr(tc, 0.5 + 0.05 * tc.refine_warmup) == pytest.approx(first, rel=1e-12)


def ngp_tiny(**kw):
    from fastenerf.config import train_preset
    from tests.test_train import NGP_TINY

    return train_preset("fast", "ngp", backend_options=dict(NGP_TINY), **{**TINY, **kw})


@pytest.mark.parametrize("settle_px", [None, 1e3])
def test_refine_diffuse_holds_the_view_direction_until_its_fraction_or_the_settle(
    scene, tmp_path, settle_px
):
    """refine_diffuse_until: the colour MLP's weights on the SH inputs past degree 0 are
    masked (and so unchanged by training) until the budget fraction, or until the poses
    settle where that comes first (here the second look, 0.05 of 40 steps); then they learn
    again. The stats say which."""
    cfg = dict(refine_poses=True, refine_start=0.0, refine_warmup=0.0, steps=40)
    cfg.update(perturb=PerturbConfig(pose_error_deg=1.0), refine_diffuse_until=0.1)
    tr = Trainer(scene, ngp_tiny(**cfg, refine_settle_px=settle_px), tmp_path / "r")
    net = tr.field.color_net
    sh = slice(net.n_h + 1, net.n_h + 16)
    w0 = net[0].weight.detach().clone()
    held = []
    for _ in range(6):
        tr.step()
        held.append(bool((net.w_mask[0, sh] == 0).all()))
        assert tr.selfcal.stats()["view_held"] == float(held[-1])  # the viewer's stats
    release = 3 if settle_px is not None else 4  # the step after the settle's (2), else 0.1's
    assert held == [True] * release + [False] * (6 - release)
    assert net.w_mask[0, net.n_h] == 1  # degree 0, a constant, stays
    w = net[0].weight.detach()
    assert not torch.equal(w[:, sh], w0[:, sh]) and not torch.equal(
        w[:, : net.n_h], w0[:, : net.n_h]
    )


def test_refine_diffuse_weights_do_not_move_while_held(scene, tmp_path):
    cfg = dict(refine_poses=True, refine_start=0.0, refine_warmup=0.0, steps=40)
    tr = Trainer(scene, ngp_tiny(**cfg, refine_diffuse_until=1.0), tmp_path / "r")
    net = tr.field.color_net
    sh = slice(net.n_h + 1, net.n_h + 16)
    w0 = net[0].weight.detach().clone()
    for _ in range(3):
        tr.step()
    w = net[0].weight.detach()
    assert torch.equal(w[:, sh], w0[:, sh]) and not torch.equal(w, w0)


def test_refine_diffuse_needs_the_poses_refined_and_the_ngp_field():
    with pytest.raises(InputError, match="'refine_diffuse_until' needs refine_poses"):
        ngp_tiny(refine_diffuse_until=0.3).validate()
    with pytest.raises(InputError, match="'refine_diffuse_until' needs the ngp backend"):
        tiny(refine_poses=True, refine_diffuse_until=0.3).validate()
    assert ngp_tiny(refine_poses=True, refine_diffuse_until=0.3).validate()


def test_reset_runaways_puts_back_only_the_rows_past_the_turn():
    """`pose_guard.reset_runaways`: the rows turned further than the bound, and their rows of
    every (G, ·) state tensor, are zeroed in place; the rest, shifts included, untouched."""
    from fastenerf.pose_guard import reset_runaways

    g = torch.Generator().manual_seed(0)
    delta = torch.randn(6, 6, generator=g) * 1e-3
    delta[2, :3] = torch.tensor([0.1, 0.0, 0.0])  # 5.7°
    delta[4, :3] = torch.tensor([0.0, 0.0, -0.06])  # 3.4°
    before = delta.clone()
    state = {"exp_avg": torch.ones(6, 6), "row_steps": torch.full((6, 1), 7.0), "step": 3}
    n = reset_runaways(delta, state, math.radians(3.0))
    assert int(n) == 2 and state["step"] == 3
    bad = torch.tensor([False, False, True, False, True, False])
    assert (delta[bad] == 0).all() and torch.equal(delta[~bad], before[~bad])
    assert (state["exp_avg"][bad] == 0).all() and (state["exp_avg"][~bad] == 1).all()
    assert (state["row_steps"][bad] == 0).all() and (state["row_steps"][~bad] == 7).all()
    assert int(reset_runaways(delta, state, math.radians(3.0))) == 0


@pytest.mark.parametrize("bound", [0.0, 2.0])
def test_refine_reset_deg_puts_back_a_runaway_row_in_a_run(scene, tmp_path, bound):
    """A row turned 5° by hand is put back at the next guard (every 1 % of the budget), its
    row Adam state cleared, and the count is in the stats and config.json; without the
    option it stays where it is."""
    cfg = dict(refine_poses=True, refine_start=0.0, refine_warmup=0.0, steps=40)
    tr = Trainer(scene, tiny(**cfg, refine_reset_deg=bound), tmp_path / "r")
    tr.step()
    pc = tr.selfcal.pose_cal
    row = int(torch.nonzero(pc.refiner.used)[3])
    with torch.no_grad():
        pc.refiner.delta[row, :3] = torch.tensor([0.0, math.radians(5.0), 0.0])
    tr.step()  # progress 1/40: a new percent, a guard
    turn = float(pc.refiner.delta.detach()[row, :3].norm())
    if not bound:
        assert turn > math.radians(4.0) and "pose_rows_reset" not in tr.selfcal.stats()
        return
    assert turn < math.radians(0.5)  # put back (then at most one small step)
    state = pc.optimizer.state[pc.refiner.delta]
    assert float(state["row_steps"][row]) <= 1.0
    assert tr.selfcal.stats()["pose_rows_reset"] == 1.0
    tr.run(progress=False)
    conf = json.loads((tmp_path / "r" / "config.json").read_text())
    assert conf["self_calibration"]["poses"]["rows_reset"] >= 1


def test_refine_reset_deg_needs_a_correction_per_pose():
    with pytest.raises(InputError, match="'refine_reset_deg' needs refine_poses"):
        tiny(refine_reset_deg=2.0).validate()
    with pytest.raises(InputError, match="'refine_reset_deg' needs refine_poses"):
        tiny(refine_poses=True, refine_knots=8, refine_reset_deg=2.0).validate()
    assert tiny(refine_poses=True, refine_reset_deg=2.0).validate()
