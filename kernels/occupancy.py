"""Occupancy grid (instant-ngp): cascaded density EMA and a packed occupancy bitfield.

Geometry. Cascade k covers the base `aabb` scaled by 2**k about its centre, split into
`resolution`**3 cells. A point belongs to the finest cascade that contains it (faces inclusive).
Cell (k, ix, iy, iz) has flat id ``((k * R + ix) * R + iy) * R + iz``; its occupancy is bit
``id & 7`` of byte ``id >> 3`` of `bitfield` (uint8, C * R**3 / 8 bytes, 256 KiB per 128**3
cascade, so marching stays in cache). `blocks` (uint8, one byte per block of F**3 cells of one
cascade, F = `block_factor`) is 1 where any cell of the block is occupied: the marcher crosses an
empty block in one jump instead of cell by cell. Blocks never straddle the region of a finer
cascade (F divides R / 4), so a jump never passes over cells that a finer cascade holds.

State. `density` (C, R**3) float32 holds the EMA of sigma (1/world units) per cell; cells that
can never hold anything (seen by no training camera, or entirely outside the cylinder clip)
hold the sentinel -1 and stay empty forever.

Update (instant-ngp's `update_density_grid`, every 16 steps from the trainer):
  - before `warmup_steps`: every valid cell is sampled; afterwards a uniform random quarter of
    all cells plus as many drawn (with replacement) from the occupied ones; no count is read
    on the host, so an update does not wait for the queued steps;
  - one uniformly jittered point per chosen cell, sigma = density_fn(x);
  - every valid cell decays, chosen cells take the max with their new value:
        density = max(density * decay, sigma_new)    (sigma_new = 0 for cells not chosen)
  - threshold on optical thickness over one minimal step (instant-ngp's
    NERF_MIN_OPTICAL_THICKNESS = 0.01 with sigma * dt_min):
        occupied = density > min(threshold / step_size, mean of density over all valid cells)
    (the mean is taken over every cascade, as nerfacc does; instant-ngp uses cascade 0 only).
Before the first update every valid cell is occupied, so marching works from step 0.
"""

from __future__ import annotations

import functools
import math

import torch
import warp as wp

from .common import fast_view, init, launch

_empty = torch.empty
# Zero-copy descriptors (not wp.array objects): a third of the per-launch Python cost.


def default_step_size(aabb, diagonal_steps: int = 1024) -> float:
    """Minimal marching step (instant-ngp's √3/1024 per box extent): √3 · max side /
    diagonal_steps, world units."""
    a = [float(v) for v in aabb]
    return math.sqrt(3.0) * max(a[3] - a[0], a[4] - a[1], a[5] - a[2]) / diagonal_steps


# ---------------------------------------------------------------- shared Warp functions


@wp.func
def cell_of_id(gid: int, res: int) -> wp.vec4i:
    """(level, ix, iy, iz) of flat cell id `gid`."""
    r3 = res * res * res
    level = gid / r3
    rem = gid - level * r3
    return wp.vec4i(level, rem / (res * res), (rem / res) % res, rem % res)


@wp.func
def cell_size(level: int, half: wp.vec3, res: int) -> wp.vec3:
    """Edge lengths of a cell of cascade `level`, world units (level < 0, outside every
    cascade: cascade 0's, so a shift is never negative)."""
    return half * (2.0 * float(1 << wp.max(level, 0)) / float(res))


@wp.func
def cell_lo(c: wp.vec4i, center: wp.vec3, half: wp.vec3, res: int) -> wp.vec3:
    """Minimum corner of cell c = (level, ix, iy, iz), world units."""
    size = cell_size(c[0], half, res)
    lo = center - half * float(1 << wp.max(c[0], 0))
    return lo + wp.cw_mul(wp.vec3(float(c[1]), float(c[2]), float(c[3])), size)


@wp.func
def cell_id(c: wp.vec4i, res: int) -> int:
    """Flat id of cell c = (level, ix, iy, iz), level >= 0 (`cell_of_id`'s inverse)."""
    return ((c[0] * res + c[1]) * res + c[2]) * res + c[3]


