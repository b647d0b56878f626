"""prune_samples / prune_samples_fixed (compacted samples) vs a float64 reference of nerfacc's
visibility rule: the kept set, the packed layout, fixed == exact where it fits, overflow
flags, padding, and that compositing the kept samples loses at most eps of each ray."""

from __future__ import annotations

import math
import random

import pytest
import torch

from fastenerf.kernels.composite import T_MIN, composite
from fastenerf.kernels.prune import prune_samples, prune_samples_fixed
from fastenerf.kernels.raymarch_fixed import empty_fixed_samples
from tests.test_kernel_composite import _packed
from tests.test_kernel_raymarch_fixed import check_against_exact, poisoned_out, untouched_past


def ref_keep(sig, t_s, t_e, pi, eps, thre):
    """Float64 reference, ray by ray over the packed slices only: keep (S,) bool,
    T_i >= eps and alpha_i >= thre; and the smallest relative margin of any decision."""
    S = sig.shape[0]
    T, alpha = torch.ones(S, dtype=torch.float64), torch.zeros(S, dtype=torch.float64)
    inside = torch.zeros(S, dtype=torch.bool)
    for a, n in pi.tolist():
        delta = (t_e[a : a + n].double() - t_s[a : a + n].double()).clamp_min(0)
        tau = sig[a : a + n].double() * delta
        T[a : a + n] = torch.exp(-(torch.cumsum(tau, 0) - tau))
        alpha[a : a + n] = -torch.expm1(-tau)
        inside[a : a + n] = True
    keep = inside & (T >= eps) & (alpha >= thre)
    margin = torch.tensor(math.inf, dtype=torch.float64)
    if eps > 0:
        margin = torch.minimum(margin, (T[inside] / eps).log().abs().min())
    if thre > 0:
        margin = torch.minimum(margin, (alpha[inside] / thre - 1).abs().min())
    return keep, float(margin)


def expected(pi, keep):
    """The packed output the kept set `keep` (S,) of input rays `pi` gives."""
    counts = torch.stack([keep[a : a + n].sum() for a, n in pi.tolist()]).to(torch.int32)
    idx = torch.nonzero(keep).flatten()
    owner = torch.zeros(keep.shape[0], dtype=torch.int32)
    for r, (a, n) in enumerate(pi.tolist()):
        owner[a : a + n] = r
    return _packed(counts), idx, owner[idx]


def _case(eps, thre, R=64, max_n=40):
    """Random packed rays with the special ones (empty, one sample, σ = 0 everywhere, σ = 1e6
    at the first sample or everywhere) and no decision within 1e-3 of a threshold."""
    for _ in range(20):
        seed = random.SystemRandom().randrange(2**31)
        print(f"prune case seed={seed}")  # shown by pytest on failure
        g = torch.Generator().manual_seed(seed)
        counts = torch.randint(0, max_n + 1, (R,), generator=g)
        counts[:3] = 0  # empty rays
        counts[3:5] = 1  # one sample
        counts[5:9] = counts[5:9].clamp_min(3)
        pi = _packed(counts)
        ray = torch.repeat_interleave(torch.arange(R), counts)
        S = int(counts.sum())
        scale = torch.exp(torch.empty(R).uniform_(math.log(0.1), math.log(300.0), generator=g))
        sig = torch.empty(S).exponential_(1.0, generator=g) * scale[ray]
        sig[torch.rand(S, generator=g) < 0.1] = 0.0
        sig[ray == 5] = 0.0  # fully transparent: every sample kept
        sig[int(pi[6, 0])] = 1e6  # T below any eps after the first sample
        sig[ray == 7] = 1e6
        sig[ray == 8] = 0.0
        sig[int(pi[8, 0]) + 1] = 1e6  # the second sample stops it
        dt = torch.empty(S).uniform_(1e-3, 5e-2, generator=g)
        excl = torch.cumsum(dt, 0) - dt
        starts = torch.rand(R, generator=g)[ray] + excl - excl[pi[ray, 0].long()]
        case = (sig, starts, starts + dt, pi)
        if ref_keep(*case, eps, thre)[1] > 1e-3:
            return case
    raise AssertionError("could not draw an unambiguous case")


def _as_fixed_input(sig, t_s, t_e, pi, cut: int, pad: int):
    """The case as a FixedSamples would hold it: rays from `cut` on overflowed (count 0),
    `pad` padding slots at t = 0, ray 0, with NaN density (never to be read)."""
    n_used = int(pi[cut, 0])
    pi = pi.clone()
    pi[cut:] = torch.tensor([n_used, 0], dtype=torch.int32)
    z = torch.zeros(pad)
    sig = torch.cat([sig[:n_used], torch.full((pad,), float("nan"))])
    return sig, torch.cat([t_s[:n_used], z]), torch.cat([t_e[:n_used], z]), pi


SETTINGS = [(T_MIN, 0.0), (1e-2, 0.0), (1e-4, 0.05), (0.0, 0.2)]


