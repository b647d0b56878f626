"""Ray-AABB and occupancy-guided marching vs a brute-force float64 reference.

The reference steps densely over every interval of the lattice (the same dt rule, no empty-space
skipping) and keeps the intervals whose midpoint cell is occupied. Float32 and float64 may put a
midpoint that lies within 1e-3 cells of a cell face on different sides: such reference samples
are "ambiguous" and may be missing from the kernel's output; all others must match.
"""

from __future__ import annotations

import math
import random

import numpy as np
import pytest
import torch

from fastenerf.kernels import raymarch as rm
from fastenerf.kernels.occupancy import OccupancyGrid
from fastenerf.kernels.raymarch import march_rays, ray_aabb
from fastenerf.kernels.raymarch_fixed import march_rays_fixed

AMBIG = 1e-3  # cells


def _seed():
    seed = random.SystemRandom().randrange(2**31)
    print(f"raymarch seed={seed}")  # shown by pytest on failure
    return np.random.default_rng(seed), torch.Generator().manual_seed(seed)


# ------------------------------------------------------------------ float64 reference


def ref_box(o, d, lo, hi, near=0.0, far=math.inf):
    tmin, tmax = -math.inf, math.inf
    for k in range(3):
        if abs(d[k]) < 1e-12:
            if o[k] < lo[k] or o[k] > hi[k]:
                return math.inf, math.inf
        else:
            ta, tb = (lo[k] - o[k]) / d[k], (hi[k] - o[k]) / d[k]
            tmin, tmax = max(tmin, min(ta, tb)), min(tmax, max(ta, tb))
    tmin, tmax = max(tmin, near), min(tmax, far)
    return (tmin, tmax) if tmax > tmin else (math.inf, math.inf)


def ref_t_of(t0, u, a, b, c):
    """Inverse warp, vectorised over u (float64)."""
    u = np.asarray(u, dtype=np.float64)
    t1p, t2p = (a / c, b / c) if c > 0 else (math.inf, math.inf)
    out = np.full(u.shape, t0)
    x, rem = t0, u.copy()
    if x < t1p:
        du = (t1p - x) / a
        m = (rem > 0) & (rem <= du)
        out[m] = x + rem[m] * a
        rem = rem - du
        x = t1p
    else:
        rem = rem.copy()
    if x < t2p and np.isfinite(x):
        L = math.log1p(c)
        du = math.log(t2p / x) / L
        m = (rem > 0) & (rem <= du)
        out[m] = x * np.exp(rem[m] * L)
        rem = rem - du
        x = t2p
    if np.isfinite(x):
        m = rem > 0
        out[m] = x + rem[m] * b
    return out


def ref_locate(p, center, half, res, C):
    q = (p - center) / half
    m = np.abs(q).max(-1)
    level = np.full(len(p), -1)
    for lv in reversed(range(C)):
        level[m <= 2.0**lv] = lv
    scale = 2.0 ** np.maximum(level, 0)
    u = (q / scale[:, None] + 1) * 0.5 * res
    cell = np.clip(np.floor(u), 0, res - 1).astype(np.int64)
    dist = np.abs(u - np.round(u))
    ambig = ((dist > 0) & (dist < AMBIG)).any(-1)
    return level, cell, ambig


