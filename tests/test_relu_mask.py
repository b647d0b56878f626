"""ReLU masks kept as bits and applied in the backward's GEMMs (fastenerf/fields/relu_mask.py):
the bit layout, the MLP it runs against a float64 reference (values and gradients), the
`relu_mask` option's MLPs against the plain ones; on CUDA, cuBLASLt's RELU_AUX / DRELU
epilogues against the torch ops that stand in for them elsewhere."""

from __future__ import annotations

import pytest
import torch

from fastenerf.fields import relu_mask as rm
from fastenerf.fields.mlp import ColorMLP, mlp

CUDA = torch.cuda.is_available()


def _reference(x: torch.Tensor, ws: list[torch.Tensor]) -> torch.Tensor:
    for w in ws[:-1]:
        x = torch.relu(x @ w.t())
    return x @ ws[-1].t()


def _problem(n: int, widths: list[int], dtype=torch.float64, device="cpu", seed=0):
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(n, widths[0], generator=g, dtype=torch.float64)
    ws = [
        torch.randn(o, i, generator=g, dtype=torch.float64) / i**0.5
        for i, o in zip(widths[:-1], widths[1:], strict=True)
    ]
    x = x.to(device, dtype).requires_grad_()
    return x, [w.to(device, dtype).requires_grad_() for w in ws]


def test_mask_bits_are_cublaslts_layout():
    """Sample n's bits start a 128-bit row; output c is bit c % 8 of byte c // 8."""
    assert rm.mask_bytes(1) == rm.mask_bytes(64) == rm.mask_bytes(128) == 16
    assert rm.mask_bytes(129) == 32
    y = -torch.ones(3, 64)
    y[0, 9] = y[1, 0] = y[2, 63] = 0.5
    y[2, 62] = 0.0  # not > 0: no bit
    m = rm.pack_mask(y)
    assert m.shape == (3, 16) and m.dtype == torch.uint8
    expect = torch.zeros(3, 16, dtype=torch.uint8)
    expect[0, 1], expect[1, 0], expect[2, 7] = 2, 1, 128
    assert torch.equal(m, expect)
    z = torch.randn(50, 100)
    assert torch.equal(rm.unpack_mask(rm.pack_mask(z), 100), z > 0)


