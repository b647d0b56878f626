"""Compositing kernels vs a float64 plain-PyTorch reference: values, gradients, stiff cases.

Every compositing test runs for both layouts (`layout` fixture): "ray" (a thread per ray) and
"block" (32 threads per ray, tile scans; on the CPU its blocks run as 32 cooperative fibers).
"""

from __future__ import annotations

import math
import random

import pytest
import torch

from fastenerf.kernels import composite as comp
from fastenerf.kernels.composite import T_MIN, composite, distortion_loss


@pytest.fixture(params=["ray", "block"])
def layout(request) -> str:
    return request.param


def _packed(counts: torch.Tensor) -> torch.Tensor:
    counts = counts.to(torch.int32)
    starts = torch.cumsum(counts, 0, dtype=torch.int32) - counts
    return torch.stack([starts, counts], 1).contiguous()


def _ray_of(packed_info: torch.Tensor) -> torch.Tensor:
    R = packed_info.shape[0]
    return torch.repeat_interleave(torch.arange(R), packed_info[:, 1].long())


def ref_composite(sigmas, rgbs, t_s, t_e, packed_info, bg=None):
    """Float64 reference: exclusive transmittance by cumprod over rays padded to a dense array."""
    R = packed_info.shape[0]
    counts = packed_info[:, 1].long()
    ray = _ray_of(packed_info)
    pos = torch.arange(ray.numel()) - packed_info[:, 0].long()[ray]
    N = int(counts.max()) if R else 0
    delta = (t_e - t_s).clamp_min(0)
    tau = torch.where(delta > 0, sigmas * delta, torch.zeros_like(sigmas))
    alpha = -torch.expm1(-tau)
    trans = torch.ones(R, N + 1, dtype=torch.float64).index_put((ray, pos + 1), torch.exp(-tau))
    T = torch.cumprod(trans, 1)[ray, pos]  # exclusive: product over j < i
    keep = (T >= T_MIN).detach()
    w = torch.where(keep, T * alpha, torch.zeros_like(T))
    mid = 0.5 * (t_s + t_e)
    z = torch.zeros(R, dtype=torch.float64)
    opacity = z.index_add(0, ray, w)
    depth = z.index_add(0, ray, w * mid)
    rgb = torch.zeros(R, 3, dtype=torch.float64).index_add(0, ray, w[:, None] * rgbs)
    if bg is not None:
        rgb = rgb + (1 - opacity)[:, None] * bg
    return {"rgb": rgb, "depth": depth, "opacity": opacity, "weights": w}, T.detach()


def _random_case(R=64, max_n=40, seed=None):
    """Random rays (some empty) whose transmittance never sits right at the stop threshold."""
    if seed is None:
        seed = random.SystemRandom().randrange(2**31)
    print(f"composite case seed={seed}")  # shown by pytest on failure
    g = torch.Generator().manual_seed(seed)
    for _ in range(20):
        counts = torch.randint(0, max_n + 1, (R,), generator=g)
        counts[:3] = 0
        pi = _packed(counts)
        ray = _ray_of(pi)
        S = int(counts.sum())
        scale = torch.exp(torch.empty(R).uniform_(math.log(0.1), math.log(300.0), generator=g))
        sig = torch.empty(S).exponential_(1.0, generator=g) * scale[ray]
        sig[torch.rand(S, generator=g) < 0.1] = 0.0
        dt = torch.empty(S).uniform_(1e-3, 5e-2, generator=g)
        excl = torch.cumsum(dt, 0) - dt
        starts = torch.rand(R, generator=g)[ray] + excl - excl[pi[ray, 0].long()]
        ends = starts + dt
        rgbs = torch.rand(S, 3, generator=g)
        args = [sig, rgbs, starts, ends]
        _, T = ref_composite(*[a.double() for a in args], pi)
        if not ((T / T_MIN).log().abs() < 1e-3).any():  # no ambiguous stop
            return sig, rgbs, starts, ends, pi
    raise AssertionError("could not draw an unambiguous case")


def _loss(out, gs):
    return sum((out[k] * gs[k]).sum() for k in gs)


def _run_both(sig, rgbs, t_s, t_e, pi, bg, grad_keys, layout="ray"):
    s32 = sig.clone().requires_grad_()
    c32 = rgbs.clone().requires_grad_()
    out = composite(s32, c32, t_s, t_e, pi, _ray_of(pi).int(), background=bg, layout=layout)
    s64 = sig.double().requires_grad_()
    c64 = rgbs.double().requires_grad_()
    ref, _ = ref_composite(
        s64, c64, t_s.double(), t_e.double(), pi, None if bg is None else bg.double()
    )
    gs = {k: torch.randn_like(out[k]) for k in grad_keys}
    _loss(out, gs).backward()
    _loss(ref, {k: v.double() for k, v in gs.items()}).backward()
    rc = c64.grad if c64.grad is not None else torch.zeros_like(c64)  # rgb unused in the loss
    return out, ref, (s32.grad, c32.grad), (s64.grad, rc)