@pytest.mark.parametrize("eps,thre", SETTINGS)
@pytest.mark.parametrize("as_fixed", [False, True])
def test_kept_samples_and_layout_match_the_reference(eps, thre, as_fixed):
    case = _case(eps, thre)
    if as_fixed:
        case = _as_fixed_input(*case, cut=50, pad=23)
    sig, t_s, t_e, pi = case
    keep, _ = ref_keep(*case, eps, thre)
    want_pi, idx, want_ri = expected(pi, keep)
    out_pi, out_ts, out_te, out_ri = prune_samples(sig, pi, t_s, t_e, eps, thre)
    assert 0 < idx.numel() < int(pi[:, 1].sum())  # not vacuous: some kept, some dropped
    assert torch.equal(out_pi, want_pi)
    assert torch.equal(out_ts, t_s[idx]) and torch.equal(out_te, t_e[idx])
    assert torch.equal(out_ri, want_ri) and out_ri.dtype == torch.int32
    # the special rays
    counts = out_pi[:, 1]
    assert counts[:3].tolist() == [0, 0, 0]
    assert counts[5] == (pi[5, 1] if thre == 0 else 0)  # σ = 0: alpha 0
    if eps > 0:
        assert counts[6] == 1 and counts[7] == 1  # σ = 1e6 at the first sample
        assert counts[8] == (2 if thre == 0 else 1)


@pytest.mark.parametrize("eps,thre", [(T_MIN, 0.0), (1e-3, 0.05)])
def test_fixed_equals_exact_when_it_fits(eps, thre):
    sig, t_s, t_e, pi = _as_fixed_input(*_case(eps, thre), cut=40, pad=11)
    ref = prune_samples(sig, pi, t_s, t_e, eps, thre)
    S = ref[1].numel()
    for capacity in (S, S + 37):
        f = prune_samples_fixed(sig, pi, t_s, t_e, eps, thre, capacity=capacity)
        assert torch.equal(f.packed_info, ref[0]) and not f.overflow.any()
        assert f.n_used.tolist() == [S]
        check_against_exact(f, ref, capacity)