@pytest.mark.parametrize("widths", [[32, 64, 16], [32, 64, 64, 8], [5, 7, 3]])
def test_masked_relu_mlp_is_the_relu_mlp(widths):
    """Values and every gradient (input and weights) as the plain ReLU MLP's, float64."""
    x, ws = _problem(37, widths)
    y = rm.masked_relu_mlp(x, ws)
    ref = _reference(x, ws)
    torch.testing.assert_close(y, ref, rtol=1e-12, atol=1e-12)
    up = torch.randn_like(y)
    got = torch.autograd.grad(y, [x, *ws], up)
    want = torch.autograd.grad(ref, [x, *ws], up)
    for a, b in zip(got, want, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    small = [w.detach()[:, :].clone().requires_grad_() for w in ws]
    assert torch.autograd.gradcheck(
        lambda x, *w: rm.masked_relu_mlp(x, list(w)), (x[:4].detach().requires_grad_(), *small)
    )


def test_masked_relu_mlp_skips_the_gradients_nobody_asked_for():
    x, ws = _problem(9, [8, 16, 4])
    x.requires_grad_(False)
    gw = torch.autograd.grad(rm.masked_relu_mlp(x, ws).sum(), ws)
    assert all(g is not None for g in gw)


def test_operands_are_read_in_place_row_or_column_major():
    """Rows, rows of a wider buffer and a transposed (feature-major) view go to cuBLAS as they
    are; anything else is copied into rows."""
    buf = torch.randn(64, 48)
    for t, ld, trans in [(buf, 48, False), (buf[:, :32], 48, False), (buf.t(), 48, True)]:
        got, got_ld, got_trans = rm._operand(t)
        assert got.data_ptr() == t.data_ptr() and (got_ld, got_trans) == (ld, trans)
    odd = buf[::2, ::2]
    got, ld, trans = rm._operand(odd)
    assert got.is_contiguous() and (ld, trans) == (24, False) and torch.equal(got, odd)
    # feature-major storage of 61 samples: a leading dimension no aligned kernel reads
    fm = torch.randn(32, 61).t()
    got, ld, trans = rm._operand(fm)
    assert got.is_contiguous() and (ld, trans) == (32, False) and torch.equal(got, fm)
    got, ld, trans = rm._operand(torch.randn(32, 64).t())
    assert (ld, trans) == (64, True)


@pytest.mark.parametrize("geo", [15, 10])
def test_relu_mask_mlps_are_the_fused_ones(geo):
    """`relu_mask` changes how the backward applies the ReLUs, not the networks: the same
    state dict, outputs and gradients (float64) as `fused_relu` alone, for the density MLP's
    shape and the padded colour MLP (its masked first weight included)."""
    torch.manual_seed(5)
    fused = ColorMLP(geo, 32, fused_relu=True).double()
    torch.manual_seed(5)
    masked = ColorMLP(geo, 32, relu_mask=True).double()  # fused_relu or not: its own GEMMs
    assert fused.state_dict().keys() == masked.state_dict().keys()
    g = torch.Generator().manual_seed(1)
    h = torch.randn(29, 1 + geo, generator=g, dtype=torch.float64, requires_grad=True)
    sh = torch.randn(29, 16, generator=g, dtype=torch.float64, requires_grad=True)
    ya, yb = fused(h, sh), masked(h, sh)
    torch.testing.assert_close(ya, yb, rtol=1e-12, atol=1e-12)
    ga = torch.autograd.grad(ya.square().sum(), [h, sh, *fused.parameters()])
    gb = torch.autograd.grad(yb.square().sum(), [h, sh, *masked.parameters()])
    for a, b in zip(ga, gb, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    assert masked[0].weight.grad is None and gb[2][:, 0].abs().max() == 0  # σ logit's column
    dens_a = mlp(32, 16, 1 + geo, 1, fused_relu=True).double()
    dens_b = mlp(32, 16, 1 + geo, 1, fused_relu=True, relu_mask=True).double()
    dens_b.load_state_dict(dens_a.state_dict())
    x = torch.randn(40, 32, dtype=torch.float64, requires_grad=True)
    for a, b in zip(
        torch.autograd.grad(dens_a(x).sum(), [x, *dens_a.parameters()]),
        torch.autograd.grad(dens_b(x).sum(), [x, *dens_b.parameters()]),
        strict=True,
    ):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    with torch.no_grad():  # no backward to keep masks for: the fused path
        torch.testing.assert_close(dens_a(x), dens_b(x), rtol=0, atol=0)


def test_relu_mask_under_autocast_gives_float32_weight_gradients():
    dens = mlp(32, 16, 16, 1, fused_relu=True, relu_mask=True)
    x = torch.randn(64, 32)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        y = dens(x)
    assert y.dtype == torch.bfloat16
    y.float().sum().backward()
    assert all(p.grad is not None and p.grad.dtype == torch.float32 for p in dens.parameters())


@pytest.mark.skipif(not CUDA, reason="no CUDA: the epilogues are cuBLASLt's")
@pytest.mark.parametrize("n", [4096, 1001, 1 << 17])
def test_cublaslt_epilogues_are_the_torch_ops(n):
    """RELU_AUX's output and bits, DRELU's product, and the whole MLP's gradients on CUDA in
    bf16 are the torch ops' (bits exactly; values within bf16's rounding), and the GEMMs ran
    in cuBLASLt (a plan with an algorithm), not in the fallback."""
    x, ws = _problem(n, [32, 64, 64, 8], torch.bfloat16, "cuda")
    rm._PLANS.clear()
    y, mask = rm.linear_relu_mask(x.detach(), ws[0].detach())
    assert any(p is not None for p in rm._PLANS.values())
    ref = torch.relu(x.detach() @ ws[0].detach().t())
    torch.testing.assert_close(y, ref, rtol=1e-2, atol=1e-2)
    assert torch.equal(mask, rm.pack_mask(y))
    g = torch.randn(n, 64, device="cuda", dtype=torch.bfloat16)
    got = rm.masked_grad(g, ws[1].detach(), mask)
    want = (g @ ws[1].detach()).masked_fill_(~(y > 0), 0)
    torch.testing.assert_close(got, want, rtol=1e-2, atol=1e-2)
    assert all(p is not None for p in rm._PLANS.values())
    xt = x.detach().t().contiguous().t()  # feature-major, as the hash grid writes it
    yt, mt = rm.linear_relu_mask(xt, ws[0].detach())
    torch.testing.assert_close(yt, ref, rtol=1e-2, atol=1e-2)
    assert torch.equal(mt, rm.pack_mask(yt))
    out = rm.masked_relu_mlp(x, ws)
    ref = _reference(x.double(), [w.double() for w in ws])
    torch.testing.assert_close(out.double(), ref, rtol=3e-2, atol=3e-2)
    up = torch.randn_like(out)
    for a, b in zip(
        torch.autograd.grad(out, [x, *ws], up),
        torch.autograd.grad(ref, [x, *ws], up.double()),
        strict=True,
    ):
        assert (a.double() - b).norm() <= 2e-2 * b.norm() + 1e-3


def test_without_cublaslt_a_gpu_mlp_keeps_the_fused_gemms(monkeypatch):
    """Off CUDA the torch stand-ins run; on CUDA without cuBLASLt's library the masked MLP
    is not used at all (its stand-ins would be slower than the fused GEMMs)."""
    assert rm.usable(torch.device("cpu"))
    monkeypatch.setattr(rm, "_lib", lambda: None)
    assert not rm.usable(torch.device("cuda"))
    assert not rm.available(torch.device("cuda"), torch.bfloat16)
    assert rm.usable(torch.device("cpu"))