def ref_march(
    o,
    d,
    box,
    binary,
    center,
    half,
    near,
    far,
    cone,
    dt_min,
    dt_max,
    jitter,
    cap,
    cylinder=None,
    exact=False,
):
    """Dense float64 marching of one ray: rows (t_start, t_end, optional).

    exact: the kept samples up to the cap (optional = 0). Otherwise the kept samples and those
    whose midpoint is too close to a cell face (or the cylinder) to call in float32: optional =
    1 marks samples the kernel may or may not emit.
    """
    t0, t1 = ref_box(o, d, box[:3], box[3:], near, far)
    if not t0 < t1:
        return np.zeros((0, 3))
    j = 0.0 if jitter is None else jitter
    # enough lattice steps to pass t1 (u grows at least 1 per dt_max)
    K = int((t1 - t0) / dt_min) + 3
    k = np.arange(K, dtype=np.float64)
    ta = ref_t_of(t0, k + j - 1, dt_min, dt_max, cone)
    tb = np.minimum(ref_t_of(t0, k + j, dt_min, dt_max, cone), t1)
    keep = (ta < t1) & (tb > ta)
    ta, tb = ta[keep], tb[keep]
    mid = 0.5 * (ta + tb)
    p = o + mid[:, None] * d
    amb = np.abs(t1 - ta) < 1e-5 * dt_min
    if binary is None:
        occ = np.ones(len(p), bool)
    else:
        C, res = binary.shape[0], binary.shape[1]
        level, cell, amb_cell = ref_locate(p, center, half, res, C)
        occ = (level >= 0) & binary[np.maximum(level, 0), cell[:, 0], cell[:, 1], cell[:, 2]]
        amb |= amb_cell
    if cylinder is not None:
        r, y0, y1 = cylinder
        rad = np.hypot(p[:, 0], p[:, 2])
        occ &= (rad <= r) & (p[:, 1] >= y0) & (p[:, 1] <= y1)
        e = 1e-5
        amb |= (np.abs(rad - r) < e) | (np.abs(p[:, 1] - y0) < e) | (np.abs(p[:, 1] - y1) < e)
    if exact:  # only the kept samples, up to the cap
        return np.stack([ta, tb, np.zeros_like(ta)], 1)[occ][:cap]
    # kept or ambiguous samples; column 2: 0 must be in the output, 1 may be
    keep = occ | amb
    return np.stack([ta, tb, (amb | ~occ).astype(np.float64)], 1)[keep]


def check_against_reference(
    out,
    rays_o,
    rays_d,
    box,
    grid,
    binary,
    near,
    far,
    cone,
    dt_min,
    dt_max,
    jitter,
    cap,
    exact=False,
):
    pi, ts, te, ri = (x.numpy() for x in out)
    R = rays_o.shape[0]
    assert pi.shape == (R, 2)
    assert (pi[:, 0] == np.concatenate([[0], np.cumsum(pi[:, 1])[:-1]])).all()
    assert pi[:, 1].sum() == len(ts) == len(te) == len(ri)
    assert (pi[:, 1] <= cap).all()
    if grid is not None:
        outer = grid.outer_aabb()
        box = [max(box[i], outer[i]) for i in range(3)] + [min(box[i], outer[i]) for i in (3, 4, 5)]
    center = None if grid is None else np.array(list(grid.center), np.float64)
    half = None if grid is None else np.array(list(grid.half), np.float64)
    cyl = None if grid is None else grid.cylinder
    o64, d64 = rays_o.double().numpy(), rays_d.double().numpy()
    n_checked = 0
    for r in range(R):
        s0, n = pi[r]
        assert (ri[s0 : s0 + n] == r).all()
        a, b = ts[s0 : s0 + n].astype(np.float64), te[s0 : s0 + n].astype(np.float64)
        j = None if jitter is None else float(jitter[r])
        ref = ref_march(
            o64[r],
            d64[r],
            np.array(box, np.float64),
            binary,
            center,
            half,
            near,
            far,
            cone,
            dt_min,
            dt_max,
            j,
            cap if exact else 10**9,
            cyl,
            exact,
        )
        tol = 1e-3 * dt_min + 2e-6 * np.abs(ref[:, 0]) if len(ref) else 0
        if exact:
            assert len(a) == len(ref), f"ray {r}: {len(a)} samples, reference {len(ref)}"
            np.testing.assert_allclose(a, ref[:, 0], atol=1e-3 * dt_min, rtol=2e-6)
            np.testing.assert_allclose(b, ref[:, 1], atol=1e-3 * dt_min, rtol=2e-6)
            n_checked += len(a)
            continue
        assert (np.diff(a) > 0).all() and (b > a).all()
        # every kernel sample is a reference sample
        idx = np.clip(np.searchsorted(ref[:, 0], a), 0, max(len(ref) - 1, 0))
        if len(a):
            assert len(ref), f"ray {r}: kernel has {len(a)} samples, reference none"
            lo_i = np.maximum(idx - 1, 0)
            pick = np.where(np.abs(ref[lo_i, 0] - a) < np.abs(ref[idx, 0] - a), lo_i, idx)
            ok = (np.abs(ref[pick, 0] - a) <= tol[pick]) & (np.abs(ref[pick, 1] - b) <= tol[pick])
            assert ok.all(), f"ray {r}: samples {a[~ok][:3]} not in the reference"
            matched = np.zeros(len(ref), bool)
            matched[pick] = True
        else:
            matched = np.zeros(len(ref), bool)
        # every unambiguous reference sample is in the kernel's output (below the cap)
        must = (ref[:, 2] == 0) & ~matched
        if pi[r, 1] < cap:
            assert not must.any(), f"ray {r}: missing samples at t={ref[must, 0][:3]}"
        n_checked += len(a)
    return n_checked


