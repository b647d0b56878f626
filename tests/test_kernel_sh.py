"""SH degree-4 Warp kernels vs explicit float64 formulas (values and autograd Jacobian)."""

import math

import pytest
import torch

from fastenerf.kernels.sh import sh_encode


def ref_sh(d):
    """Real SH, bands 0..3, tcnn order and signs, written from the closed forms."""
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    s = math.sqrt(math.pi)
    return torch.stack(
        [
            torch.full_like(x, 1 / (2 * s)),
            -math.sqrt(3) * y / (2 * s),
            math.sqrt(3) * z / (2 * s),
            -math.sqrt(3) * x / (2 * s),
            math.sqrt(15) * x * y / (2 * s),
            -math.sqrt(15) * y * z / (2 * s),
            math.sqrt(5) * (3 * z * z - 1) / (4 * s),
            -math.sqrt(15) * x * z / (2 * s),
            math.sqrt(15) * (x * x - y * y) / (4 * s),
            math.sqrt(70) * y * (-3 * x * x + y * y) / (8 * s),
            math.sqrt(105) * x * y * z / (2 * s),
            math.sqrt(42) * y * (1 - 5 * z * z) / (8 * s),
            math.sqrt(7) * z * (5 * z * z - 3) / (4 * s),
            math.sqrt(42) * x * (1 - 5 * z * z) / (8 * s),
            math.sqrt(105) * z * (x * x - y * y) / (4 * s),
            math.sqrt(70) * x * (-x * x + 3 * y * y) / (8 * s),
        ],
        dim=1,
    )


def test_sh_values_and_gradient_vs_reference():
    d = torch.nn.functional.normalize(torch.randn(4000, 3), dim=1)
    d[:6] = torch.tensor([[1, 0, 0], [0, 1, 0], [0, 0, 1], [-1, 0, 0], [0, -1, 0], [0, 0, -1.0]])
    dt = d.clone().requires_grad_(True)
    out = sh_encode(dt)
    d64 = d.double().requires_grad_(True)
    ref = ref_sh(d64)
    assert out.shape == (4000, 16) and out.t().is_contiguous()
    torch.testing.assert_close(out.double(), ref, atol=1e-6, rtol=1e-6)
    g = torch.randn(4000, 16, dtype=torch.float64)
    (ref * g).sum().backward()
    (out * g.float()).sum().backward()
    torch.testing.assert_close(dt.grad.double(), d64.grad, atol=2e-5, rtol=1e-5)


def test_sh_orthonormal_on_sphere():
    # Monte Carlo: E[Y_i Y_j] over the sphere = delta_ij / (4 pi); catches a wrong constant.
    d = torch.nn.functional.normalize(torch.randn(200_000, 3), dim=1)
    y = sh_encode(d).double()
    gram = 4 * math.pi * (y.T @ y) / d.shape[0]
    torch.testing.assert_close(gram, torch.eye(16, dtype=torch.float64), atol=0.03, rtol=0)


def test_sh_rejects_bad_shape_and_handles_empty():
    with pytest.raises(ValueError, match="d must be"):
        sh_encode(torch.rand(4, 2))
    assert sh_encode(torch.zeros(0, 3)).shape == (0, 16)


def test_bfloat16_basis_is_the_float32_one_rounded_and_reads_a_bfloat16_gradient():
    """out_dtype=bfloat16: row-major (N, 16), bit for bit `.to(torch.bfloat16)` of the float32
    basis; its bf16 gradient gives the float32 path's gradient for the same values, from a
    strided gradient too (the colour MLP hands back a (N, 32) input gradient's columns)."""
    d = torch.nn.functional.normalize(torch.randn(3000, 3), dim=1)
    f32, b16 = d.clone().requires_grad_(), d.clone().requires_grad_()
    a, b = sh_encode(f32), sh_encode(b16, out_dtype=torch.bfloat16)
    assert b.dtype == torch.bfloat16 and b.is_contiguous() and b.shape == (3000, 16)
    assert torch.equal(b, a.to(torch.bfloat16))
    wide = torch.randn(3000, 32).to(torch.bfloat16)
    g = wide[:, 16:]  # strided, as the concatenation's backward hands it
    (ga,) = torch.autograd.grad(a, f32, g.float())
    (gb,) = torch.autograd.grad(b, b16, g)
    assert torch.equal(ga, gb) and ga.abs().sum() > 0
    with pytest.raises(ValueError, match="out_dtype"):
        sh_encode(d, out_dtype=torch.float16)
    assert sh_encode(torch.zeros(0, 3), out_dtype=torch.bfloat16).shape == (0, 16)


@pytest.mark.parametrize("n", [1, 2, 3, 5, 301, 512])
def test_bfloat16_forward_every_row_and_group_for_any_count(n):
    """The bf16 forward runs a thread per (direction, 4 coefficients): every entry of every
    row, for N not a multiple of 4 too, is bit for bit the float32 basis rounded."""
    gen = torch.Generator().manual_seed(n)
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen), dim=1)
    b = sh_encode(d, out_dtype=torch.bfloat16)
    assert b.shape == (n, 16) and b.is_contiguous()
    assert torch.equal(b, sh_encode(d).to(torch.bfloat16))