@pytest.mark.parametrize("as_fixed", [False, True])
def test_src_is_each_kept_samples_input_slot(as_fixed):
    """return_src: each kept slot's input slot (a fixed buffer's padding reads slot 0), so
    what was computed for the input's samples, gathered by it, is the kept samples'."""
    sig, t_s, t_e, pi = _as_fixed_input(*_case(1e-3, 0.0), cut=40, pad=11)
    keep, _ = ref_keep(sig, t_s, t_e, pi, 1e-3, 0.0)
    _, idx, _ = expected(pi, keep)
    if not as_fixed:
        *out, src = prune_samples(sig, pi, t_s, t_e, 1e-3, return_src=True)
        assert torch.equal(src.long(), idx) and src.dtype == torch.int32
        assert torch.equal(out[1], t_s[src.long()])
        return
    S = idx.numel()
    f, src = prune_samples_fixed(sig, pi, t_s, t_e, 1e-3, capacity=S + 9, return_src=True)
    assert src.shape == (S + 9,) and torch.equal(src[:S].long(), idx)
    assert not src[S:].any()  # padding
    # a ray that does not fit writes no slots, so no rows of src either
    f, src = prune_samples_fixed(sig, pi, t_s, t_e, 1e-3, capacity=S // 2, return_src=True)
    used = int(f.n_used)
    assert f.overflow.any() and torch.equal(f.t_starts[:used], t_s[src[:used].long()])
    assert torch.equal(f.t_ends[:used], t_e[src[:used].long()]) and not src[used:].any()


def test_overflow_flags_exactly_the_rays_that_do_not_fit():
    sig, t_s, t_e, pi = _case(1e-3, 0.0)
    ref = prune_samples(sig, pi, t_s, t_e, 1e-3)
    S, counts = ref[1].numel(), ref[0][:, 1]
    for capacity in (0, 1, int(counts[counts > 0][0]), S // 3, S - 1):
        big, out = poisoned_out(pi.shape[0], capacity)
        f = prune_samples_fixed(sig, pi, t_s, t_e, 1e-3, capacity=capacity, out=out)
        assert f is out and untouched_past(big, capacity)
        assert f.overflow.any()
        check_against_exact(f, ref, capacity)


def test_nerfaccs_example_and_the_extremes():
    # nerfacc's render_visibility_from_alpha example: alphas with unit steps, 3 rays
    alphas = torch.tensor([0.4, 0.8, 0.1, 0.8, 0.1, 0.0, 0.9], dtype=torch.float64)
    sig = (-torch.log1p(-alphas)).float()
    t_s = torch.arange(7.0)
    pi = _packed(torch.tensor([3, 2, 2]))
    vis = torch.tensor([True, True, False, True, False, False, True])
    _, ts, _, ri = prune_samples(sig, pi, t_s, t_s + 1, early_stop_eps=0.3, alpha_threshold=0.2)
    assert torch.equal(ts, t_s[vis]) and ri.tolist() == [0, 0, 1, 2]
    # nothing to drop: every sample kept; eps 1: only while T = 1 (ray 2's first is empty)
    out = prune_samples(sig, pi, t_s, t_s + 1, 0.0, 0.0)
    assert torch.equal(out[0], pi) and torch.equal(out[1], t_s)
    assert prune_samples(sig, pi, t_s, t_s + 1, 1.0)[1].tolist() == [0.0, 3.0, 5.0, 6.0]
    # a NaN density is kept (its pixel stays NaN) and ends its ray
    sig[1] = float("nan")
    assert prune_samples(sig, pi, t_s, t_s + 1, 1e-4)[1].tolist() == [0, 1, 3, 4, 5, 6]
    # half-precision density is read as float32
    sig = torch.rand(7) * 3
    half = prune_samples(sig.half(), pi, t_s, t_s + 1, 0.1, 0.1)
    ref = prune_samples(sig.half().float(), pi, t_s, t_s + 1, 0.1, 0.1)
    assert all(torch.equal(a, b) for a, b in zip(half, ref, strict=True))


def test_no_rays():
    z, pi = torch.zeros(0), torch.zeros(0, 2, dtype=torch.int32)
    out = prune_samples(z, pi, z, z)
    assert out[0].shape == (0, 2) and out[1].shape == (0,)
    f = prune_samples_fixed(z, pi, z, z, capacity=3)
    check_against_exact(f, out, 3)


def test_bad_arguments_are_refused():
    sig, t_s, pi = torch.ones(4), torch.arange(4.0), _packed(torch.tensor([4]))
    for eps in (-1.0, 2.0, float("nan")):
        with pytest.raises(ValueError, match="early_stop_eps"):
            prune_samples(sig, pi, t_s, t_s + 1, eps)
    with pytest.raises(ValueError, match="alpha_threshold"):
        prune_samples(sig, pi, t_s, t_s + 1, 1e-4, -0.5)
    with pytest.raises(ValueError, match="sigmas"):
        prune_samples(sig[:3], pi, t_s, t_s + 1)
    with pytest.raises(ValueError, match="packed_info"):
        prune_samples(sig, pi.long(), t_s, t_s + 1)
    with pytest.raises(ValueError, match="out.t_starts"):
        prune_samples_fixed(sig, pi, t_s, t_s + 1, capacity=4, out=empty_fixed_samples(1, 5, "cpu"))


def _composite_kept(sig, rgb, t_s, t_e, pi, eps, thre, bg):
    """Composite of every sample and of the kept ones, with the gradients of one loss."""
    keep, _ = ref_keep(sig, t_s, t_e, pi, eps, thre)
    idx = torch.nonzero(keep).flatten()
    k_pi, k_ts, k_te, _ = prune_samples(sig, pi, t_s, t_e, eps, thre)
    res = []
    for s, c, a, b, p in ((sig, rgb, t_s, t_e, pi), (sig[idx], rgb[idx], k_ts, k_te, k_pi)):
        s, c = s.clone().requires_grad_(), c.clone().requires_grad_()
        out = composite(s, c, a, b, p, background=bg)
        loss = (out["rgb"] * torch.linspace(-1, 1, 3)).sum() + out["depth"].sum()
        res.append((out, *torch.autograd.grad(loss, (s, c))))
    return res, idx, keep


@pytest.mark.parametrize("eps,thre", SETTINGS[:3])
def test_compositing_the_kept_samples_loses_at_most_eps(eps, thre):
    sig, t_s, t_e, pi = _case(eps, thre)
    rgb = torch.rand(sig.shape[0], 3)
    bg = torch.tensor([0.3, 0.6, 0.9])
    ((full, g_s, g_c), (kept, k_s, k_c)), idx, keep = _composite_kept(
        sig, rgb, t_s, t_e, pi, eps, thre, bg
    )
    d_opacity = (full["opacity"] - kept["opacity"]).abs()
    d_rgb = (full["rgb"] - kept["rgb"]).abs().amax(1)
    if eps == T_MIN and thre == 0:
        # composite stops where the pruning does: the same pixels and gradients, bit for bit
        for k in ("rgb", "depth", "opacity"):
            assert torch.equal(full[k], kept[k]), k
        assert torch.equal(g_s[idx], k_s) and torch.equal(g_c[idx], k_c)
        assert (g_s[~keep] == 0).all() and (g_c[~keep] == 0).all()
        return
    # what a ray loses: the light behind T < eps, and (alpha threshold) the dropped samples'
    # opacity: 1 - prod(1 - alpha) over them <= their sum
    alpha = -torch.expm1(-(sig.double() * (t_e - t_s).double()))
    lost = torch.zeros(pi.shape[0], dtype=torch.float64)
    ray = torch.repeat_interleave(torch.arange(pi.shape[0]), pi[:, 1].long())
    lost.index_add_(0, ray, torch.where(keep, 0.0, alpha))
    bound = eps + (lost if thre > 0 else 0.0) + 1e-5
    assert (d_opacity <= bound).all() and (d_rgb <= bound).all()
    assert d_opacity.max() > 1e-6  # not vacuous: some light was lost
    assert torch.isfinite(k_s).all() and k_s.abs().sum() > 0
