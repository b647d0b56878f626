"""march_rays_fixed: the same samples as march_rays into fixed buffers, overflow flagged, padding
harmless for compositing (values and gradients)."""

from __future__ import annotations

import random

import pytest
import torch

from fastenerf.kernels.composite import composite, distortion_loss
from fastenerf.kernels.occupancy import OccupancyGrid
from fastenerf.kernels.raymarch import march_rays
from fastenerf.kernels.raymarch_fixed import empty_fixed_samples, march_rays_fixed

BOX = [-2.0, -2.0, -2.0, 2.0, 2.0, 2.0]


def _gen():
    seed = random.SystemRandom().randrange(2**31)
    print(f"raymarch_fixed seed={seed}")  # shown by pytest on failure
    return torch.Generator().manual_seed(seed)


def _grid(gen, C=2, res=16, p_occ=0.3, cylinder=None):
    g = OccupancyGrid([-1, -1, -1, 1, 1, 1], resolution=res, n_cascades=C, cylinder=cylinder)
    sd = g.state_dict()
    dens = (torch.rand(C, res**3, generator=gen) < p_occ).float()
    sd["density"] = torch.where(g.density < 0, g.density, dens)
    sd["threshold"] = torch.tensor([0.5])
    g.load_state_dict(sd)
    return g


def _rays(R, gen):
    o = (torch.rand(R, 3, generator=gen) * 2 - 1) * 3
    target = (torch.rand(R, 3, generator=gen) * 2 - 1) * 0.8
    d = torch.nn.functional.normalize(target - o + 0.3 * torch.randn(R, 3, generator=gen), dim=-1)
    o[:3] = torch.rand(3, 3, generator=gen) - 0.5  # cameras inside the box
    return o, d


# (grid kind, cone, dt_min, dt_max, jitter, segments, max_samples)
CASES = [
    ("cascades", 0.02, 0.01, 0.04, True, None, 10**6),
    ("cylinder", 0.0, 0.02, 0.02, False, 3, 10**6),
    ("none", 0.01, 0.03, 0.1, True, 2, 25),  # per-ray cap split over segments
]


def _march(case, gen, R=80):
    kind, cone, dt_min, dt_max, jit, seg, cap = case
    cyl = (0.6, -0.5, 0.4) if kind == "cylinder" else None
    grid = None if kind == "none" else _grid(gen, cylinder=cyl)
    o, d = _rays(R, gen)
    o[5] = torch.tensor([5.0, 5.0, 5.0])  # outside the box, looking away: no samples
    d[5] = torch.nn.functional.normalize(o[5], dim=0)
    jitter = torch.rand(R, generator=gen) if jit else None
    args = (o, d, BOX, grid, 0.02, 6.0, cone, dt_min, dt_max, cap, jitter, seg)
    return args, march_rays(*args)


def _check_padding(f, n):
    assert (f.t_starts[n:] == 0).all() and (f.t_ends[n:] == 0).all()
    assert (f.ray_indices[n:] == 0).all()


def check_against_exact(f, exact, capacity: int) -> None:
    """FixedSamples `f` of `capacity` slots holds what the exactly sized (packed_info,
    t_starts, t_ends, ray_indices) `exact` holds, as far as it fits: the rays that do not fit
    get count 0 and a flag, the ones that do keep their slots, the rest is padding."""
    pi, ts, te, ri = exact
    counts = pi[:, 1]
    ends = torch.cumsum(counts, 0)
    fits = ends <= capacity
    assert f.t_starts.shape == f.t_ends.shape == f.ray_indices.shape == (capacity,)
    assert f.overflow.dtype == torch.bool
    assert torch.equal(f.overflow, (counts > 0) & ~fits)
    assert torch.equal(f.packed_info[:, 1], torch.where(fits, counts, 0))
    n_used = int(ends[fits].max()) if fits.any() else 0
    assert f.n_used.tolist() == [n_used] and f.n_wanted.tolist() == [ts.numel()]
    assert (f.packed_info[:, 0] <= capacity).all()
    assert torch.equal(f.packed_info[fits], pi[fits])
    assert torch.equal(f.t_starts[:n_used], ts[:n_used])
    assert torch.equal(f.t_ends[:n_used], te[:n_used])
    assert torch.equal(f.ray_indices[:n_used], ri[:n_used])
    _check_padding(f, n_used)


