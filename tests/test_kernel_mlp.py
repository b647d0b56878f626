"""Fused MLP Warp tile kernels (kernels/mlp.py) vs the same MLP in float64 PyTorch.

The kernels compute in float32; the references are plain torch in float64, so the tolerances
(1e-5 of the reference's largest value) are float32 rounding over sums of up to ~200 terms.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import pytest
import torch

from fastenerf.kernels import mlp
from fastenerf.kernels.mlp import DEFAULT_TILE, fused_mlp

T = DEFAULT_TILE
SHAPES = {"density": (32, 64, 16), "color": (31, 64, 64, 3)}
RTOL = 1e-5


def make_weights(dims, gen, scale=1.0):
    """nn.Linear-like (out, in) float32 weights, He-scaled so activations stay O(1)."""
    return [
        (torch.randn(dims[k + 1], dims[k], generator=gen) * scale * math.sqrt(2 / dims[k]))
        for k in range(len(dims) - 1)
    ]


def reference(x, weights):
    """float64 torch: ReLU after every layer but the last."""
    h = x
    for k, w in enumerate(weights):
        h = h @ w.T
        if k < len(weights) - 1:
            h = torch.relu(h)
    return h


def assert_close_rel(actual, expected, rtol=RTOL, equal_nan=False):
    """|actual - expected| <= rtol * (|expected| + max |expected|) elementwise."""
    assert actual.shape == expected.shape, (actual.shape, expected.shape)
    if expected.numel() == 0:
        return
    finite = expected[torch.isfinite(expected)]
    scale = finite.abs().max().item() if finite.numel() else 1.0
    torch.testing.assert_close(
        actual.double(), expected, rtol=rtol, atol=rtol * max(scale, 1e-30), equal_nan=equal_nan
    )


def run_both(x, weights, grad_y=None, x_grad=True, **kw):
    """(y, x.grad, [w.grad]) of the kernel and of the float64 reference for cotangent grad_y."""
    xk = x.clone().requires_grad_(x_grad)
    wk = [w.clone().requires_grad_(True) for w in weights]
    y = fused_mlp(xk, wk, **kw)
    if grad_y is None:
        grad_y = torch.randn(y.shape, generator=torch.Generator().manual_seed(7))
    y.backward(grad_y)
    x64 = x.double().requires_grad_(x_grad)
    w64 = [w.double().requires_grad_(True) for w in weights]
    y64 = reference(x64, w64)
    y64.backward(grad_y.double())
    return (y, xk.grad, [w.grad for w in wk]), (y64, x64.grad, [w.grad for w in w64])


@pytest.mark.parametrize("shape", list(SHAPES))
@pytest.mark.parametrize("n", [0, 1, T - 1, T, 3 * T + 5])
def test_values_and_gradients_match_float64(shape, n):
    dims = SHAPES[shape]
    gen = torch.Generator().manual_seed(1000 * n + len(dims))
    x = torch.randn(n, dims[0], generator=gen)
    weights = make_weights(dims, gen)
    (y, gx, gw), (y64, gx64, gw64) = run_both(x, weights)
    assert y.dtype == torch.float32 and y.shape == (n, dims[-1])
    assert_close_rel(y, y64)
    assert_close_rel(gx, gx64)
    for a, b in zip(gw, gw64, strict=True):
        assert a.shape == b.shape
        assert_close_rel(a, b)
    if n == 0:
        assert all((g == 0).all() for g in gw)
    else:  # the reference is not trivially zero: the comparison can fail
        assert all(g.abs().max() > 0 for g in gw64) and gx64.abs().max() > 0


@pytest.mark.parametrize("blocks", [1, 2, 3])
def test_persistent_blocks_accumulate_every_tile(blocks):
    """Fewer blocks than tiles (the GPU default): each block loops over several tiles and sums
    their weight gradients before its one atomic add."""
    dims = SHAPES["color"]
    gen = torch.Generator().manual_seed(blocks)
    x = torch.randn(5 * T + 3, dims[0], generator=gen)
    (y, gx, gw), (y64, gx64, gw64) = run_both(x, make_weights(dims, gen), blocks=blocks)
    assert_close_rel(y, y64)
    assert_close_rel(gx, gx64)
    for a, b in zip(gw, gw64, strict=True):
        assert_close_rel(a, b)


def test_single_layer_and_odd_widths():
    dims = (5, 3)
    gen = torch.Generator().manual_seed(3)
    x = torch.randn(2 * T + 1, dims[0], generator=gen)
    (y, gx, gw), (y64, gx64, gw64) = run_both(x, make_weights(dims, gen))
    assert_close_rel(y, y64)
    assert_close_rel(gx, gx64)
    assert_close_rel(gw[0], gw64[0])


def test_x_gradient_not_computed_without_requires_grad(monkeypatch):
    calls = []
    real = mlp._backward_kernel

    def spy(dims, tile, tf32, want_dx, x_cols):
        calls.append(want_dx)
        return real(dims, tile, tf32, want_dx, x_cols)

    monkeypatch.setattr(mlp, "_backward_kernel", spy)
    dims = SHAPES["density"]
    gen = torch.Generator().manual_seed(4)
    x = torch.randn(T + 9, dims[0], generator=gen)
    (y, gx, gw), (y64, gx64, gw64) = run_both(x, make_weights(dims, gen), x_grad=False)
    assert gx is None and gx64 is None
    assert calls == [False]  # the kernel variant that writes no dX
    for a, b in zip(gw, gw64, strict=True):
        assert_close_rel(a, b)
    # and with x requiring grad, the dX variant
    run_both(x, make_weights(dims, gen), x_grad=True)
    assert calls == [False, True]


def test_column_major_x_read_in_place():
    """x as hash_grid_encode returns it (a transposed (C, N) array) needs no copy."""
    dims = SHAPES["density"]
    gen = torch.Generator().manual_seed(5)
    x = torch.randn(dims[0], 2 * T + 7, generator=gen).t()
    assert x.stride() == (1, 2 * T + 7)
    weights = make_weights(dims, gen)
    (y, gx, gw), (y64, gx64, gw64) = run_both(x, weights)
    assert_close_rel(y, y64)
    assert_close_rel(gx, gx64)
    for a, b in zip(gw, gw64, strict=True):
        assert_close_rel(a, b)
    # any other strides: copied, same values
    xs = torch.randn(T + 1, 2 * dims[0], generator=gen)[:, ::2]
    assert_close_rel(fused_mlp(xs, weights), reference(xs.double(), [w.double() for w in weights]))


def test_nan_row_stays_in_its_row():
    dims = SHAPES["color"]
    gen = torch.Generator().manual_seed(6)
    x = torch.randn(2 * T + 3, dims[0], generator=gen)
    bad = T + 2  # a row in the second tile
    x[bad, 4] = float("nan")
    (y, gx, gw), (y64, gx64, gw64) = run_both(x, make_weights(dims, gen))
    assert torch.isnan(y64[bad]).all()  # torch.relu keeps the NaN, and so must the kernel
    assert torch.isnan(y[bad]).all()
    keep = torch.arange(len(x)) != bad
    assert torch.isfinite(y[keep]).all() and torch.isfinite(gx[keep]).all()
    assert_close_rel(y[keep], y64[keep])
    assert_close_rel(gx[keep], gx64[keep])
    # the NaN row's own input gradient, and the weight gradients (sums over all rows), as
    # torch's (its ReLU derivative passes the gradient at a NaN)
    assert_close_rel(gx[bad], gx64[bad], equal_nan=True)
    for a, b in zip(gw, gw64, strict=True):
        assert_close_rel(a, b, equal_nan=True)


@pytest.mark.parametrize("shape", list(SHAPES))
def test_large_inputs_stay_finite_and_relatively_exact(shape):
    dims = SHAPES[shape]
    gen = torch.Generator().manual_seed(8)
    x = torch.randn(2 * T + 1, dims[0], generator=gen) * 1e3
    weights = make_weights(dims, gen, scale=3.0)
    (y, gx, gw), (y64, gx64, gw64) = run_both(x, weights)
    assert y64.abs().max() > 1e4
    for a in (y, gx, *gw):
        assert torch.isfinite(a).all()
    assert_close_rel(y, y64)
    assert_close_rel(gx, gx64)
    for a, b in zip(gw, gw64, strict=True):
        assert_close_rel(a, b)


def test_rejects_bad_inputs():
    gen = torch.Generator().manual_seed(9)
    w = make_weights((4, 8, 2), gen)
    with pytest.raises(ValueError, match="x must be"):
        fused_mlp(torch.rand(3, 4, dtype=torch.float64), w)
    with pytest.raises(ValueError, match="x must be"):
        fused_mlp(torch.rand(3, 4, 1), w)
    with pytest.raises(ValueError, match="weight 0 must be"):
        fused_mlp(torch.rand(3, 5), w)
    with pytest.raises(ValueError, match="weight 1 must be"):
        fused_mlp(torch.rand(3, 4), [w[0], w[1].t()])
    with pytest.raises(ValueError, match="weight 0 must be"):
        fused_mlp(torch.rand(3, 4), [w[0].double(), w[1]])
    with pytest.raises(ValueError, match="at least one"):
        fused_mlp(torch.rand(3, 4), [])


def test_benchmark_smoke_cpu(tmp_path):
    """`python -m benchmarks.kernels_mlp --device cpu --n 4096` runs and writes its rows
    (kept well under 20 s on a 2-core machine once the kernels are compiled)."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/ is not installed
    from benchmarks.kernels_mlp import main

    out = tmp_path / "mlp.json"
    assert main(["--device", "cpu", "--n", "4096", "--repeats", "1", "--out", str(out)]) == 0
    rows = json.loads(out.read_text())
    notes = tmp_path / "notes.txt"
    notes.write_text("mine")  # bad input: one line, exit 2, before any work, nothing touched
    assert main(["--device", "cpu", "--n", "0"]) == 2
    assert main(["--device", "cpu", "--n", "64", "--out", str(notes)]) == 2
    assert notes.read_text() == "mine"
    assert {r["shape"] for r in rows} == {"density", "color"}
    for r in rows:
        assert r["fwd_ms"] > 0 and r["fwdbwd_ms"] > 0 and math.isfinite(r["fwdbwd_ms"])
    fused = [r for r in rows if r["variant"].startswith("fused")]
    assert len(fused) == 2 and all(r["rel_err"] < 1e-5 for r in fused)
    bf16 = [r for r in rows if r["variant"] == "torch_bf16"]
    assert all(r["rel_err"] > 1e-4 for r in bf16)  # the error measure sees bf16's rounding
