"""Hidden cells: occupancy cells that training rays march through but never see.

On a solid object the occupancy grid keeps every cell inside it (the density is high there),
so a training ray marches the whole interior after its first surface. Compaction
(kernels/prune.py) then drops those samples again, after the density network has run on
every one of them (on blocks, H200: 142.8 marched a ray, 42.8 kept; how many of the dropped
ones lie inside solids is what the option's measurement says). This module
remembers compaction's verdict per cell and lets the training march skip a cell that no
training ray has seen:

    hits[c] = marched samples in cell c          seen[c] = those with T >= eps
    carved  = hits >= min_hits  and  seen == 0      (at each grid update)
    training march: occupied and not carved;  every `refresh` updates all three are cleared

T is the transmittance before the sample (the compositing rule of prune.py, with the same
float32 product), so a carved cell held only samples that compaction would have dropped for
every ray that crossed it since the last clearing. The counts run from one clearing to the
next (a carved cell gets no more samples, so its verdict stands until then); clearing them
every `refresh` updates lets a cell that becomes visible (the geometry moved while training)
be seen again. Only the training march uses the carved bits (`CarvedGrid`): evaluation, the
viewer and the mesh read the occupancy grid itself, so a solid stays solid there.

The tally runs inside the training step on fixed-size buffers (no host read, so a captured
step replays it).
"""

from __future__ import annotations

import functools

import torch
import warp as wp

from .common import fast_view, init, launch
from .composite import optical_depth
from .occupancy import OccupancyGrid, cell_id, locate_func


@functools.cache
def _tally_kernel(n_cascades: int):
    locate = locate_func(max(n_cascades, 1))

    @wp.kernel(enable_backward=False, module="unique")
    def tally(
        x: wp.array(dtype=wp.vec3),
        sigmas: wp.array(dtype=float),
        t_starts: wp.array(dtype=float),
        t_ends: wp.array(dtype=float),
        packed_info: wp.array(dtype=wp.vec2i),
        eps: float,
        center: wp.vec3,
        inv_half: wp.vec3,
        res: int,
        hits: wp.array(dtype=wp.int32),
        seen: wp.array(dtype=wp.int32),
    ):
        """One thread per ray: its samples' cells counted in runs (one atomic per run of
        samples in the same cell), the visible ones (T >= eps before them) apart."""
        r = wp.tid()
        start = packed_info[r][0]
        n = packed_info[r][1]
        T = wp.float32(1.0)
        cell = wp.int32(-1)
        run = wp.int32(0)
        vis = wp.int32(0)
        for i in range(n):
            s = start + i
            c = locate(x[s], center, inv_half, res)
            gid = wp.int32(-1)
            if c[0] >= 0:
                gid = cell_id(c, res)
            if gid != cell:
                if cell >= 0:
                    wp.atomic_add(hits, cell, run)
                    if vis > 0:
                        wp.atomic_add(seen, cell, vis)
                cell = gid
                run = 0
                vis = 0
            run += 1
            if T >= eps or not (T == T):  # a NaN ray is never called hidden
                vis += 1
            T = T * wp.exp(-optical_depth(sigmas[s], t_starts[s], t_ends[s]))
        if cell >= 0:
            wp.atomic_add(hits, cell, run)
            if vis > 0:
                wp.atomic_add(seen, cell, vis)

    return tally


class HiddenCells:
    """The carved cells of one occupancy grid and the training march's bits without them.

    grid: the occupancy grid; min_hits: marched samples a cell needs since the last clearing
    before it can be called hidden (>= 1); refresh: grid updates between clearings (>= 1; 1:
    nothing is ever carved).
    """

    def __init__(self, grid: OccupancyGrid, min_hits: int = 16, refresh: int = 8):
        if min_hits < 1 or refresh < 1:
            raise ValueError(f"min_hits and refresh must be >= 1, got {min_hits}, {refresh}")
        init()
        self.grid, self.min_hits, self.refresh = grid, int(min_hits), int(refresh)
        n, dev = grid.n_cells, grid.device
        self.hits = torch.zeros(n, dtype=torch.int32, device=dev)
        self.seen = torch.zeros(n, dtype=torch.int32, device=dev)
        self.carved = torch.zeros(n, dtype=torch.bool, device=dev)
        self.bitfield = grid.bitfield.clone()
        self.blocks = grid.blocks.clone()
        self.updates = 0

    def tally(self, x, sigmas, packed_info, t_starts, t_ends, eps: float) -> None:
        """Count the marched samples of one training batch per cell, and the visible ones.

        x: (S, 3) float32 sample points, world units; sigmas: (S,) float32 density, 1/world
        units; packed_info: (R, 2) int32 (first, count) per ray (slots outside every slice are
        not read); t_starts, t_ends: (S,) float32, world units; eps: the transmittance below
        which a sample is hidden (compaction's early_stop_eps)."""
        g = self.grid
        if packed_info.shape[0] == 0:
            return
        args = [
            fast_view(x.float().contiguous(), wp.vec3),
            sigmas.float().contiguous(),
            t_starts.float().contiguous(),
            t_ends.float().contiguous(),
            fast_view(packed_info.contiguous(), wp.vec2i),
            float(eps),
            g.center,
            g.inv_half,
            g.resolution,
            self.hits,
            self.seen,
        ]
        launch(_tally_kernel(g.n_cascades), packed_info.shape[0], sigmas, args)

    @torch.no_grad()
    def update(self, carve: bool = True) -> None:
        """After a grid update: carve the cells hidden since the last clearing, or clear the
        counts and the carved set (every `refresh` updates; carve=False: now, e.g. while a new
        field is still fog); then pack the training march's bits."""
        self.updates += 1
        if not carve or self.updates % self.refresh == 0:
            for t in (self.carved, self.hits, self.seen):
                t.zero_()
        else:
            torch.logical_and(self.hits >= self.min_hits, self.seen == 0, out=self.carved)
        self.pack()

    def pack(self) -> None:
        """The training bits: the grid's occupancy without the carved cells (in place, so a
        captured march keeps reading them)."""
        density = torch.where(self.carved, -1.0, self.grid.density.view(-1))
        self.grid.pack_into(density, self.bitfield, self.blocks)

    def to(self, device) -> HiddenCells:
        """Move the counts and bits to `device` (the grid's, after the field moved)."""
        for name in ("hits", "seen", "carved", "bitfield", "blocks"):
            setattr(self, name, getattr(self, name).to(device))
        return self

    def view(self) -> CarvedGrid:
        """The grid as the training march sees it."""
        return CarvedGrid(self.grid, self)


class CarvedGrid:
    """An occupancy grid with the carved cells' bits cleared: every attribute is the grid's
    but `bitfield` and `blocks` (what the marcher reads)."""

    def __init__(self, grid: OccupancyGrid, hidden: HiddenCells):
        self._grid, self.bitfield, self.blocks = grid, hidden.bitfield, hidden.blocks

    def __getattr__(self, name):
        return getattr(self._grid, name)