def _grid(C, res, p_occ, gen, cylinder=None):
    g = OccupancyGrid([-1, -1, -1, 1, 1, 1], resolution=res, n_cascades=C, cylinder=cylinder)
    dens = (torch.rand(C, res**3, generator=gen) < p_occ).float()
    sd = g.state_dict()
    sd["density"] = torch.where(g.density < 0, g.density, dens)
    sd["threshold"] = torch.tensor([0.5])
    g.load_state_dict(sd)
    return g, g.binary.numpy()


def _rays(R, gen, spread=3.0):
    o = (torch.rand(R, 3, generator=gen) * 2 - 1) * spread
    target = (torch.rand(R, 3, generator=gen) * 2 - 1) * 0.8
    d = target - o + 0.3 * torch.randn(R, 3, generator=gen)
    return o, torch.nn.functional.normalize(d, dim=-1)


# ------------------------------------------------------------------ tests


def test_ray_aabb_matches_reference_and_edge_cases():
    _, gen = _seed()
    box = [-1.0, -0.5, -2.0, 1.0, 1.5, 0.5]
    o, d = _rays(500, gen)
    special_o = torch.tensor(
        [
            [0.0, 0.0, 0.0],  # inside
            [-3.0, 1.5, 0.0],  # in the face plane y = ymax, moving along x
            [-3.0, 1.5, 0.0],  # same with d_y = -0.0
            [-3.0, 2.0, 0.0],  # parallel above the box: miss
            [-1.0, 0.0, 0.0],  # on a face, moving in
            [-1.0, 0.0, 0.0],  # on a face, moving out
            [-3.0, 1.5, 0.5],  # along an edge
            [3.0, 3.0, 3.0],  # pointing away
        ]
    )
    special_d = torch.tensor(
        [
            [0.0, 0.0, 1.0],
            [1.0, 0.0, 0.0],
            [1.0, -0.0, 0.0],
            [1.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [-1.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.6, 0.0, 0.8],
        ]
    )
    o, d = torch.cat([o, special_o]), torch.cat([d, special_d])
    near = 0.05
    tn, tf = ray_aabb(o, d, box, near=near)
    assert not torch.isnan(tn).any() and not torch.isnan(tf).any()
    for r in range(o.shape[0]):
        rn, rf = ref_box(o[r].double().tolist(), d[r].double().tolist(), box[:3], box[3:], near)
        if math.isinf(rn):
            assert math.isinf(tn[r]) and math.isinf(tf[r]), r
        else:
            assert abs(tn[r] - rn) < 1e-5 * (1 + abs(rn)) and abs(tf[r] - rf) < 1e-5 * (1 + rf)
    R0 = 500
    assert tn[R0] == near and tf[R0] == pytest.approx(0.5)
    assert tn[R0 + 1] == pytest.approx(2.0) and tf[R0 + 1] == pytest.approx(4.0)
    assert tn[R0 + 2] == tn[R0 + 1] and tf[R0 + 2] == tf[R0 + 1]  # sign of zero irrelevant
    assert math.isinf(tn[R0 + 3]) and math.isinf(tn[R0 + 7])
    assert tn[R0 + 4] == near and tf[R0 + 4] == pytest.approx(2.0)
    assert math.isinf(tn[R0 + 5])  # leaves at once: only touches the box
    assert tf[R0 + 6] == pytest.approx(4.0)


@pytest.mark.parametrize(
    "C,res,cone,dt,jit,cyl",
    [
        (2, 16, 0.02, (0.01, 0.04), True, None),  # all three step phases, two cascades
        (1, 16, 0.0, (None, None), False, None),  # default dt_min, constant steps
        (1, 8, 0.01, (0.005, 0.02), True, (0.6, -0.5, 0.4)),  # cylinder clip
    ],
)
def test_march_matches_dense_reference(C, res, cone, dt, jit, cyl):
    rng, gen = _seed()
    g, binary = _grid(C, res, 0.3, gen, cylinder=cyl)
    R = 120
    o, d = _rays(R, gen)
    o[:5] = torch.rand(5, 3, generator=gen) - 0.5  # cameras inside the box
    jitter = torch.rand(R, generator=gen) if jit else None
    box = [-2.0, -2.0, -2.0, 2.0, 2.0, 2.0]
    near, far = 0.02, 6.0
    dt_min = dt[0] or g.step_size
    dt_max = dt[1] or dt_min
    out = march_rays(o, d, box, g, near, far, cone, dt[0], dt[1], 10**6, jitter)
    n = check_against_reference(
        out,
        o,
        d,
        box,
        g,
        binary,
        near,
        far,
        cone,
        dt_min,
        dt_max,
        None if jitter is None else jitter.numpy(),
        10**6,
    )
    assert n > 100  # the case is not vacuous
    # deterministic for a fixed jitter, and the same whatever the threads per ray
    again = march_rays(o, d, box, g, near, far, cone, dt[0], dt[1], 10**6, jitter, segments=3)
    for x, y in zip(out, again, strict=True):
        assert torch.equal(x, y)


def test_boundaries_faces_and_inside_cameras_exactly():
    """Rays in cell-face planes, starting on box faces/edges or inside occupied cells:
    no sample is ambiguous there, so kernel and reference agree sample for sample."""
    _, gen = _seed()
    g, binary = _grid(1, 8, 0.5, gen)
    occ_cell = np.argwhere(binary[0])[0]
    inside = torch.tensor((occ_cell + 0.5) / 8 * 2 - 1, dtype=torch.float32)
    assert g.occupied(inside[None])[0]
    o = torch.tensor(
        [
            [-1.0, 0.0, 0.25],  # on the face x = -1, in the cell-face planes y = 0, z = 0.25
            [-1.0, -1.0, -1.0],  # on a corner, along the diagonal
            [1.0, 0.5, -0.5],  # on the face x = 1 moving in
            [-3.0, 1.0, 0.0],  # in the face plane y = 1
            [0.0, 0.0, 0.0],  # the centre: a corner of 8 cells
        ]
        + [inside.tolist()] * 2
    )
    d = torch.nn.functional.normalize(
        torch.tensor(
            [[1, 0, 0], [1, 1, 1], [-1, 0, 0], [1, 0, 0], [0, 0, 1], [0.3, -0.2, 0.9], [0, 1, 0]],
            dtype=torch.float32,
        ),
        dim=-1,
    )
    box = [-1.0, -1.0, -1.0, 1.0, 1.0, 1.0]
    dt_min = 0.0123  # incommensurate with the 0.25 cells
    out = march_rays(o, d, box, g, 0.0, None, 0.0, dt_min, dt_min, 10**6, None)
    check_against_reference(
        out, o, d, box, g, binary, 0.0, math.inf, 0.0, dt_min, dt_min, None, 10**6, exact=True
    )
    pi, ts = out[0], out[1]
    assert pi[5, 1] > 0 and ts[pi[5, 0]] == 0.0  # inside an occupied cell: starts at once


def test_empty_grid_and_full_grid_cap():
    _, gen = _seed()
    g = OccupancyGrid([-1, -1, -1, 1, 1, 1], resolution=8)
    o, d = _rays(50, gen)
    box = [-1.0] * 3 + [1.0] * 3
    # all occupied (fresh grid): the cap holds and keeps the nearest samples
    cap = 7
    out = march_rays(o, d, box, g, 0.0, None, 0.0, 0.05, 0.05, cap, None)
    full = march_rays(o, d, box, None, 0.0, None, 0.0, 0.05, 0.05, 10**6, None)
    n = check_against_reference(
        out, o, d, box, g, g.binary.numpy(), 0.0, math.inf, 0.0, 0.05, 0.05, None, cap, exact=True
    )
    assert n > 0
    torch.testing.assert_close(out[0][:, 1], full[0][:, 1].clamp(max=cap))
    # the cap across segments of one ray still keeps the nearest samples
    split = march_rays(o, d, box, g, 0.0, None, 0.0, 0.05, 0.05, cap, None, segments=5)
    for x, y in zip(out, split, strict=True):
        assert torch.equal(x, y)
    # nothing occupied: zero samples, no crash
    sd = g.state_dict()
    sd["threshold"] = torch.tensor([1.0])
    g.load_state_dict(sd)
    assert not g.binary.any()
    pi, ts, te, ri = march_rays(o, d, box, g, 0.0, None, 0.01, 0.01, 0.05, 64, torch.rand(50))
    assert pi.shape == (50, 2) and (pi == 0).all() and ts.numel() == te.numel() == ri.numel() == 0
    # no rays at all
    pi, ts, _, _ = march_rays(torch.zeros(0, 3), torch.zeros(0, 3), box, g)
    assert pi.shape == (0, 2) and ts.numel() == 0


def test_every_output_element_is_written(monkeypatch):
    def poisoned(*shape, dtype=torch.float32, device=None):
        t = torch.empty(*shape, dtype=dtype, device=device)
        return t.fill_(float("nan") if dtype.is_floating_point else -(2**30))

    _, gen = _seed()
    g, _ = _grid(1, 8, 0.4, gen)
    o, d = _rays(64, gen)
    jitter = torch.rand(64, generator=gen)
    box = [-1.0] * 3 + [1.0] * 3
    clean = march_rays(o, d, box, g, 0.0, None, 0.0, 0.02, 0.02, 40, jitter)
    clean_aabb = ray_aabb(o, d, box)
    monkeypatch.setattr(rm, "_empty", poisoned)
    out = march_rays(o, d, box, g, 0.0, None, 0.0, 0.02, 0.02, 40, jitter)
    for x, y in zip(out, clean, strict=True):
        assert torch.equal(x, y)
    for x, y in zip(ray_aabb(o, d, box), clean_aabb, strict=True):
        assert torch.equal(x, y)


@pytest.mark.parametrize("C,res,cone,jit", [(2, 32, 0.0, False), (2, 16, 0.02, True)])
def test_empty_blocks_are_jumped_without_losing_a_sample(C, res, cone, jit):
    """A sparse grid (two blobs in mostly empty blocks): jumping empty blocks gives the dense
    reference's samples and the same output as marching cell by cell (block = 1)."""
    _, gen = _seed()
    grids = []
    for block in (None, 1):
        g = OccupancyGrid([-1, -1, -1, 1, 1, 1], resolution=res, n_cascades=C, block=block)
        sd = g.state_dict()
        x = (torch.arange(res) + 0.5) / res * 2 - 1
        p = torch.stack(torch.meshgrid(x, x, x, indexing="ij"), -1).view(-1, 3)
        dens = [(p - 0.3).norm(dim=-1) < 0.2, (p + 0.35).norm(dim=-1) < 0.12]
        outer = [((2 * p - torch.tensor([0.9, -0.5, 0.1])).norm(dim=-1) < 0.3)] * (C - 1)
        sd["density"] = torch.stack([dens[0] | dens[1], *outer]).float()
        sd["threshold"] = torch.tensor([0.5])
        g.load_state_dict(sd)
        grids.append(g)
    g, g1 = grids
    assert g.block > 1 and g1.block == 1
    assert (g.blocks == 0).float().mean() > 0.5  # the jump is exercised
    R = 150
    o, d = _rays(R, gen)
    aim = torch.tensor([[0.3] * 3, [-0.35] * 3])[torch.arange(R) % 2]  # half at each blob
    d = torch.nn.functional.normalize(aim + 0.15 * torch.randn(R, 3, generator=gen) - o, dim=-1)
    jitter = torch.rand(R, generator=gen) if jit else None
    box = [-4.0, -4.0, -4.0, 4.0, 4.0, 4.0]
    dt = (0.01, 0.04) if cone else (None, None)
    out = march_rays(o, d, box, g, 0.0, None, cone, dt[0], dt[1], 10**6, jitter)
    dt_min = dt[0] or g.step_size
    n = check_against_reference(
        out,
        o,
        d,
        box,
        g,
        g.binary.numpy(),
        0.0,
        math.inf,
        cone,
        dt_min,
        dt[1] or dt_min,
        None if jitter is None else jitter.numpy(),
        10**6,
    )
    assert n > 200
    cellwise = march_rays(o, d, box, g1, 0.0, None, cone, dt[0], dt[1], 10**6, jitter)
    # equal up to a midpoint within float rounding of a block face, which random rays miss
    for x, y in zip(out, cellwise, strict=True):
        assert torch.equal(x, y)
    split = march_rays(o, d, box, g, 0.0, None, cone, dt[0], dt[1], 10**6, jitter, segments=3)
    for x, y in zip(out, split, strict=True):
        assert torch.equal(x, y)


@pytest.mark.parametrize("cap,segments,jit", [(10**6, None, True), (9, 3, False)])
def test_runs_and_blocks_change_no_sample(monkeypatch, cap, segments, jit):
    """An occupied cell's samples taken as one run, and empty blocks jumped in one step, give
    the per-sample, cell-by-cell march bit for bit (two cascades, all three step phases; a
    midpoint within float rounding of a block face aside, which random rays miss)."""
    _, gen = _seed()
    res, C = 16, 2
    grids = []
    for block in (None, 1):
        g = OccupancyGrid([-1, -1, -1, 1, 1, 1], resolution=res, n_cascades=C, block=block)
        sd = g.state_dict()
        sd["density"] = (torch.rand(C, res**3, generator=gen.manual_seed(5)) < 0.05).float()
        sd["threshold"] = torch.tensor([0.5])
        g.load_state_dict(sd)
        grids.append(g)
    assert grids[0].block > 1 and (grids[0].blocks == 0).any()
    o, d = _rays(200, gen)
    jitter = torch.rand(200, generator=gen) if jit else None
    box = [-4.0] * 3 + [4.0] * 3
    outs = []
    for runs, g in ((False, grids[1]), (True, grids[1]), (True, grids[0]), (True, None)):
        monkeypatch.setattr(rm, "RUNS", runs)
        outs.append(march_rays(o, d, box, g, 0.05, None, 0.02, 0.01, 0.08, cap, jitter, segments))
    assert outs[0][1].numel() > 100
    for out in outs[1:3]:
        for x, y in zip(out, outs[0], strict=True):
            assert torch.equal(x, y)
    monkeypatch.setattr(rm, "RUNS", False)
    dense = march_rays(o, d, box, None, 0.05, None, 0.02, 0.01, 0.08, cap, jitter, segments)
    for x, y in zip(outs[3], dense, strict=True):
        assert torch.equal(x, y)
    # the fixed-capacity path, one slot short of fitting (the last ray with samples overflows)
    args = (o, d, box, grids[0], 0.05, None, 0.02, 0.01, 0.08, cap, jitter, segments)
    fixed = []
    for runs in (False, True):
        monkeypatch.setattr(rm, "RUNS", runs)
        fixed.append(march_rays_fixed(*args, capacity=outs[0][1].numel() - 1))
    assert fixed[0].overflow.any()
    for x, y in zip(*fixed, strict=True):
        assert torch.equal(x, y)


def test_runs_keep_to_the_per_sample_march_on_degenerate_rays(monkeypatch):
    """Where float32 cannot tell neighbouring lattice points apart (steps below a few ulps of
    t) the per-sample march drops the empty intervals and a run must not take them; rays with
    no direction or an unbounded range (t1 ~ 1e30) must not run to the cap of the lattice."""
    box = [-1.0, -1.0, -1.0, 1.0, 1.0, 1.0]
    grid = OccupancyGrid(box, resolution=16)
    far = torch.tensor([[-3000.0, 0.1, 0.2], [0.1, 0.2, 0.3], [0.1, 0.2, 0.3], [0.1, 0.2, 0.3]])
    d = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 0.0], [2e-12, 0.0, 0.0], [0.0, 0.0, 1.0]])
    for g, dt in ((None, 1e-4), (grid, 1e-4), (None, 0.01), (grid, 0.01)):
        outs = []
        for runs in (False, True):
            monkeypatch.setattr(rm, "RUNS", runs)
            outs.append(march_rays(far, d, box, g, 0.0, None, 0.0, dt, dt, 20))
        for x, y in zip(*outs, strict=True):
            assert torch.equal(x, y)
        ts, te = outs[1][1], outs[1][2]
        assert (te > ts).all()  # no zero-width interval
