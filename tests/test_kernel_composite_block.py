"""The two compositing layouts ("ray": a thread per ray, "block": 32 threads per ray with tile
scans over chunks of 32 samples) against each other and against float64, where the block
layout has edges of its own: chunk boundaries, the carry between chunks, NaN and inf in a later
chunk, every ray stopped at once. The shared cases run for both layouts in
test_kernel_composite.py."""

from __future__ import annotations

import pytest
import torch
import warp as wp

from fastenerf.kernels import common
from fastenerf.kernels import composite as comp
from fastenerf.kernels.composite import CUDA_AUTO, T_MIN, composite, resolve_layout
from fastenerf.kernels.composite_block import (
    BLOCK_DIM,
    composite_bwd_block_kernel,
    composite_fwd_block,
)
from tests.test_kernel_composite import _packed, _random_case, _ray_of, ref_composite

ALL_GRADS = ("rgb", "depth", "opacity", "weights")


@pytest.fixture(params=["ray", "block"])
def layout(request) -> str:
    return request.param


def _n_used(out: dict) -> torch.Tensor:
    """n_used (R,) int32 as the forward pass saved it for the backward."""
    return out["rgb"].grad_fn.saved_tensors[6]


def _run(sig, rgbs, t_s, t_e, pi, layout, bg=None, gs=None):
    """composite + backward of sum_k <out[k], gs[k]>: (outputs, n_used, dsigma, drgb)."""
    s = sig.clone().requires_grad_()
    c = rgbs.clone().requires_grad_()
    out = composite(s, c, t_s, t_e, pi, background=bg, layout=layout)
    if gs is None:
        gs = {k: torch.randn_like(out[k], generator=torch.Generator().manual_seed(7)) for k in out}
    n_used = _n_used(out).clone()  # freed by the backward
    sum((out[k] * g).sum() for k, g in gs.items()).backward()
    return {k: v.detach() for k, v in out.items()}, n_used, s.grad, c.grad


def _rays_of_steps(taus_per_ray: list[torch.Tensor], dt: float = 0.01):
    """Packed rays with the given optical depths, steps of dt (sigma = tau / dt)."""
    counts = torch.tensor([len(t) for t in taus_per_ray])
    pi = _packed(counts)
    tau = torch.cat(taus_per_ray) if len(taus_per_ray) else torch.zeros(0)
    S = tau.numel()
    t_s = (torch.arange(S) - pi[_ray_of(pi), 0]).float() * dt + 0.5
    return tau / dt, torch.rand(S, 3), t_s, t_s + dt, pi


def test_layout_choice():
    assert resolve_layout("auto", torch.device("cpu")) == "ray"
    assert resolve_layout("auto", torch.device("cuda")) == CUDA_AUTO in ("ray", "block")
    assert resolve_layout("block", torch.device("cpu")) == "block"
    x = torch.rand(2)
    with pytest.raises(ValueError, match="layout"):
        composite(x, torch.rand(2, 3), x, x + 0.1, _packed(torch.tensor([2])), layout="warp")


def test_block_layout_runs_32_lanes_on_the_cpu():
    """Without cooperative CPU blocks Warp runs a 1-lane block: the kernels would still be right
    (they read the width from wp.block_dim()) and test nothing of the 32-lane schedule."""
    cpu_blocks = wp.config.enable_cpu_blocks
    sig, rgbs, t_s, t_e, pi = _random_case(R=8, max_n=70)
    _run(sig, rgbs, t_s, t_e, pi, "block")
    for kernel in (composite_fwd_block, composite_bwd_block_kernel(True, True, True, True)):
        assert common.tiled_launcher(kernel, BLOCK_DIM)._cmds["cpu"].block_dim == 32
    assert wp.config.enable_cpu_blocks == cpu_blocks  # switched on only while recording