@wp.func
def bit_at(bitfield: wp.array(dtype=wp.uint8), c: wp.vec4i, res: int) -> int:
    """Occupancy bit (0/1) of cell c = (level, ix, iy, iz); level < 0 reads as empty."""
    if c[0] < 0:
        return 0
    gid = cell_id(c, res)
    return (int(bitfield[gid >> 3]) >> (gid & 7)) & 1


@wp.func
def block_corner(c: wp.vec4i, f: int) -> wp.vec4i:
    """The first cell (level, ix, iy, iz) of the f**3-cell block holding cell c."""
    return wp.vec4i(c[0], (c[1] / f) * f, (c[2] / f) * f, (c[3] / f) * f)


@wp.func
def block_bit(blocks: wp.array(dtype=wp.uint8), c: wp.vec4i, res: int, f: int) -> int:
    """1 if any cell of the f**3-cell block holding cell c (level >= 0) is occupied."""
    rb = res / f
    return int(blocks[((c[0] * rb + c[1] / f) * rb + c[2] / f) * rb + c[3] / f])


def block_factor(resolution: int, n_cascades: int) -> int:
    """Cells per block edge: the largest of 8, 4, 2 that divides the resolution (R / 4 with
    several cascades, so no block straddles a finer cascade) and leaves >= 2 blocks per axis;
    1 (no blocks) if none does."""
    edge = resolution // 4 if n_cascades > 1 else resolution
    for f in (8, 4, 2):
        if edge % f == 0 and resolution // f >= 2:
            return f
    return 1


@functools.cache
def locate_func(n_cascades: int):
    """`locate(p, center, inv_half, res) -> vec4i(level, ix, iy, iz)`, level -1 outside every
    cascade (or p NaN); the cascade count is compiled in. inv_half = 1 / (half extent)."""

    @wp.func
    def locate(p: wp.vec3, center: wp.vec3, inv_half: wp.vec3, res: int) -> wp.vec4i:
        q = wp.cw_mul(p - center, inv_half)
        m = wp.max(wp.abs(q))
        level = wp.int32(0)
        scale = wp.float32(1.0)
        for _ in range(wp.static(n_cascades - 1)):
            if m > scale:
                level += 1
                scale *= 2.0
        if not (m <= scale):
            return wp.vec4i(-1, 0, 0, 0)
        u = (q / scale + wp.vec3(1.0)) * (0.5 * float(res))
        hi = res - 1
        return wp.vec4i(
            level,
            wp.clamp(int(wp.floor(u[0])), 0, hi),
            wp.clamp(int(wp.floor(u[1])), 0, hi),
            wp.clamp(int(wp.floor(u[2])), 0, hi),
        )

    return locate


# ---------------------------------------------------------------- kernels


@wp.kernel
def _cell_points(
    ids: wp.array(dtype=wp.int32),
    seed: int,
    center: wp.vec3,
    half: wp.vec3,
    res: int,
    points: wp.array(dtype=wp.vec3),
):
    i = wp.tid()
    c = cell_of_id(ids[i], res)
    state = wp.rand_init(seed, i)
    u = wp.vec3(wp.randf(state), wp.randf(state), wp.randf(state))
    points[i] = cell_lo(c, center, half, res) + wp.cw_mul(u, cell_size(c[0], half, res))


@wp.kernel
def _pack_bits(
    density: wp.array(dtype=float),
    threshold: wp.array(dtype=float),
    bitfield: wp.array(dtype=wp.uint8),
):
    b = wp.tid()
    thre = threshold[0]
    byte = wp.int32(0)
    for k in range(8):
        if density[b * 8 + k] > thre:
            byte = byte | (1 << k)
    bitfield[b] = wp.uint8(byte)