@pytest.mark.parametrize(
    "with_bg,grad_keys",
    [
        (True, ("rgb", "depth", "opacity", "weights")),
        (False, ("rgb",)),
        (False, ("depth", "opacity")),
        ("per_ray", ("rgb", "weights")),
        ("per_ray", ("opacity",)),
        (True, ("weights",)),
    ],
)
def test_values_and_gradients_match_float64(with_bg, grad_keys, layout):
    # rays of up to 100 samples: more than one and two chunks of the block layout
    sig, rgbs, t_s, t_e, pi = _random_case(max_n=100)
    bg = torch.rand(pi.shape[0], 3) if with_bg == "per_ray" else torch.rand(3) if with_bg else None
    out, ref, (gs, gc), (rs, rc) = _run_both(sig, rgbs, t_s, t_e, pi, bg, grad_keys, layout)
    for k in ("rgb", "depth", "opacity", "weights"):
        torch.testing.assert_close(out[k].double(), ref[k].detach(), rtol=1e-5, atol=2e-6)
    # sigma gradients carry delta * (sum of up to ~100 terms): scale-aware tolerance
    torch.testing.assert_close(gs.double(), rs, rtol=1e-4, atol=1e-5 * float(rs.abs().max()))
    torch.testing.assert_close(gc.double(), rc, rtol=1e-5, atol=1e-6)


def test_finite_difference_of_sigma_gradient(layout):
    """The analytic gradient agrees with central differences of the float64 reference."""
    sig, rgbs, t_s, t_e, pi = _random_case(R=6, max_n=40)
    s = sig.clone().requires_grad_()
    out = composite(s, rgbs, t_s, t_e, pi, layout=layout)
    g = torch.randn(pi.shape[0], 3)
    (out["rgb"] * g).sum().backward()
    s64 = sig.double()
    h = 1e-6
    for i in torch.randperm(s64.numel())[:10].tolist():
        sp, sm = s64.clone(), s64.clone()
        sp[i] += h
        sm[i] = max(sm[i] - h, 0.0)
        args = (rgbs.double(), t_s.double(), t_e.double(), pi)
        fp = (ref_composite(sp, *args)[0]["rgb"] * g.double()).sum()
        fm = (ref_composite(sm, *args)[0]["rgb"] * g.double()).sum()
        fd = float(fp - fm) / float(sp[i] - sm[i])
        assert abs(float(s.grad[i]) - fd) <= 1e-4 * max(1.0, abs(fd))


def test_early_stop_is_consistent(layout):
    # a dense wall early on each ray: transmittance collapses after a few samples
    R, n = 16, 50
    pi = _packed(torch.full((R,), n))
    S = R * n
    sig = torch.rand(S) * 5
    sig.view(R, n)[:, 5 + torch.randint(0, 10, (1,)).item()] = 2000.0
    dt = torch.full((S,), 0.01)
    t_s = torch.arange(S).float().remainder(n) * 0.01
    t_e = t_s + dt
    rgbs = torch.rand(S, 3)
    s = sig.clone().requires_grad_()
    c = rgbs.clone().requires_grad_()
    out = composite(s, c, t_s, t_e, pi, layout=layout)
    (out["rgb"].sum() + out["depth"].sum() + out["weights"].sum()).backward()
    _, T = ref_composite(sig.double(), rgbs.double(), t_s.double(), t_e.double(), pi)
    stopped = T < T_MIN
    assert stopped.view(R, n).any(1).all()
    assert (out["weights"][stopped] == 0).all()
    assert (s.grad[stopped] == 0).all() and (c.grad[stopped] == 0).all()
    assert (out["weights"][~stopped] > 0).any()
    # compositing only the kept samples gives the same rays
    keep = ~stopped
    counts = keep.view(R, n).sum(1)
    pi2 = _packed(counts)
    out2 = composite(sig[keep], rgbs[keep], t_s[keep], t_e[keep], pi2, layout=layout)
    for k in ("rgb", "depth", "opacity"):
        torch.testing.assert_close(out2[k], out[k].detach())