def poisoned_out(R: int, capacity: int, guard: int = 50):
    """(big, out): output buffers of `capacity` slots that are views into `guard` slots larger
    poisoned ones (NaN, 7); `untouched_past(big, capacity)` says nothing landed beyond."""
    big = empty_fixed_samples(R, capacity + guard, "cpu")
    for t in big:
        t.fill_(float("nan") if t.dtype.is_floating_point else 7)
    out = big._replace(
        t_starts=big.t_starts[:capacity],
        t_ends=big.t_ends[:capacity],
        ray_indices=big.ray_indices[:capacity],
    )
    return big, out


def untouched_past(big, capacity: int) -> bool:
    return bool(
        big.t_starts[capacity:].isnan().all()
        and big.t_ends[capacity:].isnan().all()
        and (big.ray_indices[capacity:] == 7).all()
    )


@pytest.mark.parametrize("case", CASES)
def test_equals_march_rays_when_it_fits(case):
    gen = _gen()
    args, (pi, ts, te, ri) = _march(case, gen)
    S = ts.numel()
    assert S > 200 and (pi[:, 1] == 0).any()  # not vacuous; empty rays included
    for capacity in (S, S + 37):
        f = march_rays_fixed(*args, capacity=capacity)
        assert torch.equal(f.packed_info, pi) and not f.overflow.any()
        assert f.n_used.tolist() == [S]
        check_against_exact(f, (pi, ts, te, ri), capacity)


