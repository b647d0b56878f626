"""Occupancy grid: EMA/threshold update, unseen-cell marking, cylinder clip, lookups."""

from __future__ import annotations

import math
import random

import numpy as np
import pytest
import torch

from fastenerf.kernels.occupancy import OccupancyGrid


def _gen():
    seed = random.SystemRandom().randrange(2**31)
    print(f"occupancy seed={seed}")  # shown by pytest on failure
    torch.manual_seed(seed)  # the grid draws its cells and jitter from torch's generator
    return torch.Generator().manual_seed(seed)


def cell_boxes(grid: OccupancyGrid) -> tuple[np.ndarray, np.ndarray]:
    """(C*R^3, 3) float64 min and max corners of every cell, in flat-id order."""
    R, C = grid.resolution, grid.n_cascades
    c = np.array(list(grid.center), np.float64)
    h = np.array(list(grid.half), np.float64)
    i = np.stack(np.meshgrid(*[np.arange(R)] * 3, indexing="ij"), -1).reshape(-1, 3)
    lo, hi = [], []
    for k in range(C):
        size = 2 * h * 2**k / R
        lo.append(c - h * 2**k + i * size)
        hi.append(c - h * 2**k + (i + 1) * size)
    return np.concatenate(lo), np.concatenate(hi)


class Recorder:
    """density_fn that records its inputs; sigma is a smooth blob (1/world units)."""

    def __init__(self, peak=200.0):
        self.x, self.peak = [], peak

    def __call__(self, x):
        self.x.append(x.clone())
        return self.peak * torch.exp(-8 * (x * x).sum(-1))


def test_warmup_update_samples_every_cell_once_and_thresholds():
    _gen()
    g = OccupancyGrid([-1, -0.5, -1, 1, 1.5, 1], resolution=8, n_cascades=2)
    f = Recorder()
    g.update(0, f, decay=0.95, threshold=0.01, warmup_steps=256, chunk=300)
    x = torch.cat(f.x).double().numpy()
    assert len(f.x) == math.ceil(g.n_cells / 300)  # chunked
    lo, hi = cell_boxes(g)
    assert x.shape == lo.shape
    assert ((x >= lo - 1e-6) & (x <= hi + 1e-6)).all()  # one point inside each cell, in order
    sig = f.peak * np.exp(-8 * (x * x).sum(-1))
    np.testing.assert_allclose(g.density.view(-1).double().numpy(), sig, rtol=1e-5, atol=1e-6)
    thre = min(0.01 / g.step_size, sig.mean())
    assert float(g.threshold) == pytest.approx(thre, rel=1e-5)
    expect = sig > thre
    ambiguous = np.abs(sig - thre) < 1e-4 * thre
    got = g.binary.view(-1).numpy()
    assert (got[~ambiguous] == expect[~ambiguous]).all()
    assert 0 < got.sum() < g.n_cells


def test_sparse_update_ema_rule():
    _gen()
    g = OccupancyGrid([-1, -1, -1, 1, 1, 1], resolution=16, n_cascades=1)
    g.update(0, Recorder(), warmup_steps=1)
    old = g.density.view(-1).clone().double().numpy()
    occ_before = g.binary.view(-1).numpy().copy()
    f = Recorder(peak=50.0)
    g.update(10, f, decay=0.9, threshold=0.01, warmup_steps=1)
    x = torch.cat(f.x).double().numpy()
    n = g.n_cells // 4
    assert len(x) == 2 * n  # fixed sizes: the host never reads a count
    # which cell each point came from (C = 1: plain floor)
    ijk = np.floor((x + 1) / 2 * 16).astype(int).clip(0, 15)
    ids = (ijk[:, 0] * 16 + ijk[:, 1]) * 16 + ijk[:, 2]
    sig = 50.0 * np.exp(-8 * (x * x).sum(-1))
    new = np.zeros(g.n_cells)
    np.maximum.at(new, ids, sig)
    expect = np.maximum(old * 0.9, new)
    np.testing.assert_allclose(g.density.view(-1).double().numpy(), expect, rtol=1e-5, atol=1e-6)
    # the second half is drawn from the occupied cells, with replacement, uniformly
    assert 0 < occ_before.sum() < g.n_cells and occ_before[ids[n:]].all()
    hit = np.isin(np.nonzero(occ_before)[0], ids[n:]).mean()
    assert hit > 1 - math.exp(-n / occ_before.sum()) - 0.1
    thre = min(0.01 / g.step_size, expect.mean())
    amb = np.abs(expect - thre) < 1e-4 * thre
    assert (g.binary.view(-1).numpy()[~amb] == (expect > thre)[~amb]).all()


