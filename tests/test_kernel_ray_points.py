"""kernels/ray_points: points on packed rays and their per-ray backward, on Warp's CPU backend,
against float64 autograd through plain indexing."""

import pytest
import torch

from fastenerf.kernels.ray_points import ray_points


def packed_layout(counts: list[int], padding: int):
    """ray_indices (S,) int32, packed_info (R, 2) int32 for slices of `counts` samples laid
    out ray by ray, then `padding` fixed-capacity slots (ray 0, outside every slice)."""
    starts = torch.cumsum(torch.tensor([0, *counts[:-1]]), 0)
    packed = torch.stack([starts, torch.tensor(counts)], 1).int()
    ray_idx = torch.repeat_interleave(torch.arange(len(counts)), torch.tensor(counts))
    ray_idx = torch.cat([ray_idx, torch.zeros(padding, dtype=torch.long)]).int()
    return ray_idx, packed


@pytest.mark.parametrize("padding", [0, 7])
def test_points_and_per_ray_gradients_match_float64(padding):
    gen = torch.Generator().manual_seed(3)
    counts = [5, 0, 1, 40, 3, 0, 17]  # rays without samples too
    ray_idx, packed = packed_layout(counts, padding)
    s, r = len(ray_idx), len(counts)
    o = torch.randn(r, 3, generator=gen)
    d = torch.nn.functional.normalize(torch.randn(r, 3, generator=gen), dim=-1)
    t = torch.rand(s, generator=gen) * 4.0
    t[sum(counts) :] = 0.0  # the padding's zero-width intervals
    gx, gd = torch.randn(s, 3, generator=gen), torch.randn(s, 3, generator=gen)

    ot, dt = o.clone().requires_grad_(True), d.clone().requires_grad_(True)
    x, dirs = ray_points(ot, dt, t, ray_idx, packed)
    ((x * gx).sum() + (dirs * gd).sum()).backward()

    o64, d64 = o.double().requires_grad_(True), d.double().requires_grad_(True)
    ri = ray_idx.long()
    x64 = o64[ri] + t.double()[:, None] * d64[ri]
    torch.testing.assert_close(x.double(), x64.detach(), atol=1e-6, rtol=1e-6)
    torch.testing.assert_close(dirs, d[ri], atol=0, rtol=0)
    # the reference sums only the packed slices: padding passes no gradient to ray 0
    live = torch.zeros(s, 1, dtype=torch.float64)
    live[: sum(counts)] = 1.0
    ((x64 * gx.double() * live).sum() + (d64[ri] * gd.double() * live).sum()).backward()
    torch.testing.assert_close(ot.grad.double(), o64.grad, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(dt.grad.double(), d64.grad, atol=1e-4, rtol=1e-5)
    assert (ot.grad[[1, 5]] == 0).all()  # rays without samples get no gradient


def test_one_output_used_and_bad_inputs():
    ray_idx, packed = packed_layout([3, 2], 0)
    o = torch.zeros(2, 3, requires_grad=True)
    d = torch.ones(2, 3, requires_grad=True)
    t = torch.arange(5.0)
    x, _ = ray_points(o, d, t, ray_idx, packed)
    x.sum().backward()  # dirs unused: its gradient is None
    assert o.grad.tolist() == [[3.0] * 3, [2.0] * 3]
    assert d.grad.tolist() == [[3.0] * 3, [7.0] * 3]  # t = 0+1+2, 3+4
    with pytest.raises(ValueError, match="int32"):
        ray_points(o, d, t, ray_idx.long(), packed)
    with pytest.raises(ValueError, match="packed_info"):
        ray_points(o, d, t, ray_idx, packed[:1])