@pytest.mark.parametrize("case", CASES)
def test_overflow_flags_exactly_the_rays_that_do_not_fit(case):
    gen = _gen()
    args, (pi, ts, te, ri) = _march(case, gen)
    S, R = ts.numel(), pi.shape[0]
    counts = pi[:, 1]
    for capacity in (0, 1, int(counts[counts > 0][0]), S // 3, S - 1):
        # the buffers are views into larger poisoned ones: nothing may land past `capacity`
        big, out = poisoned_out(R, capacity)
        f = march_rays_fixed(*args, capacity=capacity, out=out)
        assert f is out  # written in place
        assert untouched_past(big, capacity)
        assert f.overflow.any()
        check_against_exact(f, (pi, ts, te, ri), capacity)


def test_no_rays_and_zero_capacity():
    grid = OccupancyGrid([-1, -1, -1, 1, 1, 1], resolution=8)
    f = march_rays_fixed(torch.zeros(0, 3), torch.zeros(0, 3), BOX, grid, capacity=4)
    assert f.packed_info.shape == (0, 2) and f.overflow.shape == (0,)
    assert f.n_used.tolist() == [0] and f.n_wanted.tolist() == [0]
    _check_padding(f, 0)
    o, d = _rays(4, _gen())
    f = march_rays_fixed(o, d, BOX, grid, capacity=0)
    exact = march_rays(o, d, BOX, grid)
    assert f.t_starts.shape == (0,) and f.n_used.tolist() == [0]
    # every ray with samples overflows; a random ray that misses the box has none to lose
    assert torch.equal(f.overflow, exact[0][:, 1] > 0) and f.overflow.any()
    assert f.n_wanted.item() == exact[1].numel()


def test_bad_arguments_are_refused():
    o, d = _rays(4, _gen())
    with pytest.raises(ValueError, match="capacity"):
        march_rays_fixed(o, d, BOX, None, capacity=-1)
    with pytest.raises(ValueError, match="out.t_starts"):
        march_rays_fixed(o, d, BOX, None, capacity=8, out=empty_fixed_samples(4, 9, "cpu"))
    with pytest.raises(ValueError, match="out.packed_info"):
        march_rays_fixed(o, d, BOX, None, capacity=8, out=empty_fixed_samples(5, 8, "cpu"))


def _field(o, d, t_s, t_e, ri):
    """Analytic density / colour at the sample midpoints (finite everywhere, padding too)."""
    x = o[ri.long()] + 0.5 * (t_s + t_e)[:, None] * d[ri.long()]
    sigma = 40.0 * torch.exp(-4.0 * (x.norm(dim=-1) - 0.6) ** 2)
    return sigma, torch.sigmoid(3.0 * x)


def _render(sig, rgb, t_s, t_e, ri, pi, bg):
    sig, rgb = sig.detach().requires_grad_(), rgb.detach().requires_grad_()
    out = composite(sig, rgb, t_s, t_e, pi, ri, background=bg)
    dist = distortion_loss(out["weights"], t_s, t_e, pi)
    g = torch.linspace(-1, 1, 3 * pi.shape[0]).view(-1, 3)
    loss = (out["rgb"] * g).sum() + out["depth"].sum() + out["opacity"].sum() + dist.sum()
    loss = loss + (out["weights"] * (t_s + t_e)).sum()
    gs, gc = torch.autograd.grad(loss, (sig, rgb))
    return out, dist, gs, gc


@pytest.mark.parametrize("slack", [0, 53, -1])
def test_composite_over_fixed_buffers_equals_exact(slack):
    """An MLP-like field evaluated on every slot, padding included, then composite and the
    distortion loss: the pixels and the sigma / rgb gradients of the exact-size path; the
    padding gets weight 0 and gradient 0. slack -1: a buffer too small (overflowed rays show
    the background, the others are unchanged)."""
    gen = _gen()
    args, (pi, ts, te, ri) = _march(CASES[0], gen, R=48)
    o, d = args[0], args[1]
    S = ts.numel()
    capacity = S + slack if slack >= 0 else S // 2
    f = march_rays_fixed(*args, capacity=capacity)
    n = int(f.n_used)
    bg = torch.tensor([0.2, 0.4, 0.9])
    sig, rgb = _field(o, d, f.t_starts, f.t_ends, f.ray_indices)
    ref_sig, ref_rgb = _field(o, d, ts, te, ri)
    # The same samples give the same field values only up to an ulp: torch's vectorised loop
    # and its tail round differently, and the tail falls elsewhere in a longer buffer (seed
    # 1174341980 on CI). Share the values so that compositing alone is compared exactly.
    torch.testing.assert_close(sig[:n], ref_sig[:n])
    torch.testing.assert_close(rgb[:n], ref_rgb[:n])
    ref_sig, ref_rgb = torch.cat([sig[:n], ref_sig[n:]]), torch.cat([rgb[:n], ref_rgb[n:]])
    ref, ref_dist, ref_gs, ref_gc = _render(ref_sig, ref_rgb, ts, te, ri, pi, bg)
    out, dist, gs, gc = _render(sig, rgb, f.t_starts, f.t_ends, f.ray_indices, f.packed_info, bg)
    keep = ~f.overflow
    assert f.overflow.any() == (slack < 0)
    for k in ("rgb", "depth", "opacity"):
        torch.testing.assert_close(out[k][keep], ref[k][keep], rtol=0, atol=0)
    torch.testing.assert_close(dist[keep], ref_dist[keep], rtol=0, atol=0)
    torch.testing.assert_close(out["rgb"][~keep], bg.expand(int((~keep).sum()), 3))
    assert (out["weights"][n:] == 0).all() and (gs[n:] == 0).all() and (gc[n:] == 0).all()
    # the samples that were written are march_rays' first n: identical weights and gradients
    torch.testing.assert_close(out["weights"][:n], ref["weights"][:n], rtol=0, atol=0)
    torch.testing.assert_close(gc[:n], ref_gc[:n], rtol=0, atol=0)
    torch.testing.assert_close(gs[:n], ref_gs[:n], rtol=0, atol=0)
    assert torch.isfinite(gs).all() and torch.isfinite(gc).all() and gs[:n].abs().sum() > 0


# -- the single pass (march_scratch.SINGLE_PASS): the same samples from one march ----------


def _both(fn, *args, **kw):
    """fn's outputs marched twice and marched once, in that order."""
    return fn(*args, single_pass=False, **kw), fn(*args, single_pass=True, **kw)


def _same(a, b) -> None:
    for x, y in zip(a, b, strict=True):
        assert torch.equal(x, y)


@pytest.mark.parametrize("case", CASES)
def test_single_pass_gives_the_two_passes_samples(case):
    """Exact and fixed buffers, fitting and overflowing (nothing past the capacity), and the
    per-ray cap split over segments (CASES' last): bit for bit."""
    from fastenerf.kernels import march_scratch as ms
    from fastenerf.kernels import raymarch as rm

    gen = _gen()
    args, exact = _march(case, gen)
    p = rm.plan_march(*args)
    assert ms.scratch_stride(p.R * p.n_seg, p.bound, True) == p.bound < 10**6  # not the cap
    _same(*_both(march_rays, *args))
    S, R = exact[1].numel(), exact[0].shape[0]
    for capacity in (S + 37, S - 1, S // 3):
        outs = []
        for single in (False, True):
            big, out = poisoned_out(R, capacity)
            outs.append(march_rays_fixed(*args, single, capacity=capacity, out=out))
            assert untouched_past(big, capacity)
        _same(*outs)
        check_against_exact(outs[1], exact, capacity)


def test_single_pass_marches_again_what_its_rows_cannot_hold(monkeypatch):
    """Rows shorter than a slice (a ray with no direction reaches max_samples; or the scratch
    limit shortens every row): those slices come from a second march, the rest from the
    rows, and the output is still the two passes' own; with no room at all, two passes."""
    from fastenerf.kernels import march_scratch as ms
    from fastenerf.kernels import raymarch as rm

    gen = _gen()
    box = [-1.0, -1.0, -1.0, 1.0, 1.0, 1.0]
    o, d = _rays(60, gen)
    o[0], d[0] = torch.tensor([0.1, 0.2, 0.3]), torch.zeros(3)  # t1 ~ 1e30: max_samples
    grid = OccupancyGrid(box, resolution=16)  # new: every cell occupied
    args = (o, d, box, grid, 0.0, None, 0.0, 0.01, 0.01, 300, torch.rand(60, generator=gen), 3)
    p = rm.plan_march(*args)
    two, one = _both(march_rays, *args)
    _same(two, one)
    assert two[0][0, 1] == 300 > p.bound  # the degenerate ray's slice outgrew its row
    assert (two[0][1:, 1] <= p.n_seg * p.bound).all() and two[0][1:, 1].max() > p.bound
    R = p.R * p.n_seg
    for slots in (3 * R, R - 1):  # rows of 3 samples; no room: scratch_stride 0
        monkeypatch.setattr(ms, "SCRATCH_MAX_SLOTS", slots)
        assert ms.scratch_stride(R, p.bound, True) == slots // R
        _same(two, march_rays(*args, single_pass=True))
        fixed = _both(march_rays_fixed, *args, capacity=two[1].numel() - 5)
        _same(*fixed)
        assert fixed[0].overflow.any()


def test_single_pass_is_off_unless_asked_and_follows_the_module_switch(monkeypatch):
    from fastenerf.kernels import march_scratch as ms
    from fastenerf.kernels import raymarch as rm

    gen = _gen()
    args, _ = _march(CASES[0], gen)
    p = rm.plan_march(*args)
    n = p.R * p.n_seg
    assert ms.SINGLE_PASS is False and ms.scratch_stride(n, p.bound, None) == 0
    monkeypatch.setattr(ms, "SINGLE_PASS", True)
    assert ms.scratch_stride(n, p.bound, None) == p.bound
    assert ms.scratch_stride(n, p.bound, False) == ms.scratch_stride(0, p.bound, True) == 0
