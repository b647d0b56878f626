"""Hash-grid Warp kernels vs an independent float64 PyTorch reference (DESIGN §4, §5)."""

import dataclasses
import itertools
import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from fastenerf.kernels.hashgrid import (
    HashGridConfig,
    _alloc_out,
    _launch_forward,
    _Variant,
    grid_indices,
    hash_grid_encode,
    init_table,
)

P1, P2, M32 = 2654435761, 805459861, 0xFFFFFFFF

SMALL = HashGridConfig(
    n_levels=6, n_features=2, log2_table_size=10, base_resolution=4, max_resolution=96
)


def ref_layout(cfg):
    """(resolution, dense?, size) per level, from DESIGN §4 and the documented convention."""
    L, n0, n1, T = cfg.n_levels, cfg.base_resolution, cfg.max_resolution, 2**cfg.log2_table_size
    b = math.exp((math.log(n1) - math.log(n0)) / (L - 1)) if L > 1 else 1.0
    out = []
    for lv in range(L):
        n = int(math.floor(n0 * b**lv + 1e-9))
        dense = (n + 1) ** 3 <= T
        out.append((n, dense, math.ceil((n + 1) ** 3 / 8) * 8 if dense else T))  # 8-row padding
    return out


def ref_encode(x, table, cfg):
    """float64 reference: clamp, pos = x * N, trilinear over the 8 corners, own hash."""
    feats, off = [], 0
    T = 2**cfg.log2_table_size
    for n, dense, size in ref_layout(cfg):
        p = x.clamp(0.0, 1.0) * n
        c = torch.floor(p).clamp(0, n - 1).detach()
        f = p - c
        c = c.long()
        acc = 0.0
        for corner in itertools.product((0, 1), repeat=3):
            v = c + torch.tensor(corner)
            if dense:
                idx = v[:, 0] + (n + 1) * (v[:, 1] + (n + 1) * v[:, 2])
            else:
                idx = (v[:, 0] ^ ((v[:, 1] * P1) & M32) ^ ((v[:, 2] * P2) & M32)) & (T - 1)
            w = torch.ones_like(f[:, 0])
            for d in range(3):
                w = w * (f[:, d] if corner[d] else 1.0 - f[:, d])
            acc = acc + w[:, None] * table[off + idx]
        feats.append(acc)
        off += size
    assert off == table.shape[0]
    return torch.cat(feats, 1)