@wp.kernel
def _pack_blocks(
    bitfield: wp.array(dtype=wp.uint8),
    res: int,
    f: int,
    blocks: wp.array(dtype=wp.uint8),
):
    """blocks[b] = 1 where any of block b's f**3 cells is occupied (a thread per block)."""
    b = wp.tid()
    c = cell_of_id(b, res / f)  # (level, block x, y, z)
    occ = wp.int32(0)
    for i in range(f):
        for j in range(f):
            row = ((c[0] * res + c[1] * f + i) * res + c[2] * f + j) * res + c[3] * f
            for k in range(f):
                gid = row + k
                occ = occ | ((int(bitfield[gid >> 3]) >> (gid & 7)) & 1)
    blocks[b] = wp.uint8(occ)


@wp.kernel
def _mark_unseen(
    w2c: wp.array(dtype=wp.mat44),
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    width: float,
    height: float,
    near: float,
    center: wp.vec3,
    half: wp.vec3,
    res: int,
    density: wp.array(dtype=float),
):
    gid = wp.tid()
    c = cell_of_id(gid, res)
    size = cell_size(c[0], half, res)
    x = cell_lo(c, center, half, res) + 0.5 * size
    rad = 0.5 * wp.length(size)  # bounding sphere: a cell counts as seen if any of it may be
    seen = wp.int32(0)
    for k in range(w2c.shape[0]):
        if seen == 0:
            p = wp.transform_point(w2c[k], x)
            z = p[2]
            if z > near:
                mu = fx * rad / z
                mv = fy * rad / z
                u = fx * p[0] / z + cx
                v = fy * p[1] / z + cy
                if u >= -mu and u <= width + mu and v >= -mv and v <= height + mv:
                    seen = 1
            elif z + rad > near:  # straddles the near plane
                seen = 1
    if seen == 0:
        density[gid] = -1.0


@wp.kernel
def _clip_cylinder(
    radius: float,
    y_min: float,
    y_max: float,
    center: wp.vec3,
    half: wp.vec3,
    res: int,
    density: wp.array(dtype=float),
):
    gid = wp.tid()
    c = cell_of_id(gid, res)
    lo = cell_lo(c, center, half, res)
    hi = lo + cell_size(c[0], half, res)
    # distance from the y axis to the cell's xz rectangle
    dx = wp.max(wp.max(lo[0], -hi[0]), 0.0)
    dz = wp.max(wp.max(lo[2], -hi[2]), 0.0)
    outside = dx * dx + dz * dz > radius * radius or hi[1] < y_min or lo[1] > y_max
    if outside:
        density[gid] = -1.0


@functools.cache
def _lookup_kernel(n_cascades: int):
    locate = locate_func(n_cascades)

    @wp.kernel(module="unique")
    def lookup(
        points: wp.array(dtype=wp.vec3),
        center: wp.vec3,
        inv_half: wp.vec3,
        res: int,
        bitfield: wp.array(dtype=wp.uint8),
        out: wp.array(dtype=wp.uint8),
    ):
        i = wp.tid()
        out[i] = wp.uint8(bit_at(bitfield, locate(points[i], center, inv_half, res), res))

    return lookup


# ---------------------------------------------------------------- the grid