@pytest.mark.parametrize("bg_kind", ["shared", "per_ray"])
def test_layouts_agree_on_a_random_batch(bg_kind):
    sig, rgbs, t_s, t_e, pi = _random_case(R=160, max_n=150)
    R = pi.shape[0]
    bg = torch.rand(R, 3) if bg_kind == "per_ray" else torch.rand(3)
    ray = _run(sig, rgbs, t_s, t_e, pi, "ray", bg)
    block = _run(sig, rgbs, t_s, t_e, pi, "block", bg)
    # no transmittance near T_MIN in the case: both stop at the same sample
    assert torch.equal(ray[1], block[1])
    assert ((ray[1] > 32) & (ray[1] < pi[:, 1])).any()  # some stop after the first chunk
    for k in ALL_GRADS:
        torch.testing.assert_close(block[0][k], ray[0][k], rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(block[2], ray[2], rtol=1e-4, atol=1e-5 * float(ray[2].abs().max()))
    torch.testing.assert_close(block[3], ray[3], rtol=1e-5, atol=1e-6)
    # samples past n_used: weight 0 and no gradient, in both
    for out, n_used, g_s, g_c in (ray, block):
        pos = torch.arange(sig.numel()) - pi[_ray_of(pi), 0]
        past = pos >= n_used[_ray_of(pi)]
        assert past.any() and (out["weights"][past] == 0).all()
        assert (g_s[past] == 0).all() and (g_c[past] == 0).all()


STOPS = [1, 2, 17, 31, 32, 33, 45, 63, 64, 65, 96, 97]


def test_stops_inside_chunks_and_at_their_boundaries(layout):
    """Ray j has a wall (tau = 20) at sample STOPS[j] - 1 among steps of tau = 0.01, so its first
    sample with T_i < T_MIN is STOPS[j]; the last rays do not stop (lengths 32, 64, 70, 1, 0)."""
    rays = []
    for k in STOPS:
        tau = torch.full((100,), 0.01)
        tau[k - 1] = 20.0
        rays.append(tau)
    rays += [torch.full((n,), 0.01) for n in (32, 64, 70, 1, 0)]
    sig, rgbs, t_s, t_e, pi = _rays_of_steps(rays)
    bg = torch.rand(pi.shape[0], 3)
    out, n_used, g_s, g_c = _run(sig, rgbs, t_s, t_e, pi, layout, bg)
    assert n_used.tolist() == STOPS + [32, 64, 70, 1, 0]
    ref, T = ref_composite(sig.double(), rgbs.double(), t_s.double(), t_e.double(), pi, bg.double())
    for k in ALL_GRADS:
        torch.testing.assert_close(out[k].double(), ref[k], rtol=1e-5, atol=1e-6)
    ray = _ray_of(pi)
    pos = torch.arange(sig.numel()) - pi[ray, 0]
    visited = pos < n_used[ray]
    assert torch.equal(visited, T >= T_MIN)
    assert (out["weights"][visited] > 0).all() and (out["weights"][~visited] == 0).all()
    assert (g_s[~visited] == 0).all() and (g_c[~visited] == 0).all()
    assert (g_c[visited] != 0).all()


def test_nan_density_stops_its_ray_and_no_other(layout):
    """NaN at sample 0, at a chunk's first (32) and mid-chunk (40): the ray's weight is NaN
    there, 0 after, n_used = i + 1, its colour and the gradients of its visited samples NaN;
    every other ray is bit for bit what it is without the NaN rays."""
    sig, rgbs, t_s, t_e, pi = _rays_of_steps([torch.full((90,), 0.02) for _ in range(6)])
    nan_at = {1: 0, 2: 32, 4: 40}
    bad = sig.clone()
    for r, i in nan_at.items():
        bad[int(pi[r, 0]) + i] = float("nan")
    out, n_used, g_s, g_c = _run(bad, rgbs, t_s, t_e, pi, layout)
    clean, _, c_s, c_c = _run(sig, rgbs, t_s, t_e, pi, layout)
    ray = _ray_of(pi)
    for r in range(pi.shape[0]):
        m = ray == r
        if r not in nan_at:
            assert n_used[r] == 90
            for k in ("rgb", "depth", "opacity"):
                assert torch.equal(out[k][r], clean[k][r]), k
            for a, b in ((out["weights"], clean["weights"]), (g_s, c_s), (g_c, c_c)):
                assert torch.equal(a[m], b[m])
            continue
        i = nan_at[r]
        assert n_used[r] == i + 1
        w = out["weights"][m]
        assert torch.isnan(w[i]) and torch.isfinite(w[:i]).all() and (w[i + 1 :] == 0).all()
        assert torch.isnan(out["rgb"][r]).all() and torch.isnan(out["opacity"][r])
        assert torch.isnan(g_s[m][: i + 1]).all() and (g_s[m][i + 1 :] == 0).all()
        assert torch.isnan(g_c[m][i]).all() and (g_c[m][i + 1 :] == 0).all()
        assert torch.isfinite(g_c[m][:i]).all()


def test_inf_density_and_tiny_steps_in_later_chunks(layout):
    """inf density on a positive step at sample 40 (stops the ray there), inf on zero-length
    steps at 31 and 32 (no effect), and optical depths ~1e-12 through three chunks."""
    tiny = torch.full((100,), 1e-12)
    wall = torch.full((100,), 0.01)
    zero_len = torch.full((100,), 0.01)
    sig, rgbs, t_s, t_e, pi = _rays_of_steps([tiny, wall, zero_len])
    s1, s2 = int(pi[1, 0]), int(pi[2, 0])
    sig[s1 + 40] = float("inf")
    sig[s2 + 31 : s2 + 33] = float("inf")
    t_e[s2 + 31 : s2 + 33] = t_s[s2 + 31 : s2 + 33]
    bg = torch.tensor([0.2, 0.5, 0.8])
    out, n_used, g_s, g_c = _run(sig, rgbs, t_s, t_e, pi, layout, bg)
    assert n_used.tolist() == [100, 41, 100]
    for v in (*out.values(), g_s, g_c):
        assert torch.isfinite(v).all()
    ref, _ = ref_composite(sig.double(), rgbs.double(), t_s.double(), t_e.double(), pi, bg.double())
    w, rw = out["weights"].double(), ref["weights"]
    nz = rw > 0
    assert ((w[nz] - rw[nz]).abs() <= 1e-5 * rw[nz]).all()  # relative, also at tau ~ 1e-12
    assert (w[~nz] == 0).all()
    expect = torch.ones_like(nz)
    expect[s1 + 41 : s2] = False  # after the wall
    expect[s2 + 31 : s2 + 33] = False  # zero-length steps
    assert torch.equal(nz, expect)
    for k in ("rgb", "depth", "opacity"):
        torch.testing.assert_close(out[k].double(), ref[k], rtol=1e-5, atol=1e-7)


def test_t_min_above_one_stops_every_ray(layout, monkeypatch):
    """t_min > 1 fails at T_0 = 1: nothing visited, the background everywhere, no gradient;
    every per-ray output is still written (poisoned buffers)."""

    def poisoned(*shape, dtype=torch.float32, device=None):
        t = torch.empty(*shape, dtype=dtype, device=device)
        return t.fill_(float("nan") if dtype.is_floating_point else -(2**30))

    monkeypatch.setattr(comp, "T_MIN", 2.0)
    monkeypatch.setattr(comp, "_empty", poisoned)
    sig, rgbs, t_s, t_e, pi = _random_case(R=12, max_n=70)
    bg = torch.rand(pi.shape[0], 3)
    out, n_used, g_s, g_c = _run(sig, rgbs, t_s, t_e, pi, layout, bg)
    assert (n_used == 0).all()
    assert (out["weights"] == 0).all() and (out["opacity"] == 0).all()
    assert (out["depth"] == 0).all() and torch.equal(out["rgb"], bg)
    assert (g_s == 0).all() and (g_c == 0).all()


def test_gradients_that_arrive_strided(layout):
    """Upstream gradients of a .sum() arrive expanded (stride 0) and are copied to contiguous
    memory before the launch; the copy must outlive the launch (a Warp view holds no
    reference: a freed copy was once read after the next one reused its memory)."""
    sig, rgbs, t_s, t_e, pi = _random_case(R=40, max_n=70)
    s = sig.clone().requires_grad_()
    c = rgbs.clone().requires_grad_()
    out = composite(s, c, t_s, t_e, pi, layout=layout)
    sum(out[k].sum() for k in ALL_GRADS).backward()
    s64 = sig.double().requires_grad_()
    c64 = rgbs.double().requires_grad_()
    ref, _ = ref_composite(s64, c64, t_s.double(), t_e.double(), pi)
    sum(ref[k].sum() for k in ALL_GRADS).backward()
    torch.testing.assert_close(s.grad.double(), s64.grad, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(c.grad.double(), c64.grad, rtol=1e-5, atol=1e-6)