def random_points(n, cfg, gen):
    """Uniform points plus points on cell boundaries of every level and on the box faces."""
    x = torch.rand(n, 3, generator=gen)
    res = [r for r, _, _ in ref_layout(cfg)]
    k = torch.randint(0, 10**6, (n // 2, 3), generator=gen)
    lv = torch.randint(0, len(res), (n // 2, 1), generator=gen)
    nl = torch.tensor(res)[lv]
    x_b = (
        (k % (nl + 1)).double() / nl
    ).float()  # on a vertex plane of some level (to float32 rounding)
    faces = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [0.0, 1.0, 0.5], [1.0, 0.25, 0.0]])
    return torch.cat([x, x_b, faces])


def test_layout_matches_design():
    cfg = HashGridConfig()
    lay = ref_layout(cfg)
    assert cfg.resolutions == tuple(r for r, _, _ in lay)
    assert cfg.resolutions[0] == 16 and cfg.resolutions[-1] == 2048
    assert cfg.hashed == tuple(not d for _, d, _ in lay)
    assert cfg.hashed[:5] == (False,) * 5 and all(cfg.hashed[5:])
    assert cfg.level_offsets == tuple(np.concatenate([[0], np.cumsum([s for *_, s in lay])]))
    assert init_table(cfg).shape == (cfg.n_params, 2)
    t = init_table(SMALL)
    assert t.abs().max() <= 1e-4 and t.std() > 1e-5


def test_hash_matches_numpy_uint32():
    cfg = HashGridConfig(n_levels=2, log2_table_size=13, base_resolution=64, max_resolution=4096)
    assert cfg.hashed == (True, True)
    ijk = np.random.randint(0, 2**16, size=(4096, 3)).astype(np.int32)
    ijk[:4] = [[0, 0, 0], [65535, 65535, 65535], [1, 0, 0], [0, 1, 1]]
    u = ijk.astype(np.uint32)
    h = (u[:, 0] * np.uint32(1)) ^ (u[:, 1] * np.uint32(P1)) ^ (u[:, 2] * np.uint32(P2))
    for level in (0, 1):
        want = (h & np.uint32(cfg.table_size - 1)).astype(np.int64) + cfg.level_offsets[level]
        got = grid_indices(torch.from_numpy(ijk), level, cfg).numpy()
        np.testing.assert_array_equal(got, want)


def test_dense_hashed_switch_at_exact_fit():
    # (15 + 1)^3 = 4096 = T: level 0 fits exactly and is dense; level 1 (N = 30) is hashed.
    cfg = HashGridConfig(n_levels=2, log2_table_size=12, base_resolution=15, max_resolution=30)
    assert cfg.resolutions == (15, 30) and cfg.hashed == (False, True)
    assert cfg.level_sizes == (4096, 4096)
    v = torch.tensor(list(itertools.product(range(16), repeat=3)), dtype=torch.int32)
    rows = grid_indices(v, 0, cfg)
    assert torch.equal(torch.sort(rows).values, torch.arange(4096))  # bijection onto the slice
    want = v[:, 0] + 16 * (v[:, 1] + 16 * v[:, 2])
    assert torch.equal(rows, want.long())
    rows1 = grid_indices(v, 1, cfg)
    assert rows1.min() >= 4096 and rows1.max() < 8192
    assert not torch.equal(rows1 - 4096, rows)  # hashed, not dense, indexing


TINY_TABLE = HashGridConfig(
    n_levels=4, n_features=2, log2_table_size=4, base_resolution=1, max_resolution=64
)


@pytest.mark.parametrize(
    "cfg,variant",
    [
        (SMALL, _Variant()),  # 6 levels: the last 4-level backward group is partial
        (TINY_TABLE, _Variant()),
        (SMALL, _Variant(run=1)),  # a thread per point in the table's backward
        (SMALL, _Variant(group=1, pairs=False, run=1)),
    ],
    ids=["small", "tiny_table_everything_collides", "thread_per_point", "ungrouped_unpaired"],
)
def test_forward_backward_vs_reference(cfg, variant):
    gen = torch.Generator().manual_seed(int(torch.randint(0, 2**31, ())))
    x = random_points(1500, cfg, gen)
    table = (torch.rand(cfg.n_params, cfg.n_features, generator=gen) * 2 - 1).float()

    # Forward into a NaN-poisoned buffer: every element must be written.
    storage = _alloc_out(x.shape[0], cfg, variant, "cpu").fill_(float("nan"))
    out = _launch_forward(x, table, cfg, variant, storage)
    assert out.shape == (x.shape[0], cfg.n_output_dims) and torch.isfinite(storage).all()

    x64 = x.double().requires_grad_(True)
    t64 = table.double().requires_grad_(True)
    ref = ref_encode(x64, t64, cfg)
    torch.testing.assert_close(out.double(), ref, atol=2e-5, rtol=0)

    # Gradients w.r.t. the table (scatter with collisions) and x, for a random cotangent.
    g = torch.randn(ref.shape, generator=gen, dtype=torch.float64)
    (ref * g).sum().backward()
    xt = x.clone().requires_grad_(True)
    tt = table.clone().requires_grad_(True)
    enc = hash_grid_encode(xt, tt, cfg, variant)
    torch.testing.assert_close(enc.detach().double(), ref.detach(), atol=2e-5, rtol=0)
    (enc * g.float()).sum().backward()
    scale = t64.grad.abs().max().item()
    torch.testing.assert_close(tt.grad.double(), t64.grad, atol=2e-5 * scale, rtol=1e-5)

    # x-gradient only away from cell boundaries: the encoding has kinks there.
    res = torch.tensor(cfg.resolutions, dtype=torch.float64)
    frac = torch.frac(x.double()[:, None, :] * res[None, :, None])
    interior = ((frac > 1e-3) & (frac < 1 - 1e-3)).all(2).all(1)
    assert interior.sum() > 500
    scale = x64.grad[interior].abs().max().item()
    torch.testing.assert_close(
        xt.grad[interior].double(), x64.grad[interior], atol=1e-4 * scale, rtol=1e-4
    )


def ray_samples(n_rays: int, per_ray: int, gen) -> torch.Tensor:
    """Samples ordered ray by ray, as the marcher emits them: (n_rays * per_ray, 3) float32,
    a short step (runs of samples share a cell at the coarse levels, cross cells at the fine
    ones), some rays leaving the box (clamped corners, the same cell many times over)."""
    o = torch.rand(n_rays, 3, generator=gen) * 0.6 + 0.2
    d = torch.nn.functional.normalize(torch.randn(n_rays, 3, generator=gen), dim=1)
    t = torch.arange(per_ray, dtype=torch.float32) * 0.011
    return (o[:, None, :] + t[None, :, None] * d[:, None, :]).reshape(-1, 3)


@pytest.mark.parametrize("run,F", [(2, 2), (5, 2), (8, 2), (3, 4), (4, 1)])
def test_run_backward_matches_reference_on_ray_ordered_samples(run, F):
    """The run-aggregated table backward (`backward_run`) against the float64 reference, on
    samples in ray order with zero-gradient samples inside runs (a march's padding) and a
    point count that is no multiple of the run."""
    gen = torch.Generator().manual_seed(int(torch.randint(0, 2**31, ())))
    cfg = HashGridConfig(
        n_levels=6,
        n_features=F,
        log2_table_size=10,
        base_resolution=4,
        max_resolution=96,
        backward_run=run,
    )
    x = ray_samples(37, 41, gen)  # 1517 points
    table = (torch.rand(cfg.n_params, F, generator=gen) * 2 - 1).float()
    g = torch.randn(x.shape[0], cfg.n_output_dims, generator=gen, dtype=torch.float64)
    g[torch.rand(x.shape[0], generator=gen) < 0.2] = 0.0
    t64 = table.double().requires_grad_(True)
    (ref_encode(x.double(), t64, cfg) * g).sum().backward()
    tt = table.clone().requires_grad_(True)
    (hash_grid_encode(x, tt, cfg) * g.float()).sum().backward()
    scale = t64.grad.abs().max().item()
    torch.testing.assert_close(tt.grad.double(), t64.grad, atol=2e-5 * scale, rtol=1e-5)
    # and the same rows as the thread-per-point backward, up to float rounding order
    tp = table.clone().requires_grad_(True)
    (hash_grid_encode(x, tp, dataclasses.replace(cfg, backward_run=1)) * g.float()).sum().backward()
    assert torch.equal(tp.grad != 0, tt.grad != 0)


def test_backward_run_must_be_positive():
    with pytest.raises(ValueError, match="backward_run"):
        HashGridConfig(backward_run=0)


def test_out_of_box_points_are_clamped_and_layout_variant_agrees():
    cfg = SMALL
    gen = torch.Generator().manual_seed(int(torch.randint(0, 2**31, ())))
    x = torch.rand(300, 3, generator=gen) * 2.0 - 0.5  # about half the coordinates outside
    table = (torch.rand(cfg.n_params, 2, generator=gen) * 2 - 1).float()
    xt = x.clone().requires_grad_(True)
    enc = hash_grid_encode(xt, table, cfg)
    enc.square().sum().backward()
    x64 = x.double().requires_grad_(True)
    ref = ref_encode(x64, table.double(), cfg)
    ref.square().sum().backward()
    torch.testing.assert_close(enc.detach().double(), ref.detach(), atol=2e-5, rtol=0)
    outside = (x < 0) | (x > 1)
    assert outside.any() and (xt.grad[outside] == 0).all()

    # The other launch layout (point-major threads, point-major output, plain atomics).
    v = _Variant(level_outer=False, feature_major=False, vector_red=False)
    storage = _alloc_out(x.shape[0], cfg, v, "cpu").fill_(float("nan"))
    out2 = _launch_forward(x, table, cfg, v, storage)
    assert out2.is_contiguous()
    torch.testing.assert_close(out2, enc.detach(), atol=0, rtol=0)


def test_x_gradient_on_box_faces():
    # On x = 0 / x = 1 the derivative is one-sided, from the cell inside the box.
    cfg = SMALL
    gen = torch.Generator().manual_seed(int(torch.randint(0, 2**31, ())))
    x = torch.rand(400, 3, generator=gen)
    x[:200, 0] = 1.0
    x[200:, 0] = 0.0
    res = torch.tensor(cfg.resolutions, dtype=torch.float64)
    frac = torch.frac(x.double()[:, None, 1:] * res[None, :, None])
    x = x[((frac > 1e-3) & (frac < 1 - 1e-3)).all(2).all(1)]
    table = (torch.rand(cfg.n_params, 2, generator=gen) * 2 - 1).float()
    xt = x.clone().requires_grad_(True)
    hash_grid_encode(xt, table, cfg).square().sum().backward()
    x64 = x.double().requires_grad_(True)
    ref_encode(x64, table.double(), cfg).square().sum().backward()
    assert (x64.grad[:, 0] != 0).all()
    scale = x64.grad.abs().max().item()
    torch.testing.assert_close(xt.grad.double(), x64.grad, atol=1e-4 * scale, rtol=1e-4)


def test_table_not_16_byte_aligned():
    # A table that is a slice of a larger buffer (8-byte aligned only) takes the unpaired path.
    cfg = SMALL
    buf = torch.rand(cfg.n_params + 1, 2) * 2 - 1
    table = buf[1:]
    assert table.data_ptr() % 16 == 8
    x = torch.rand(500, 3)
    ref = ref_encode(x.double(), table.double(), cfg)
    torch.testing.assert_close(hash_grid_encode(x, table, cfg).double(), ref, atol=2e-5, rtol=0)


def test_rejects_bad_inputs():
    t = init_table(SMALL)
    with pytest.raises(ValueError, match="x must be"):
        hash_grid_encode(torch.rand(4, 2), t, SMALL)
    with pytest.raises(ValueError, match="table must be"):
        hash_grid_encode(torch.rand(4, 3), t[:-1], SMALL)
    assert hash_grid_encode(torch.rand(0, 3), t, SMALL).shape == (0, SMALL.n_output_dims)


def test_benchmark_smoke_cpu():
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/ is not installed
    from benchmarks.kernels_encoding import bench_hashgrid

    r = bench_hashgrid(device="cpu", n_points=2**10, log2_T=10, repeats=2)
    assert r["max_abs_err"] < 1e-5
    for k in ("warp_fwd_ms", "warp_bwd_ms", "warp_fwdbwd_ms", "torch_fwdbwd_ms"):
        assert r[k] > 0 and math.isfinite(r[k])


def smooth_points_and_table(cfg):
    """(generator, points away from every level's cell faces (the x-gradient's kinks), a
    random table), freshly seeded each call."""
    gen = torch.Generator().manual_seed(int(torch.randint(0, 2**31, ())))
    x = random_points(600, cfg, gen)
    res = torch.tensor(cfg.resolutions, dtype=torch.float64)
    frac = torch.frac(x.double()[:, None, :] * res[None, :, None])
    x = x[((frac > 1e-3) & (frac < 1 - 1e-3)).all(2).all(1)]
    table = (torch.rand(cfg.n_params, cfg.n_features, generator=gen) * 2 - 1).float()
    return gen, x, table


def test_x_grad_weights_weight_only_the_position_gradient():
    """x_grad_weights (coarse-to-fine on the pose gradient): the value and the table's
    gradient are the unweighted ones; the x-gradient is the float64 reference's for the
    cotangent times the weights."""
    cfg = SMALL
    gen, x, table = smooth_points_and_table(cfg)
    w = torch.rand(cfg.n_output_dims, generator=gen)
    w[: cfg.n_features] = 1.0  # a schedule keeps level 0
    w[-cfg.n_features :] = 0.0  # and cuts the finest
    g = torch.randn(len(x), cfg.n_output_dims, generator=gen, dtype=torch.float64)

    xt, tt = x.clone().requires_grad_(True), table.clone().requires_grad_(True)
    enc = hash_grid_encode(xt, tt, cfg, x_grad_weights=w)
    (enc * g.float()).sum().backward()
    x64, t64 = x.double().requires_grad_(True), table.double().requires_grad_(True)
    ref = ref_encode(x64, t64, cfg)
    torch.testing.assert_close(enc.detach().double(), ref.detach(), atol=2e-5, rtol=0)
    (ref * g).sum().backward()
    scale = t64.grad.abs().max().item()
    torch.testing.assert_close(tt.grad.double(), t64.grad, atol=2e-5 * scale, rtol=1e-5)
    x64w = x.double().requires_grad_(True)
    (ref_encode(x64w, table.double(), cfg) * g * w.double()).sum().backward()
    scale = x64w.grad.abs().max().item()
    torch.testing.assert_close(xt.grad.double(), x64w.grad, atol=1e-4 * scale, rtol=1e-4)
    assert not torch.allclose(x64w.grad, x64.grad)  # the weights changed the x-gradient
    with pytest.raises(ValueError, match="x_grad_weights"):
        hash_grid_encode(xt, tt, cfg, x_grad_weights=w[:-1])


def test_x_grad_weights_skip_a_level_held_off():
    """A level coarse-to-fine holds off (weights 0) is skipped in the x-gradient, not read:
    the finest level's rows made non-finite leave the x-gradient the float64 reference's of
    the others (read, they would make it NaN: 0 x inf)."""
    cfg = SMALL
    gen, x, table = smooth_points_and_table(cfg)
    w = torch.ones(cfg.n_output_dims)
    w[-cfg.n_features :] = 0.0
    g = torch.randn(len(x), cfg.n_output_dims, generator=gen, dtype=torch.float64)
    x64 = x.double().requires_grad_(True)
    (ref_encode(x64, table.double(), cfg) * g * w.double()).sum().backward()
    table[cfg.level_offsets[-2] :] = float("inf")
    xt = x.clone().requires_grad_(True)
    (hash_grid_encode(xt, table, cfg, x_grad_weights=w) * g.float()).sum().backward()
    scale = x64.grad.abs().max().item()
    torch.testing.assert_close(xt.grad.double(), x64.grad, atol=1e-4 * scale, rtol=1e-4)


def test_x_grad_mask_zeroes_only_the_masked_points_position_gradient():
    """x_grad_mask (the rays whose pose gradient is dropped): the masked points' x-gradient is
    exactly 0, the others' the float64 reference's, with the coarse-to-fine weights too; the
    value and the table's gradient are the unmasked ones."""
    cfg = SMALL
    gen, x, table = smooth_points_and_table(cfg)
    g = torch.randn(len(x), cfg.n_output_dims, generator=gen, dtype=torch.float64)
    keep = torch.rand(len(x), generator=gen) < 0.3
    w = torch.rand(cfg.n_output_dims, generator=gen)

    x64, t64 = x.double().requires_grad_(True), table.double().requires_grad_(True)
    ref = ref_encode(x64, t64, cfg)
    (ref * g).sum().backward()
    x64w = x.double().requires_grad_(True)
    (ref_encode(x64w, table.double(), cfg) * g * w.double()).sum().backward()
    for weights, ref_x in ((None, x64.grad), (w, x64w.grad)):
        xt, tt = x.clone().requires_grad_(True), table.clone().requires_grad_(True)
        enc = hash_grid_encode(xt, tt, cfg, x_grad_weights=weights, x_grad_mask=keep)
        (enc * g.float()).sum().backward()
        torch.testing.assert_close(enc.detach().double(), ref.detach(), atol=2e-5, rtol=0)
        scale = t64.grad.abs().max().item()
        torch.testing.assert_close(tt.grad.double(), t64.grad, atol=2e-5 * scale, rtol=1e-5)
        want = torch.where(keep[:, None], ref_x, 0.0)
        scale = ref_x.abs().max().item()
        torch.testing.assert_close(xt.grad.double(), want, atol=1e-4 * scale, rtol=1e-4)
        assert (xt.grad[~keep] == 0).all() and (ref_x[~keep].abs() > 0).any()
    xt = x.clone().requires_grad_(True)
    for bad in (keep[:-1], keep.to(torch.uint8)):
        with pytest.raises(ValueError, match="x_grad_mask"):
            hash_grid_encode(xt, table, cfg, x_grad_mask=bad)


@pytest.mark.parametrize(
    "variant,track",
    [
        (_Variant(), False),
        (_Variant(run=1), False),
        (_Variant(feature_major=False), False),
        (_Variant(), True),
    ],
    ids=["runs", "thread_per_point", "point_major", "row_tracker"],
)
def test_bfloat16_features_are_the_float32_ones_rounded(variant, track):
    """out_dtype=bfloat16 writes the float32 features rounded to nearest even, bit for bit
    what `.to(torch.bfloat16)` makes of them, and reads a bfloat16 gradient as the float32
    path reads the same values: the table's and x's gradients are those of the float32 path
    given that gradient, in every backward (runs, a thread per point, the row tracker's)."""
    from fastenerf.kernels.rows import track_rows

    gen = torch.Generator().manual_seed(11)
    x = ray_samples(23, 37, gen)
    table = (torch.rand(SMALL.n_params, SMALL.n_features, generator=gen) * 2 - 1).float()
    g = torch.randn(x.shape[0], SMALL.n_output_dims, generator=gen).to(torch.bfloat16)
    g[::7] = 0  # points without gradient scatter nothing, in bfloat16 too
    grads = []
    for dt in (torch.float32, torch.bfloat16):
        xt, tt = x.clone().requires_grad_(), table.clone().requires_grad_()
        if track:
            track_rows(tt)
        out = hash_grid_encode(xt, tt, SMALL, variant, out_dtype=dt)
        assert out.dtype == dt and out.shape == (x.shape[0], SMALL.n_output_dims)
        grads.append((out.detach(), *torch.autograd.grad((out * g.to(dt)).sum(), (xt, tt))))
    (f32, gx32, gt32), (b16, gx16, gt16) = grads
    assert torch.equal(b16, f32.to(torch.bfloat16))
    assert torch.equal(gt16, gt32) and torch.equal(gx16, gx32)
    assert gt16.abs().sum() > 0 and gx16.abs().sum() > 0


def test_bfloat16_features_write_every_element():
    gen = torch.Generator().manual_seed(3)
    x = random_points(300, SMALL, gen)
    table = init_table(SMALL, generator=gen)
    storage = _alloc_out(x.shape[0], SMALL, _Variant(), "cpu", torch.bfloat16).fill_(float("nan"))
    out = _launch_forward(x, table, SMALL, _Variant(), storage)
    assert out.dtype == torch.bfloat16 and torch.isfinite(storage).all()


def test_rejects_a_feature_dtype_it_cannot_write():
    with pytest.raises(ValueError, match="out_dtype"):
        hash_grid_encode(torch.rand(4, 3), init_table(SMALL), SMALL, out_dtype=torch.float16)


@pytest.mark.parametrize("variant", [_Variant(), _Variant(feature_major=False)], ids=["fm", "pm"])
@pytest.mark.parametrize("dt", [torch.float32, torch.bfloat16])
def test_from_rows_gathers_the_encoding_and_keeps_its_backward(variant, dt):
    """from_rows (a prune's encoding of every marched sample, and the kept ones' rows): the
    value is those rows, in the layout the encoder writes; the table's and x's gradients
    are the encoder's own, bit for bit. Fails if the gather hands feature-major features
    on row-major (the backward reads either; the layout is what the forward promises)."""
    gen = torch.Generator().manual_seed(5)
    every = ray_samples(9, 31, gen)
    rows = torch.randperm(every.shape[0], generator=gen)[:150].sort().values.int()
    table = (torch.rand(SMALL.n_params, SMALL.n_features, generator=gen) * 2 - 1).float()
    with torch.no_grad():
        seen = hash_grid_encode(every, table, SMALL, variant, out_dtype=dt)
    g = torch.randn(len(rows), SMALL.n_output_dims, generator=gen).to(dt)
    grads = []
    for from_rows in (None, (seen, rows)):
        xt = every[rows.long()].clone().requires_grad_()
        tt = table.clone().requires_grad_()
        out = hash_grid_encode(xt, tt, SMALL, variant, out_dtype=dt, from_rows=from_rows)
        grads.append((out.detach(), *torch.autograd.grad((out * g).float().sum(), (xt, tt))))
    (a, gxa, gta), (b, gxb, gtb) = grads
    assert b.dtype == dt and torch.equal(a, b)
    assert (b.stride(0) == 1) == variant.feature_major  # the encoder's layout
    assert torch.equal(gta, gtb) and torch.equal(gxa, gxb) and gtb.abs().sum() > 0


def test_from_rows_must_fit_the_points_and_the_encoding():
    x, table = torch.rand(4, 3), init_table(SMALL)
    feats = hash_grid_encode(torch.rand(10, 3), table, SMALL)
    cases = [
        ((feats, torch.arange(3)), "rows must be \\(4,\\)"),
        ((feats, torch.arange(4).float()), "int32 or int64"),
        ((feats[:, :4], torch.arange(4)), "features must be"),
        ((feats.to(torch.bfloat16), torch.arange(4)), "features must be"),
    ]
    for from_rows, match in cases:
        with pytest.raises(ValueError, match=match):
            hash_grid_encode(x, table, SMALL, from_rows=from_rows)
