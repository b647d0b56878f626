"""Windows on the pose grid, event/negative pixels, rays in torch, targets (numpy and Warp)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fastenerf.config import IntrinsicsConfig
from fastenerf.data.events import EventIndex, EventStream
from fastenerf.data.rig import Rig
from fastenerf.errors import InputError
from fastenerf.render import camera_directions, generate_rays
from fastenerf.sampling import RaySampler, WindowSampler


def make_sampler(stream, cfg, use_kernel=None, **kw):
    idx = EventIndex(
        stream,
        cfg.pos_threshold,
        cfg.neg_threshold,
        cfg.polarity_offset,
        t_start=cfg.t_start_us,
        t_end=cfg.t_end_us,
        loop=cfg.loop,
    )
    ws = WindowSampler(
        cfg.n_views,
        cfg.t_start_us,
        cfg.t_end_us,
        kw.pop("win_min", 1),
        kw.pop("win_max", 30),
        kw.pop("redraw", "step"),
        cfg.loop,
        seed=3,
    )
    rig = Rig.from_scene(cfg)
    args = dict(rays_per_step=400, windows_per_step=4, neg_ratio=0.25, seed=5)
    args.update(kw)
    return RaySampler(idx, rig, ws, use_kernel=use_kernel, **args), idx, ws, rig


def test_windows_end_on_the_grid_with_lengths_in_range():
    ws = WindowSampler(100, 1000, 101_000, 3, 7, "step", loop=True, seed=0)
    j0, j1 = ws.sample(5000)
    assert ((j1 >= 1) & (j1 <= 100)).all()
    assert set(np.unique(j1 - j0)) == set(range(3, 8))
    assert (ws.grid_times(j1) == 1000 + 1000 * j1).all()
    assert (j0 < 0).any()  # a loop wraps before t_start ...
    assert ((ws.pose_index(j0) >= 0) & (ws.pose_index(j0) < 100)).all()
    assert ws.pose_index(np.array([-1, 0, 100])).tolist() == [99, 0, 0]
    flat = WindowSampler(100, 0, 100_000, 3, 7, "step", loop=False, seed=0)
    j0, j1 = flat.sample(5000)
    assert (j0 >= 0).all() and (j0 < j1).all()  # ... a plain stream clamps


def test_load_time_lengths_are_fixed_per_end_view():
    ws = WindowSampler(50, 0, 50_000, 1, 20, "load", loop=True, seed=1)
    j0, j1 = ws.sample(4000)
    for j in np.unique(j1):
        assert len(np.unique((j1 - j0)[j1 == j])) == 1
    step = WindowSampler(50, 0, 50_000, 1, 20, "step", loop=True, seed=1)
    j0, j1 = step.sample(4000)
    assert max(len(np.unique((j1 - j0)[j1 == j])) for j in np.unique(j1)) > 1
    with pytest.raises(InputError):
        WindowSampler(50, 0, 50_000, 5, 2)


@pytest.mark.parametrize("redraw", ["step", "load"])
def test_lengthened_windows_draw_longer_and_resume_mid_block_exactly(
    random_stream, scene_config, redraw
):
    """set_win_max changes the lengths from the next block on; a checkpoint taken between
    the change and that block resumes with the block as drawn (short) and the next as the
    run went on (long), bit for bit."""
    cfg = scene_config(16, 12, t_end_us=100_000, n_views=50)
    stream = random_stream(3000, 16, 12, t_max=99_999)
    rs, _, ws, _ = make_sampler(stream, cfg, use_kernel=False, prefetch=4, win_max=3, redraw=redraw)
    [rs.sample() for _ in range(2)]
    ws.set_win_max(40)
    assert ws.win_max == 40
    state = rs.state_dict()
    rest = [rs.sample() for _ in range(6)]  # two of the short block, then a long one

    rs.load_state_dict(state)
    assert ws.win_max == 40
    again = [rs.sample() for _ in range(6)]
    for a, b in zip(rest, again, strict=True):
        assert torch.equal(a.pix, b.pix) and torch.equal(a.rays_o, b.rays_o)
        assert torch.equal(a.target, b.target)
    j0, j1 = ws.sample(4000)
    assert (j1 - j0).max() > 3 and (j1 - j0).max() <= 40
    with pytest.raises(InputError, match="win_max >= win_min"):
        ws.set_win_max(0)


def test_targets_and_pixels(random_stream, scene_config):
    cfg = scene_config(16, 12, t_end_us=100_000, n_views=50)
    stream = random_stream(3000, 16, 12, t_max=99_999)
    rs, idx, ws, rig = make_sampler(stream, cfg, use_kernel=False)
    state = ws.state_dict()
    b = rs.sample()
    ws.load_state_dict(state)
    j0, j1 = ws.sample(4)  # the same windows again
    win = np.repeat(np.arange(4), 100)
    t0, t1 = ws.grid_times(j0)[win], ws.grid_times(j1)[win]
    pix = b.pix.numpy()
    assert np.allclose(b.target.numpy(), idx.query(pix, t0, t1))
    # Event pixels have events in their window (wrapping on this loop) ...
    pos = b.positive.numpy()
    counts = np.zeros(len(pix))
    for part in (idx.split_wrapped(t0, t1)[:2], idx.split_wrapped(t0, t1)[2:]):
        counts += idx.counts(pix, *part)[0]
    assert (counts[pos] > 0).all()
    # ... and a quarter of each window's rays are negatives (uniform pixels).
    assert pos.reshape(4, 100)[:, 75:].sum() == 0 and pos.reshape(4, 100)[:, :75].all()
    # Channel per pixel (RGGB), rays at the window's two poses.
    assert torch.equal(b.channel, rig.channel(b.pix))
    c2w0 = rig.pose(ws.grid_times(j0))[win]
    o, d = rig.rays(pix[:5], c2w0[:5])
    assert np.allclose(b.rays_o[:5].numpy(), o, atol=1e-5)
    assert np.allclose(b.rays_d[:5].numpy(), d, atol=1e-5)
    c2w1 = rig.pose(ws.grid_times(j1))[win]
    o, d = rig.rays(pix[-5:], c2w1[-5:])
    assert np.allclose(b.rays_d[-5:].numpy(), d, atol=1e-5)
    assert b.rays_o.shape == (800, 3) and b.target.shape == (400,)


def test_a_window_without_events_falls_back_to_uniform_pixels(scene_config):
    cfg = scene_config(8, 6, t_end_us=100_000, n_views=100, loop=False)
    # All events in the last 10 ms: windows ending before 90 ms see none.
    n = 200
    rng = np.random.default_rng(0)
    stream = EventStream.from_arrays(
        rng.integers(0, 8, n),
        rng.integers(0, 6, n),
        np.sort(rng.integers(90_001, 100_000, n)),
        rng.choice([-1, 1], n),
        8,
        6,
    )
    rs, idx, ws, _ = make_sampler(stream, cfg, use_kernel=False, win_min=1, win_max=5)
    seen_empty = False
    for _ in range(20):
        b = rs.sample()
        assert ((b.pix >= 0) & (b.pix < 48)).all() and torch.isfinite(b.rays_d).all()
        per = b.positive.reshape(4, -1).any(1)
        seen_empty |= bool((~per).any())
    assert seen_empty
    # A stream with no events at all never crashes either.
    empty = EventStream.from_arrays([], [], [], [], 8, 6, allow_empty=True)
    rs, *_ = make_sampler(empty, cfg, use_kernel=False)
    b = rs.sample()
    assert not b.positive.any() and (b.target == 0).all()


def test_mono_sensor_has_no_channel(random_stream, scene_config):
    cfg = scene_config(16, 12, t_end_us=100_000, n_views=20, bayer=None)
    rs, *_ = make_sampler(random_stream(500, 16, 12, t_max=99_999), cfg, use_kernel=False)
    assert rs.sample().channel is None


def test_distortion_goes_through_the_direction_table(scene_config):
    cfg = scene_config(32, 24, intrinsics=IntrinsicsConfig(30, 30, 16, 12, k1=-0.2, k2=0.05))
    rig = Rig.from_scene(cfg)
    assert rig.intrinsics.distorted
    dirs = camera_directions(rig.intrinsics)
    pix = np.array([0, 31, 400, 767])
    c2w = rig.pose([123_456])[0]
    o, d = generate_rays(dirs[torch.from_numpy(pix)], torch.from_numpy(c2w).float())
    o_ref, d_ref = rig.rays(pix, c2w)
    assert np.allclose(d.numpy(), d_ref, atol=1e-5) and np.allclose(o.numpy(), o_ref, atol=1e-5)


def test_warp_targets_match_numpy(random_stream, scene_config):
    pytest.importorskip("fastenerf.kernels.events", reason="Warp event kernel not built yet")
    cfg = scene_config(16, 12, t_end_us=100_000, n_views=50)
    stream = random_stream(3000, 16, 12, t_max=99_999)
    rs_np, *_ = make_sampler(stream, cfg, use_kernel=False)
    rs_wp, *_ = make_sampler(stream, cfg, use_kernel=None)
    assert rs_wp.target_backend == "warp", "the Warp window_sum disagreed with EventIndex"
    for _ in range(3):
        a, b = rs_np.sample(), rs_wp.sample()
        assert torch.equal(a.pix, b.pix)
        assert torch.allclose(a.target, b.target, atol=1e-5)
    # windows that wrap past the loop's start (the host decides there is a second part) and
    # ones that do not, in one batch and alone
    idx = rs_wp.index
    assert idx.loop
    pix = torch.arange(0, 16 * 12, 7)
    n = len(pix)
    t1 = np.linspace(10_000, 90_000, n).astype(np.int64)
    for t0 in (t1 - 30_000, t1 - 5_000):  # some before t_start / none
        want = idx.query(pix.numpy(), t0, t1)
        got = rs_wp.targets(pix, t0, t1).numpy()
        assert np.allclose(got, want, atol=1e-5), (t0 < idx.t_start).any()


def test_sampler_state_round_trip(random_stream, scene_config):
    cfg = scene_config(16, 12, t_end_us=100_000, n_views=50)
    rs, *_ = make_sampler(
        random_stream(1000, 16, 12, t_max=99_999), cfg, use_kernel=False, redraw="load"
    )
    rs.sample()
    state = rs.state_dict()
    a = rs.sample()
    rs.load_state_dict(state)
    b = rs.sample()
    assert torch.equal(a.pix, b.pix) and torch.equal(a.rays_d, b.rays_d)


def test_prefetched_blocks_hand_out_whole_batches_and_resume_mid_block(random_stream, scene_config):
    cfg = scene_config(16, 12, t_end_us=100_000, n_views=50)
    stream = random_stream(3000, 16, 12, t_max=99_999)
    rs, idx, *_ = make_sampler(stream, cfg, use_kernel=False, prefetch=4)
    batches = [rs.sample() for _ in range(3)]
    state = rs.state_dict()
    assert state["position"] == 3
    rest = [rs.sample() for _ in range(3)]  # the block's last batch, then a new block
    for b in batches + rest:
        assert b.rays_o.shape == (800, 3) and b.rays_o.is_contiguous()
        assert b.pix.shape == b.target.shape == b.positive.shape == (400,)
        assert b.channel is not None and b.channel.shape == (400,)
        assert b.n_windows == 4
    for b in batches:  # per window, its pixels' rays leave one camera centre at t0 and at t1
        o = b.rays_o.reshape(2, 4, 100, 3)
        assert torch.allclose(o, o[:, :, :1].expand_as(o))
    assert not torch.equal(batches[0].pix, batches[1].pix)
    rs.load_state_dict(state)
    again = [rs.sample() for _ in range(3)]
    for a, b in zip(rest, again, strict=True):
        assert torch.equal(a.pix, b.pix) and torch.equal(a.rays_d, b.rays_d)
        assert torch.equal(a.target, b.target)
    with pytest.raises(InputError, match="prefetch"):
        make_sampler(stream, cfg, use_kernel=False, prefetch=0)