class OccupancyGrid:
    """Cascaded occupancy grid over `aabb`; a plain object holding torch tensors.

    Args:
        aabb: [xmin, ymin, zmin, xmax, ymax, zmax] of cascade 0, world units.
        resolution: cells per axis per cascade (even; a multiple of 4 with several cascades).
        n_cascades: 1 for an object inside `aabb`; cascade k covers aabb scaled by 2**k.
        cylinder: optional (radius, y_min, y_max) clip (x² + z² ≤ r², y_min ≤ y ≤ y_max) or an
            object with those attributes (`fastenerf.config.CylinderConfig`); cells entirely
            outside are never occupied, and the marcher drops samples outside it.
        step_size: minimal marching step that `threshold` refers to (default
            `default_step_size(aabb)`).
        block: cells per edge of the empty-space blocks the marcher jumps over (default
            `block_factor`; 1: none). It must divide the resolution (R / 4 with cascades).
    """

    def __init__(
        self,
        aabb,
        resolution: int = 128,
        n_cascades: int = 1,
        cylinder=None,
        step_size: float | None = None,
        device: str | torch.device = "cpu",
        block: int | None = None,
    ):
        init()
        a = [float(v) for v in aabb]
        if len(a) != 6 or not all(a[i] < a[i + 3] for i in range(3)):
            raise ValueError(f"aabb must be [xmin, ymin, zmin, xmax, ymax, zmax], got {a}")
        if resolution < 2 or resolution % 2 or (n_cascades > 1 and resolution % 4):
            raise ValueError(f"resolution must be even (multiple of 4 for cascades): {resolution}")
        if not 1 <= n_cascades <= 8:
            raise ValueError(f"n_cascades must be in 1..8, got {n_cascades}")
        self.resolution = int(resolution)
        self.n_cascades = int(n_cascades)
        self.aabb_list = a
        self.step_size = float(step_size) if step_size else default_step_size(a)
        if cylinder is not None and not isinstance(cylinder, (tuple, list)):
            cylinder = (cylinder.radius, cylinder.y_min, cylinder.y_max)
        self.cylinder = None if cylinder is None else tuple(float(v) for v in cylinder)
        self.device = torch.device(device)
        n = self.n_cascades * self.resolution**3
        self.density = torch.zeros(self.n_cascades, self.resolution**3, device=self.device)
        self._valid_cache: torch.Tensor | None = None  # `_valid_ids`; None after any -1 write
        self.bitfield = torch.zeros(n // 8, dtype=torch.uint8, device=self.device)
        self.block = block_factor(resolution, n_cascades) if block is None else int(block)
        edge = self.resolution // 4 if self.n_cascades > 1 else self.resolution
        if self.block < 1 or edge % self.block:
            raise ValueError(f"block must divide {edge} (resolution {resolution}), got {block}")
        n_blocks = n // self.block**3 if self.block > 1 else 1  # 1: a placeholder, never read
        self.blocks = torch.zeros(n_blocks, dtype=torch.uint8, device=self.device)
        # Until the first update every valid cell (density 0 > -0.5) is occupied.
        self.threshold = torch.full((1,), -0.5, device=self.device)
        if self.cylinder is not None:
            r, y0, y1 = self.cylinder
            self._launch(_clip_cylinder, n, [r, y0, y1, *self._geom()], [self.density])
        self._pack()

    # -- geometry -------------------------------------------------------------------------
    @property
    def aabb(self) -> torch.Tensor:
        """(6,) float32 aabb of cascade 0."""
        return torch.tensor(self.aabb_list, device=self.device)

    @property
    def aabb_list(self) -> list[float]:
        """[xmin, ymin, zmin, xmax, ymax, zmax] of cascade 0 as Python floats."""
        return self._aabb

    @aabb_list.setter
    def aabb_list(self, a) -> None:
        # cached as Python/Warp values: building them per launch costs more than small kernels
        a = [float(v) for v in a]
        self._aabb = a
        self._c = [0.5 * (a[i] + a[i + 3]) for i in range(3)]
        self._h = [0.5 * (a[i + 3] - a[i]) for i in range(3)]
        self.center = wp.vec3(*self._c)
        self.half = wp.vec3(*self._h)
        self.inv_half = wp.vec3(*[1.0 / h for h in self._h])

    def outer_aabb(self) -> list[float]:
        """Box covered by the coarsest cascade, world units."""
        c, h, s = self._c, self._h, float(2 ** (self.n_cascades - 1))
        return [c[i] - s * h[i] for i in range(3)] + [c[i] + s * h[i] for i in range(3)]

    def _geom(self):
        return [self.center, self.half, self.resolution]

    @property
    def n_cells(self) -> int:
        return self.n_cascades * self.resolution**3

    @property
    def binary(self) -> torch.Tensor:
        """(C, R, R, R) bool occupancy, unpacked from `bitfield`."""
        bits = torch.arange(8, dtype=torch.uint8, device=self.device)
        R = self.resolution
        return ((self.bitfield[:, None] >> bits) & 1).bool().view(self.n_cascades, R, R, R)

    @property
    def valid(self) -> torch.Tensor:
        """(C, R**3) bool: cells that may ever be occupied (not marked -1)."""
        return self.density >= 0

    def _launch(self, kernel, dim, inputs, outputs):
        if dim > 0:
            launch(kernel, dim, self.density, [*inputs, *[x.view(-1) for x in outputs]])

    def _pack(self) -> None:
        self.pack_into(self.density, self.bitfield, self.blocks)

    def pack_into(self, density: torch.Tensor, bitfield: torch.Tensor, blocks: torch.Tensor):
        """Pack `density` ((C, R**3) or (C·R**3,) float32, 1/world units; -1 never occupied)
        against the grid's threshold into `bitfield` and `blocks` (this grid's layout), in
        place: the grid's own bits, or another set a march reads (hidden_cells.py)."""
        self._launch(_pack_bits, self.n_cells // 8, [density.view(-1), self.threshold], [bitfield])
        if self.block > 1:
            f = self.block
            self._launch(
                _pack_blocks, self.n_cells // f**3, [bitfield, self.resolution, f], [blocks]
            )

    # -- queries ----------------------------------------------------------------------------
    def cell_points(self, ids: torch.Tensor, seed: int | None = None) -> torch.Tensor:
        """One uniformly jittered world point (M, 3) inside each cell of flat ids (M,)."""
        if seed is None:
            seed = int(torch.randint(0, 2**31 - 1, (1,)))
        ids = ids.to(device=self.device, dtype=torch.int32).contiguous()
        pts = _empty(ids.shape[0], 3, dtype=torch.float32, device=self.device)
        if ids.shape[0] > 0:
            launch(
                _cell_points, ids.shape[0], pts, [ids, seed, *self._geom(), fast_view(pts, wp.vec3)]
            )
        return pts

    def occupied(self, x: torch.Tensor) -> torch.Tensor:
        """(N,) bool: is world point x (N, 3) in an occupied cell (False outside the grid)."""
        x = x.to(device=self.device, dtype=torch.float32).contiguous()
        out = _empty(x.shape[0], dtype=torch.uint8, device=self.device)
        if x.shape[0] > 0:
            launch(
                _lookup_kernel(self.n_cascades),
                x.shape[0],
                out,
                [
                    fast_view(x, wp.vec3),
                    self.center,
                    self.inv_half,
                    self.resolution,
                    self.bitfield,
                    out,
                ],
            )
        return out.bool()

    # -- updates ----------------------------------------------------------------------------
    @torch.no_grad()
    def update(
        self,
        step: int,
        density_fn,
        decay: float = 0.95,
        threshold: float = 0.01,
        warmup_steps: int = 256,
        chunk: int = 2**18,
    ) -> None:
        """One instant-ngp grid update (see the module docstring for the exact rule).

        Args:
            step: the trainer's step (selects warm-up vs. sparse sampling).
            density_fn: x (M, 3) world float32 -> sigma (M,) or (M, 1), 1/world units; called
                in chunks of `chunk` points under no_grad. NaN reads as 0, +inf as float max.
            decay: EMA decay per update.
            threshold: optical-thickness threshold over one `step_size`.
        """
        valid = self.valid.view(-1)
        if step < warmup_steps:
            ids = self._valid_ids()
        else:
            # fixed sizes, so the host never waits for a count; an invalid cell drawn here is
            # evaluated and then left as it is by the `where(valid, ...)` below
            n = self.n_cells // 4
            uniform = torch.randint(0, self.n_cells, (n,), device=self.device)
            ids = torch.cat([uniform, self._draw_occupied(n)])
        pts = self.cell_points(ids)
        sig = [density_fn(pts[i : i + chunk]).reshape(-1) for i in range(0, pts.shape[0], chunk)]
        sig = torch.cat(sig) if sig else pts.new_zeros(0)
        sig = torch.nan_to_num(sig.float(), nan=0.0).clamp_min(0.0)
        new = torch.zeros(self.n_cells, device=self.device)
        new.scatter_reduce_(0, ids, sig, reduce="amax")
        d = self.density.view(-1)
        d.copy_(torch.where(valid, torch.maximum(d * decay, new), d))
        mean = torch.where(valid, d, 0.0).sum() / valid.sum().clamp_min(1)
        self.threshold = torch.clamp(mean, max=threshold / self.step_size).reshape(1)
        self._pack()

    def _valid_ids(self) -> torch.Tensor:
        """(M,) int64 flat ids of the valid cells; counted once (one host read) per change."""
        if self._valid_cache is None:
            self._valid_cache = torch.nonzero(self.valid.view(-1))[:, 0]
        return self._valid_cache

    def _draw_occupied(self, n: int) -> torch.Tensor:
        """(n,) int64 flat ids drawn uniformly, with replacement, from the occupied cells
        (instant-ngp's non-uniform half), without reading their count on the host. With no
        cell occupied the draw is the last cell, which the update then simply re-measures."""
        cum = torch.cumsum(self.binary.view(-1), 0)
        r = (torch.rand(n, device=self.device, dtype=torch.float64) * cum[-1]).long()
        return torch.searchsorted(cum, r, right=True).clamp_(max=self.n_cells - 1)

    @torch.no_grad()
    def mark_unseen(
        self, K: torch.Tensor, c2ws: torch.Tensor, width: int, height: int, near: float = 0.0
    ) -> None:
        """Mark cells that no camera sees as never occupied (density -1, bit cleared).

        A cell counts as seen by a camera (OpenCV, pinhole K (3, 3), camera-to-world c2ws
        (M, 4, 4)) when its bounding sphere lies partly in front of the near plane and its
        centre projects within the image grown by the sphere's projected radius (a cell only
        partly in view is kept). Cost: cells x cameras; pass a subset of views when M is large.
        """
        K = torch.as_tensor(K, dtype=torch.float64).cpu()
        c2ws = torch.as_tensor(c2ws, dtype=torch.float64).reshape(-1, 4, 4)
        w2c = torch.linalg.inv(c2ws).float().to(self.device).contiguous()
        fx, fy, cx, cy = (float(v) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
        launch(
            _mark_unseen,
            self.n_cells,
            self.density,
            [
                fast_view(w2c, wp.mat44),
                fx,
                fy,
                cx,
                cy,
                float(width),
                float(height),
                float(near),
                *self._geom(),
                self.density.view(-1),
            ],
        )
        self._valid_cache = None
        self._pack()

    # -- persistence --------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {
            "aabb": self.aabb.cpu(),
            "resolution": self.resolution,
            "n_cascades": self.n_cascades,
            "step_size": self.step_size,
            "cylinder": None if self.cylinder is None else list(self.cylinder),
            "density": self.density.cpu(),
            "threshold": self.threshold.cpu(),
        }

    def load_state_dict(self, sd: dict) -> None:
        if sd["resolution"] != self.resolution or sd["n_cascades"] != self.n_cascades:
            raise ValueError(
                f"occupancy grid {sd['n_cascades']}x{sd['resolution']}^3 in the state does not "
                f"match this grid ({self.n_cascades}x{self.resolution}^3)"
            )
        self.aabb_list = [float(v) for v in sd["aabb"]]
        self.step_size = float(sd["step_size"])
        self.cylinder = None if sd["cylinder"] is None else tuple(sd["cylinder"])
        self.density.copy_(sd["density"])
        self._valid_cache = None
        self.threshold = sd["threshold"].to(self.device).reshape(1).float()
        self._pack()

    def to(self, device) -> OccupancyGrid:
        self.device = torch.device(device)
        self.density = self.density.to(self.device)
        self._valid_cache = None
        self.bitfield = self.bitfield.to(self.device)
        self.blocks = self.blocks.to(self.device)
        self.threshold = self.threshold.to(self.device)
        return self
