"""The ngp field's sampler: rays marched through an occupancy grid (DESIGN §4).

As nerfacc's OccGridEstimator is separate from the radiance field it samples, this holds what
places the samples, and the field (fields/ngp.py) only evaluates and composites them:
    rays --march_rays (occupancy grid)--> packed samples [--prune (σ alone)--> fewer samples]
The sampler owns the occupancy grid and refreshes it from the field's σ (`update`); it decides
whether a training step compacts its samples (`MarcherOptions.early_stop_eps`; compaction.py)
and sizes the fixed-capacity buffers a captured step marches into (capacity.py). It is not a
module: it adds no parameter or buffer to the field, whose extra state carries the grid.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from ..backends import NGPOptions
from ..config import CylinderConfig
from ..kernels.hidden_cells import HiddenCells
from ..kernels.occupancy import OccupancyGrid, default_step_size
from ..kernels.prune import prune_samples, prune_samples_fixed
from ..kernels.ray_points import ray_points
from ..kernels.raymarch import march_rays
from ..kernels.raymarch_fixed import FixedSamples, empty_fixed_samples, march_rays_fixed
from .base import view_cone_angle
from .capacity import SampleCapacity
from .compaction import CompactionSwitch

# σ (N,) float32, 1/world units, at world points (N, 3): the field's density, unchecked
SigmaFn = Callable[[torch.Tensor], torch.Tensor]


class OccupancySampler:
    """Samples along rays through an occupancy grid over `aabb`, for an ngp field.

    aabb: [xmin, ymin, zmin, xmax, ymax, zmax] world units; options: the field's options (the
    marcher and occupancy sections apply here); cylinder: optional clip of the grid's cells;
    device: where the grid is built (its kernels launched).
    """

    # the training step `update` last saw (the early cone applies before `early_steps`)
    train_step: int = 0
    # fixed-capacity training marches (None: exactly sized, the host reads the count)
    sample_capacity: SampleCapacity | None = None
    # the same for the compacted samples (MarcherOptions.early_stop_eps), None: exact or off
    pruned_capacity: SampleCapacity | None = None
    # (R,) uniform [0, 1) march offsets drawn outside a captured step (None: drawn per march)
    train_jitter: torch.Tensor | None = None
    _fixed_out = None
    _fixed_key = None
    _pruned_out = None
    _pruned_key = None
    _capacity_cone = None

    def __init__(
        self,
        aabb,
        options: NGPOptions,
        cylinder: CylinderConfig | None,
        device: torch.device,
    ):
        self.options = options
        # the box as kernel arguments: read on the host once, not from the device every march
        self._aabb_host = [float(v) for v in np.asarray(aabb, dtype=np.float32)]
        cyl = None if cylinder is None else (cylinder.radius, cylinder.y_min, cylinder.y_max)
        # The grid's threshold is an optical thickness over one minimal step: the marcher's.
        self.grid = OccupancyGrid(
            list(aabb),
            options.occupancy.grid_resolution,
            1,
            cylinder=cyl,
            step_size=options.marcher.dt_min
            or default_step_size(aabb, options.marcher.diagonal_steps),
            device=device,
        )
        # the training march's carved cells (MarcherOptions.carve_hidden; None: off)
        self.hidden = None
        if options.marcher.carve_hidden and self._compaction_set():
            m = options.marcher
            self.hidden = HiddenCells(self.grid, m.carve_min_hits, m.carve_refresh)
        self.compaction = None  # compaction_auto's switch (None: fixed by the options)
        if options.marcher.compaction_auto and self._compaction_set():
            self.compaction = CompactionSwitch(options.marcher.compact_below)

    # -- marching ------------------------------------------------------------------------
    def march(self, rays_o, rays_d, near: float, train: bool) -> tuple:
        """Training or inference samples: (packed_info, t_starts, t_ends, ray_idx), or a
        FixedSamples when training marches into fixed-capacity buffers."""
        opt = self.options.marcher
        cone = self._train_cone() if train else opt.cone_angle
        if not train and (view := view_cone_angle()) is not None:
            cone = max(cone, view)
        jitter = None
        if train:
            jitter = self.train_jitter
            if jitter is None or len(jitter) != len(rays_o):
                jitter = torch.rand(len(rays_o), device=rays_o.device)
        march = dict(
            near=near,
            cone_angle=cone,
            dt_min=opt.dt_min,
            max_samples=opt.max_samples,
            jitter=jitter,
            single_pass=opt.single_pass,
        )
        if train and self.sample_capacity is not None:
            return self._march_fixed(rays_o, rays_d, cone, march)
        return march_rays(rays_o, rays_d, self._aabb_host, self._grid_for(train), **march)

    def _grid_for(self, train: bool):
        """The grid a march reads: the training march's skips the carved cells."""
        return self.hidden.view() if train and self.hidden is not None else self.grid

    def _train_cone(self) -> float:
        opt = self.options.marcher
        if opt.early_cone_angle is not None and self.train_step < opt.early_steps:
            return opt.early_cone_angle
        return opt.cone_angle

    def graph_key(self) -> tuple | None:
        """What a captured training step bakes in from the sampler: (capacities, cone), or
        None while training marches into exactly sized buffers (not capturable)."""
        if self.sample_capacity is None:
            return None
        pruned = self.pruned_capacity  # compacting or not is in the key even before sizing
        cap = (self.prunes(), pruned and pruned.capacity)
        return (self.sample_capacity.capacity, cap, self._train_cone())

    def graph_state(self) -> dict:
        """What a captured training step reads and writes outside its own memory that the
        sampler replaces when the key changes: the fixed buffers (with their keys) and the
        capacities' running maxima. `set_graph_state` puts them back when a kept graph of
        that key replays again (`graph_step`), so it writes what the sampler reads."""
        caps = (self.sample_capacity, self.pruned_capacity)
        return {
            "fixed": (self._fixed_out, self._fixed_key),
            "pruned": (self._pruned_out, self._pruned_key),
            "max": [None if c is None else c.running_max for c in caps],
        }

    def set_graph_state(self, state: dict) -> None:
        """Make `state` (a `graph_state()`) the sampler's buffers and running maxima again."""
        self._fixed_out, self._fixed_key = state["fixed"]
        self._pruned_out, self._pruned_key = state["pruned"]
        for cap, t in zip((self.sample_capacity, self.pruned_capacity), state["max"], strict=True):
            if cap is not None and t is not None:
                cap.use_running_max(t)

    def use_fixed_capacity(self, on: bool) -> None:
        """March (and compact) training batches into fixed-capacity buffers (no host sync;
        `capacity.py`) or into exactly sized ones (the host reads the counts)."""
        self.sample_capacity = self._capacity() if on else None
        self.pruned_capacity = self._new_pruned_capacity()
        self._capacity_cone = None

    def _march_fixed(self, rays_o, rays_d, cone: float, march: dict):
        cap = self.sample_capacity
        if cap.capacity is None or cone != self._capacity_cone:
            # first batch, or the cone changed (the want jumps): size it once, exactly
            exact = march_rays(rays_o, rays_d, self._aabb_host, self._grid_for(True), **march)
            cap.reset(len(exact[1]))
            self._capacity_cone = cone
            if self.pruned_capacity is not None:
                self.pruned_capacity.reset()  # its want jumps too: sized at this batch
        key = (len(rays_o), cap.capacity)
        if self._fixed_out is None or self._fixed_key != key:
            self._fixed_out = empty_fixed_samples(len(rays_o), cap.capacity, rays_o.device)
            self._fixed_key = key
        fixed = march_rays_fixed(
            rays_o,
            rays_d,
            self._aabb_host,
            self._grid_for(True),
            capacity=cap.capacity,
            out=self._fixed_out,
            **march,
        )
        cap.observe(fixed.n_wanted)
        return fixed

    # -- compaction ----------------------------------------------------------------------
    def _capacity(self) -> SampleCapacity:
        opt = self.options.marcher
        return SampleCapacity(
            headroom=opt.capacity_headroom,
            shrink_below=opt.capacity_shrink_below,
            shrink_patience=opt.capacity_shrink_patience,
        )

    def _new_pruned_capacity(self) -> SampleCapacity | None:
        """The compacted samples' buffer: with fixed capacity, while compacting."""
        on = self.sample_capacity is not None and self.prunes()
        return self._capacity() if on else None

    def trained_slots(self) -> int | None:
        """Slots of the buffer the field trains on (padding included): the compacted buffer's
        while compacting, else the marched one's; None while buffers are exactly sized (the
        plain step) or the buffer is still to be sized at the next batch."""
        cap = self.pruned_capacity if self.prunes() else self.sample_capacity
        return None if cap is None else cap.capacity

    def _compaction_set(self) -> bool:
        opt = self.options.marcher
        return opt.early_stop_eps > 0 or opt.alpha_threshold > 0

    def prunes(self) -> bool:
        """Whether training compacts its marched samples now (`MarcherOptions.early_stop_eps`;
        with `compaction_auto`, while the switch says it pays)."""
        return self._compaction_set() and (self.compaction is None or self.compaction.on)

    def prune(self, rays_o, rays_d, marched, density: SigmaFn, with_src: bool = False):
        """The marched samples a training step trains on: those still visible by the density
        alone (kernels/prune.py), exactly sized or a FixedSamples as `marched` is; with_src,
        (those, src): each kept slot's marched slot, (S',) int32."""
        opt = self.options.marcher
        packed_info, t_starts, t_ends, ray_idx = marched[:4]
        x, _ = ray_points(rays_o, rays_d, 0.5 * (t_starts + t_ends), ray_idx, packed_info)
        sigma = density(x)  # every slot, a fixed buffer's padding too: never read
        args = (sigma, packed_info, t_starts, t_ends, opt.early_stop_eps, opt.alpha_threshold)
        if self.hidden is not None:
            self.hidden.tally(x, sigma, packed_info, t_starts, t_ends, opt.early_stop_eps)
        if not isinstance(marched, FixedSamples):
            out = prune_samples(*args, return_src=with_src)
            return (out[:4], out[4]) if with_src else out
        cap = self.pruned_capacity
        if cap.capacity is None:  # first batch: size it once, exactly
            cap.reset(len(prune_samples(*args)[1]))
        key = (len(rays_o), cap.capacity)
        if self._pruned_out is None or self._pruned_key != key:
            self._pruned_out = empty_fixed_samples(len(rays_o), cap.capacity, rays_o.device)
            self._pruned_key = key
        out = prune_samples_fixed(
            *args, capacity=cap.capacity, out=self._pruned_out, return_src=with_src
        )
        pruned = out[0] if with_src else out
        cap.observe(pruned.n_wanted)
        return out

    # -- occupancy -----------------------------------------------------------------------
    def update(self, step: int, density: SigmaFn) -> None:
        """Refresh the occupancy grid from `density` every `update_every` steps (instant-ngp's
        schedule; at step 0 and `update_offset` past each multiple), and the buffer sizes and
        the compaction switch with it."""
        self.train_step = step
        opt = self.options.occupancy
        if step and step % opt.update_every != opt.update_offset % opt.update_every:
            return
        for cap in (self.sample_capacity, self.pruned_capacity):
            if cap is not None:
                cap.refresh()
        if self.compaction is not None and self.compaction.refresh():
            self.pruned_capacity = self._new_pruned_capacity()  # sized anew at the next batch
        with torch.no_grad():
            self.grid.update(
                step,
                density,
                decay=opt.grid_decay,
                threshold=opt.density_threshold,
                warmup_steps=opt.warmup_steps,
            )
            if self.hidden is not None:  # not while the field is still fog
                self.hidden.update(carve=step >= opt.warmup_steps)