def test_sparse_update_with_no_occupied_cell():
    """An empty grid has nothing to draw from: the draw still has its fixed size and the
    update stays finite (no device-side assert, no host read)."""
    _gen()
    g = OccupancyGrid([-1, -1, -1, 1, 1, 1], resolution=8)
    g.update(0, lambda x: torch.zeros(x.shape[0]), warmup_steps=1)
    assert not g.binary.any()
    f = Recorder(peak=0.0)
    g.update(10, f, warmup_steps=1)
    assert sum(len(x) for x in f.x) == 2 * (g.n_cells // 4)
    assert torch.isfinite(g.density).all() and not g.binary.any()


def test_warmup_update_skips_cells_marked_after_an_earlier_update():
    """The warm-up's list of valid cells is counted once, and again after cells are marked
    never occupied: a stale list would re-evaluate (and could revive) a marked cell."""
    _gen()
    g = OccupancyGrid([-1, -1, -1, 1, 1, 1], resolution=8)
    g.update(0, Recorder())
    K = torch.tensor([[80.0, 0, 8], [0, 80.0, 8], [0, 0, 1]])  # a narrow view
    g.mark_unseen(K, torch.tensor(_look_at([0, 0, -4], [0, 0, 0]))[None], 16, 16, 0.5)
    valid = g.valid.view(-1)
    assert 0 < valid.sum() < g.n_cells
    f = Recorder()
    g.update(16, f)
    assert sum(len(x) for x in f.x) == int(valid.sum())
    assert (g.density.view(-1)[~valid] == -1).all()


def test_nan_density_does_not_poison_the_grid():
    _gen()
    g = OccupancyGrid([-1, -1, -1, 1, 1, 1], resolution=8)

    def f(x):
        s = 100.0 * torch.ones(x.shape[0])
        s[::7] = float("nan")
        return s

    g.update(0, f)
    assert torch.isfinite(g.density).all() and torch.isfinite(g.threshold).all()
    assert g.binary.sum() > 0.8 * g.n_cells


def _look_at(eye, target):
    """OpenCV camera-to-world (x right, y down, z forward) looking from eye at target."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    z = target - eye
    z /= np.linalg.norm(z)
    up = np.array([0.0, 1.0, 0.0]) if abs(z[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(-up, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    m = np.eye(4)
    m[:3, :3] = np.stack([x, y, z], 1)
    m[:3, 3] = eye
    return m


def test_mark_unseen_with_known_cameras():
    _gen()
    g = OccupancyGrid([-1, -1, -1, 1, 1, 1], resolution=16, n_cascades=2)
    W, H = 64, 48
    K = np.array([[150.0, 0, 32], [0, 150.0, 24], [0, 0, 1]])
    c2ws = np.stack([_look_at([0, 0, -4], [0, 0, 0]), _look_at([4, 0.5, 0], [0, 0.2, 0])])
    near = 0.5
    g.mark_unseen(torch.tensor(K), torch.tensor(c2ws), W, H, near)
    # float64 reference of the documented rule
    lo, hi = cell_boxes(g)
    centre, rad = 0.5 * (lo + hi), 0.5 * np.linalg.norm(hi - lo, axis=1)
    seen = np.zeros(len(lo), bool)
    margin = np.full(len(lo), np.inf)  # distance to the decision boundary, to skip ties
    for c2w in c2ws:
        p = (np.linalg.inv(c2w) @ np.c_[centre, np.ones(len(lo))].T).T[:, :3]
        z = p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = K[0, 0] * p[:, 0] / z + K[0, 2]
            v = K[1, 1] * p[:, 1] / z + K[1, 2]
            mu, mv = K[0, 0] * rad / z, K[1, 1] * rad / z
            slack = np.minimum.reduce([u + mu, W + mu - u, v + mv, H + mv - v])
        front = z > near
        seen |= (front & (slack >= 0)) | (~front & (z + rad > near))
        margin = np.minimum(margin, np.where(front, np.abs(slack), np.abs(z + rad - near)))
        margin = np.minimum(margin, np.abs(z - near))
    clear = margin > 1e-3
    valid = g.valid.view(-1).numpy()
    assert (valid[clear] == seen[clear]).all()
    assert 0 < (~seen).sum() and seen.sum() > 0
    assert not g.binary.view(-1).numpy()[~valid].any()
    # unseen cells stay empty whatever the field says, seen cells fill up
    g.update(0, lambda x: torch.full((x.shape[0],), 1e3))
    g.update(300, lambda x: torch.full((x.shape[0],), 1e3))
    b = g.binary.view(-1).numpy()
    assert (b == valid).all()
    assert (g.density.view(-1).numpy()[~valid] == -1).all()


@pytest.mark.parametrize("n_cascades", [1, 2])
def test_cylinder_clip(n_cascades):
    _gen()
    cyl = (0.5, -0.3, 0.6)
    g = OccupancyGrid([-1, -1, -1, 1, 1, 1], resolution=16, n_cascades=n_cascades, cylinder=cyl)
    lo, hi = cell_boxes(g)
    dx = np.maximum.reduce([lo[:, 0], -hi[:, 0], np.zeros(len(lo))])
    dz = np.maximum.reduce([lo[:, 2], -hi[:, 2], np.zeros(len(lo))])
    outside = (dx**2 + dz**2 > cyl[0] ** 2) | (hi[:, 1] < cyl[1]) | (lo[:, 1] > cyl[2])
    assert (g.valid.view(-1).numpy() == ~outside).all()
    g.update(0, lambda x: torch.full((x.shape[0],), 1e3))
    assert (g.binary.view(-1).numpy() == ~outside).all()
    # state round trip keeps the clip and the occupancy
    g2 = OccupancyGrid([-1, -1, -1, 1, 1, 1], resolution=16, n_cascades=n_cascades)
    g2.load_state_dict(g.state_dict())
    assert g2.cylinder == cyl
    assert torch.equal(g2.bitfield, g.bitfield) and torch.equal(g2.density, g.density)


def test_occupied_lookup_matches_reference():
    gen = _gen()
    C, R = 3, 8
    g = OccupancyGrid([0, -1, -1, 2, 1, 1], resolution=R, n_cascades=C)
    sd = g.state_dict()
    sd["density"] = (torch.rand(C, R**3, generator=gen) < 0.5).float()
    sd["threshold"] = torch.tensor([0.5])
    g.load_state_dict(sd)
    x = (torch.rand(5000, 3, generator=gen) * 2 - 1) * 5 + torch.tensor([1.0, 0, 0])
    got = g.occupied(x).numpy()
    q = x.double().numpy() - np.array([1.0, 0, 0])  # half extent 1
    m = np.abs(q).max(1)
    level = np.full(len(q), -1)
    for lv in reversed(range(C)):
        level[m <= 2.0**lv] = lv
    u = (q / 2.0 ** np.maximum(level, 0)[:, None] + 1) * 0.5 * R
    cell = np.clip(np.floor(u), 0, R - 1).astype(int)
    b = g.binary.numpy()
    expect = (level >= 0) & b[np.maximum(level, 0), cell[:, 0], cell[:, 1], cell[:, 2]]
    amb = (np.abs(u - np.round(u)) < 1e-4).any(1)
    assert (got[~amb] == expect[~amb]).all()
    assert expect.any() and (~expect).any() and (level < 0).any()
    # the faces of the outermost cascade are inside (last cell), beyond is empty
    on_face = g.occupied(torch.tensor([[1.0 + 4.0, 0.0, -4.0], [5.001, 0.0, 0.0]]))
    assert bool(on_face[0]) == bool(b[2, 7, 4, 0]) and not on_face[1]


@pytest.mark.parametrize(
    "res,C,f", [(128, 1, 8), (128, 4, 8), (32, 2, 8), (16, 2, 4), (8, 1, 4), (8, 2, 2), (4, 2, 1)]
)
def test_block_factor_keeps_blocks_inside_one_cascade_ring(res, C, f):
    from fastenerf.kernels.occupancy import block_factor

    assert block_factor(res, C) == f
    assert (res // 4 if C > 1 else res) % f == 0 and (f == 1 or res // f >= 2)


@pytest.mark.parametrize("res,C,f", [(16, 2, None), (8, 1, None), (16, 1, 2), (32, 2, 8)])
def test_blocks_are_any_of_their_cells(res, C, f):
    gen = torch.Generator().manual_seed(3)
    g = OccupancyGrid([-1, -1, -1, 1, 1, 1], resolution=res, n_cascades=C, block=f)
    f = g.block
    assert f > 1
    sd = g.state_dict()
    # sparse: most blocks empty, some with a single occupied cell
    sd["density"] = (torch.rand(C, res**3, generator=gen) < 2.0 / f**3).float()
    sd["threshold"] = torch.tensor([0.5])
    g.load_state_dict(sd)
    b = res // f
    want = g.binary.view(C, b, f, b, f, b, f).any(6).any(4).any(2).reshape(-1)
    assert torch.equal(g.blocks.bool(), want)
    assert 0 < want.sum() < want.numel()  # both kinds of block present


def test_block_must_divide_the_resolution():
    with pytest.raises(ValueError, match="block must divide"):
        OccupancyGrid([-1, -1, -1, 1, 1, 1], resolution=16, n_cascades=2, block=8)
    with pytest.raises(ValueError, match="block must divide"):
        OccupancyGrid([-1, -1, -1, 1, 1, 1], resolution=12, block=8)
    g = OccupancyGrid([-1, -1, -1, 1, 1, 1], resolution=12, block=1)
    assert g.block == 1 and g.blocks.numel() == 1
