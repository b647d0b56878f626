"""The distortion loss's two layouts ("ray": a thread per ray, "block": 32 threads per ray
with tile scans, kernels/distortion_block.py) against the float64 double sum and against each
other, values and gradients, at the block layout's own edges: empty rays, rays of one
sample, chunk boundaries (31, 32, 33, 64, 65 samples) and the carry between chunks."""

from __future__ import annotations

import pytest
import torch

from fastenerf.kernels import common
from fastenerf.kernels import composite as comp
from fastenerf.kernels.composite import DISTORTION_CUDA_AUTO, distortion_loss, resolve_layout
from fastenerf.kernels.distortion_block import BLOCK_DIM, distortion_bwd_block, distortion_fwd_block
from tests.test_kernel_composite import _packed, _random_case, ref_distortion

EDGES = [0, 1, 2, 31, 32, 33, 63, 64, 65, 100, 0, 7]


@pytest.fixture(params=["ray", "block"])
def layout(request) -> str:
    return request.param


def _case(counts: list[int], seed: int = 0):
    """Packed rays of the given lengths: sorted, touching intervals of random lengths from
    t = 0.5 along each ray, weights in [0, 0.2)."""
    g = torch.Generator().manual_seed(seed)
    dt = [torch.rand(n, generator=g) * 0.05 + 1e-3 for n in counts]
    t_e = torch.cat([0.5 + torch.cumsum(d, 0) for d in dt])
    t_s = t_e - torch.cat(dt)
    return torch.rand(t_s.numel(), generator=g) * 0.2, t_s, t_e, _packed(torch.tensor(counts))


def _loss_and_grad(w, t_s, t_e, pi, layout, g):
    """(loss (R,), dL/dw (S,)) of sum_r g_r L_r."""
    w = w.clone().requires_grad_()
    loss = distortion_loss(w, t_s, t_e, pi, layout=layout)
    (loss * g).sum().backward()
    return loss.detach(), w.grad


def test_layout_choice():
    assert resolve_layout("auto", torch.device("cpu"), DISTORTION_CUDA_AUTO) == "ray"
    assert resolve_layout("auto", torch.device("cuda"), DISTORTION_CUDA_AUTO) == "block"
    x = torch.rand(2)
    with pytest.raises(ValueError, match="layout"):
        distortion_loss(x, x, x + 0.1, _packed(torch.tensor([2])), layout="warp")


def test_block_layout_runs_32_lanes_on_the_cpu():
    w, t_s, t_e, pi = _case([40, 3])
    _loss_and_grad(w, t_s, t_e, pi, "block", torch.ones(2))
    for kernel in (distortion_fwd_block, distortion_bwd_block):
        assert common.tiled_launcher(kernel, BLOCK_DIM)._cmds["cpu"].block_dim == 32


def test_both_layouts_match_the_double_sum_at_chunk_edges(layout):
    w, t_s, t_e, pi = _case(EDGES)
    g = torch.randn(len(EDGES), generator=torch.Generator().manual_seed(3))
    loss, grad = _loss_and_grad(w, t_s, t_e, pi, layout, g)
    w64 = w.double().requires_grad_()
    ref = ref_distortion(w64, t_s.double(), t_e.double(), pi)
    (ref * g.double()).sum().backward()
    torch.testing.assert_close(loss.double(), ref.detach(), rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(grad.double(), w64.grad, rtol=1e-4, atol=1e-6)
    assert (loss[pi[:, 1] == 0] == 0).all()  # empty rays


def test_layouts_agree_on_a_random_batch():
    sig, _, t_s, t_e, pi = _random_case(R=120, max_n=150)
    w = torch.rand(sig.numel()) * 0.1
    g = torch.randn(pi.shape[0])
    ray = _loss_and_grad(w, t_s, t_e, pi, "ray", g)
    block = _loss_and_grad(w, t_s, t_e, pi, "block", g)
    assert (pi[:, 1] > 64).any()  # rays of three chunks and more
    torch.testing.assert_close(block[0], ray[0], rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(block[1], ray[1], rtol=1e-4, atol=1e-6)


def test_the_block_layout_writes_every_gradient(layout, monkeypatch):
    """Per-ray outputs come from torch.empty: poison it, and every loss must still be
    written; a sample outside every ray's slice keeps gradient 0."""
    real = torch.empty
    monkeypatch.setattr(comp, "_empty", lambda *a, **k: real(*a, **k).fill_(float("nan")))
    w, t_s, t_e, pi = _case([5, 0, 40])
    pi = pi.clone()
    pi[2, 1] -= 1  # the last sample belongs to no ray
    loss, grad = _loss_and_grad(w, t_s, t_e, pi, layout, torch.ones(3))
    assert torch.isfinite(loss).all() and torch.isfinite(grad).all()
    assert grad[-1] == 0 and (grad[:-1] != 0).any()


def test_the_benchmark_times_both_layouts_and_its_baseline_is_the_double_sum():
    """benchmarks.kernels_render's distortion timing runs at a tiny size, and its plain-PyTorch
    baseline (also its float64 reference) is the brute-force double sum."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/ is not installed
    from benchmarks.kernels_render import bench_distortion
    from benchmarks.render_torch import torch_distortion

    w, t_s, t_e, pi = _case(EDGES, seed=5)
    w64 = w.double().requires_grad_()
    ref = ref_distortion(w64, t_s.double(), t_e.double(), pi)
    w64b = w.double().requires_grad_()
    base = torch_distortion(w64b, t_s.double(), t_e.double(), pi)
    torch.testing.assert_close(base, ref, rtol=1e-12, atol=1e-15)
    g = torch.randn(len(EDGES), dtype=torch.float64)
    torch.testing.assert_close(
        torch.autograd.grad((base * g).sum(), w64b)[0], torch.autograd.grad((ref * g).sum(), w64)[0]
    )
    r = bench_distortion("cpu", n_rays=48, mean_samples=40, repeats=1)
    for L in ("ray", "block", "torch"):
        assert r[f"{L}_fwd_ms"] > 0 and r[f"{L}_fwdbwd_ms"] > 0
    for L in ("ray", "block"):
        assert r[f"{L}_max_rel_err_loss"] < 1e-5 and r[f"{L}_max_rel_err_grad"] < 1e-4
    assert r["block_over_ray_fwdbwd"] > 0