@pytest.mark.parametrize("delta", [1e-12, 1e-7, 1e-3, 0.5])
def test_stiff_sigma_and_tiny_steps(delta, layout):
    sigmas = torch.tensor([0.0, 1e-3, 1.0, 10.0, 1e3, 1e5, 1e6, 3e38, float("inf")])
    n = sigmas.numel()
    # one ray per sigma value (each preceded by a mild sample) and one ray with all of them
    R1 = n
    sig = torch.cat([torch.stack([torch.full((n,), 0.5), sigmas], 1).reshape(-1), sigmas])
    counts = torch.tensor([2] * R1 + [n])
    pi = _packed(counts)
    S = sig.numel()
    t_s = torch.arange(S).float() * 0.7
    t_e = t_s + delta
    rgbs = torch.rand(S, 3)
    bg = torch.tensor([0.2, 0.5, 0.8])
    out, ref, (gs, gc), (rs, rc) = _run_both(
        sig, rgbs, t_s, t_e, pi, bg, ("rgb", "depth", "opacity", "weights"), layout
    )
    for k, v in out.items():
        assert torch.isfinite(v).all(), k
    assert torch.isfinite(gs).all() and torch.isfinite(gc).all()
    assert (out["opacity"] <= 1 + 1e-6).all() and (out["opacity"] >= 0).all()
    w, rw = out["weights"].double(), ref["weights"].detach()
    # relative accuracy also when sigma * delta ~ 1e-15 (plain 1 - exp(-x) gives 0 there)
    nz = rw > 0
    assert ((w[nz] - rw[nz]).abs() <= 1e-5 * rw[nz] + 1e-30).all()
    assert (w[~nz] == 0).all()
    finite = torch.isfinite(rs)
    torch.testing.assert_close(gs.double()[finite], rs[finite], rtol=1e-4, atol=1e-5)


def test_inf_sigma_on_zero_length_step_is_not_nan(layout):
    sig = torch.tensor([float("inf"), 1.0, float("inf")], requires_grad=True)
    t_s = torch.tensor([0.0, 0.0, 0.5])
    t_e = torch.tensor([0.0, 0.5, 0.5])  # zero, positive, zero length
    pi = _packed(torch.tensor([3]))
    out = composite(sig, torch.rand(3, 3), t_s, t_e, pi, layout=layout)
    (out["rgb"].sum() + out["opacity"].sum()).backward()
    assert torch.isfinite(out["weights"]).all() and torch.isfinite(out["rgb"]).all()
    assert out["weights"][0] == 0 and out["weights"][2] == 0
    assert torch.isfinite(sig.grad).all()


def test_empty_rays_show_background(layout):
    bg = torch.tensor([0.1, 0.2, 0.3])
    pi = _packed(torch.tensor([0, 0, 0]))
    e = torch.zeros(0)
    s = torch.zeros(0, requires_grad=True)
    c = torch.zeros(0, 3, requires_grad=True)
    out = composite(s, c, e, e, pi, background=bg, layout=layout)
    torch.testing.assert_close(out["rgb"], bg.expand(3, 3))
    assert (out["opacity"] == 0).all() and (out["depth"] == 0).all()
    out["rgb"].sum().backward()
    assert s.grad.shape == (0,)
    # no rays at all
    out = composite(s, c, e, e, _packed(torch.zeros(0)), background=bg, layout=layout)
    assert out["rgb"].shape == (0, 3)


def test_every_output_element_is_written(monkeypatch, layout):
    def poisoned(*shape, dtype=torch.float32, device=None):
        t = torch.empty(*shape, dtype=dtype, device=device)
        return t.fill_(float("nan") if dtype.is_floating_point else -(2**30))

    sig, rgbs, t_s, t_e, pi = _random_case(R=32)
    sig[: sig.numel() // 2] *= 1000  # many stopped samples
    clean = _run_both(sig, rgbs, t_s, t_e, pi, None, ("rgb", "weights"), layout)
    monkeypatch.setattr(comp, "_empty", poisoned)
    torch.manual_seed(0)
    s = sig.clone().requires_grad_()
    c = rgbs.clone().requires_grad_()
    out = composite(s, c, t_s, t_e, pi, layout=layout)
    (out["rgb"].sum() + out["weights"].sum()).backward()
    for k, v in out.items():
        assert torch.isfinite(v).all(), k
        torch.testing.assert_close(v, clean[0][k].detach())
    assert torch.isfinite(s.grad).all() and torch.isfinite(c.grad).all()
    w = out["weights"].detach().requires_grad_()
    loss = distortion_loss(w, t_s, t_e, pi)
    loss.sum().backward()
    assert torch.isfinite(loss).all() and torch.isfinite(w.grad).all()


def ref_distortion(w, t_s, t_e, pi):
    ray = _ray_of(pi)
    mid = 0.5 * (t_s + t_e)
    same = ray[:, None] == ray[None, :]
    pair = (w[:, None] * w[None, :] * (mid[:, None] - mid[None, :]).abs() * same).sum(1)
    uni = w * w * (t_e - t_s) / 3
    return torch.zeros(pi.shape[0], dtype=w.dtype).index_add(0, ray, pair + uni)


def test_distortion_loss_matches_brute_force():
    sig, rgbs, t_s, t_e, pi = _random_case(R=24, max_n=30)
    w = torch.rand(sig.numel()) * 0.2
    w32 = w.clone().requires_grad_()
    w64 = w.double().requires_grad_()
    loss = distortion_loss(w32, t_s, t_e, pi)
    ref = ref_distortion(w64, t_s.double(), t_e.double(), pi)
    torch.testing.assert_close(loss.double(), ref.detach(), rtol=1e-5, atol=1e-7)
    g = torch.randn(pi.shape[0])
    (loss * g).sum().backward()
    (ref * g.double()).sum().backward()
    torch.testing.assert_close(w32.grad.double(), w64.grad, rtol=1e-4, atol=1e-6)
    # through the compositor: gradient reaches sigmas
    s = sig.clone().requires_grad_()
    distortion_loss(composite(s, rgbs, t_s, t_e, pi)["weights"], t_s, t_e, pi).sum().backward()
    assert torch.isfinite(s.grad).all() and s.grad.abs().sum() > 0


def test_render_benchmarks_run_at_tiny_size():
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/ is not installed
    from benchmarks.kernels_render import bench_composite, bench_march_composite

    r = bench_composite("cpu", n_rays=64, mean_samples=8, repeats=1)
    assert r["n_samples"] > 0 and r["warp_fwdbwd_ms"] > 0 and r["torch_fwdbwd_ms"] > 0
    assert r["max_abs_err_rgb"] < 1e-5 and r["max_rel_err_grad_sigma"] < 1e-4
    assert r["warp_layout"] == "ray"  # what "auto" picks on the CPU
    for L in ("ray", "block"):
        assert r[f"{L}_fwd_ms"] > 0 and r[f"{L}_fwdbwd_ms"] > 0 and r[f"speedup_{L}_fwdbwd"] > 0
        assert r[f"{L}_max_abs_err_rgb"] < 1e-5 and r[f"{L}_max_rel_err_grad_sigma"] < 1e-4
    r = bench_march_composite("cpu", n_rays=64, resolution=16, repeats=1)
    assert r["n_samples"] > 0 and r["warp_march_ms"] > 0 and r["torch_march_ms"] > 0
    assert r["count_mismatch_fraction"] < 0.01 and r["max_abs_err_rgb"] < 1e-2
    assert r["march_fixed_matches_march_rays"] and r["warp_march_fixed_ms"] > 0
    assert r["march_single_matches"] and r["warp_march_single_ms"] > 0
    assert r["warp_pipeline_fixed_ms"] > 0 and r["fixed_capacity"] > r["n_samples"]


def test_plain_pytorch_baseline_matches_the_kernel():
    """The benchmark's PyTorch composite (its speed baseline) computes the same maths as the
    kernel, values and gradients, with n_max given (graph-capturable) or read."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/ is not installed
    from benchmarks.kernels_render import torch_composite

    sig, rgbs, t_s, t_e, pi = _random_case(R=24, max_n=40)
    bg = torch.tensor([0.2, 0.4, 0.6])
    outs = []
    for fn in (
        lambda s, c: composite(s, c, t_s, t_e, pi, background=bg),
        lambda s, c: torch_composite(s, c, t_s.double(), t_e.double(), pi, bg.double()),
        lambda s, c: torch_composite(
            s, c, t_s.double(), t_e.double(), pi, bg.double(), n_max=int(pi[:, 1].max())
        ),
    ):
        double = len(outs) > 0
        s = (sig.double() if double else sig).clone().requires_grad_()
        c = (rgbs.double() if double else rgbs).clone().requires_grad_()
        out = fn(s, c)
        (out["rgb"].sum() + out["depth"].sum()).backward()
        outs.append((out["rgb"].double(), s.grad.double(), c.grad.double()))
    for a, b in zip(outs[1], outs[2], strict=True):
        assert torch.equal(a, b)
    for a, b in zip(outs[0], outs[1], strict=True):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)


def test_background_shape_is_checked():
    pi = _packed(torch.tensor([2, 1]))
    x = torch.rand(3)
    with pytest.raises(ValueError, match="background"):
        composite(x, torch.rand(3, 3), x, x + 0.1, pi, background=torch.rand(3, 3))
