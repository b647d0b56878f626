"""Hidden cells (kernels/hidden_cells.py): the tally against a float64 walk, and carving that
drops the inside of a solid from the training march without losing one visible sample."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from fastenerf.kernels.hidden_cells import HiddenCells
from fastenerf.kernels.occupancy import OccupancyGrid
from fastenerf.kernels.prune import prune_samples
from fastenerf.kernels.ray_points import ray_points
from fastenerf.kernels.raymarch import march_rays

EPS = 1e-4
BOX = [-1.0, -1.0, -1.0, 1.0, 1.0, 1.0]


def cube_sigma(x: torch.Tensor, half: float = 0.45, sigma: float = 300.0) -> torch.Tensor:
    """A solid cube of side 2·half about the origin: sigma inside (1/world units), 0 outside."""
    return torch.where((x.abs() <= half).all(-1), sigma, 0.0).float()


def rays_around(n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """n rays (origins (n, 3) on a sphere of radius 3, unit directions (n, 3)) aimed at points
    near the origin, from every side."""
    g = torch.Generator().manual_seed(seed)
    o = torch.randn(n, 3, generator=g, dtype=torch.float64)
    o = 3.0 * o / o.norm(dim=-1, keepdim=True)
    aim = 0.6 * (torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5)
    d = aim - o
    return o.float(), (d / d.norm(dim=-1, keepdim=True)).float()


def solid_grid(res: int = 16) -> OccupancyGrid:
    grid = OccupancyGrid(BOX, res, 1, device="cpu")
    torch.manual_seed(0)  # the update's jittered points: the same grid whatever ran before
    grid.update(0, cube_sigma, warmup_steps=1)  # every cell measured once
    return grid


def marched(grid, o, d):
    """The march's samples, their points (S, 3) and densities (S,)."""
    info, t0, t1, ri = march_rays(o, d, BOX, grid, near=0.0, cone_angle=0.0)
    x, _ = ray_points(o, d, 0.5 * (t0 + t1), ri, info)
    return (info, t0, t1, ri), x, cube_sigma(x)


def reference_tally(x, sigma, info, t0, t1, res: int):
    """hits, seen per cell (n_cells,) int64 by a float64 walk of each ray's slice."""
    hits = np.zeros(res**3, np.int64)
    seen = np.zeros(res**3, np.int64)
    x, sigma = x.double().numpy(), sigma.double().numpy()
    dt = (t1 - t0).double().numpy()
    for first, n in info.tolist():
        T = 1.0
        for s in range(first, first + n):
            q = np.clip(np.floor((x[s] + 1.0) * 0.5 * res).astype(int), 0, res - 1)
            gid = (q[0] * res + q[1]) * res + q[2]
            hits[gid] += 1
            seen[gid] += T >= EPS
            T *= math.exp(-sigma[s] * dt[s])
    return hits, seen


def test_tally_counts_every_cells_samples_and_the_visible_ones_as_a_float64_walk():
    grid = solid_grid()
    o, d = rays_around(300, seed=1)
    (info, t0, t1, _), x, sigma = marched(grid, o, d)
    hidden = HiddenCells(grid, min_hits=1, refresh=8)
    hidden.tally(x, sigma, info, t0, t1, EPS)
    hits, seen = reference_tally(x, sigma, info, t0, t1, grid.resolution)
    assert hits.sum() == len(t0) > 0 and seen.sum() < hits.sum()  # some samples are hidden
    np.testing.assert_array_equal(hidden.hits.numpy(), hits)
    np.testing.assert_array_equal(hidden.seen.numpy(), seen)


def test_carving_drops_the_inside_of_a_solid_and_keeps_every_visible_sample():
    """The training march with carved cells marches far fewer samples, and compaction keeps
    exactly the same ones on the same rays: no visible sample is lost. The grid itself (what
    evaluation and the mesh read) keeps the solid's inside."""
    grid = solid_grid()
    o, d = rays_around(2000, seed=2)
    (info, t0, t1, _), x, sigma = marched(grid, o, d)
    hidden = HiddenCells(grid, min_hits=4, refresh=8)
    hidden.tally(x, sigma, info, t0, t1, EPS)
    hidden.update()
    assert hidden.carved.any()
    (info_c, t0_c, t1_c, _), _, sigma_c = marched(hidden.view(), o, d)
    assert len(t0_c) < 0.7 * len(t0)  # the cube's inside is no longer marched
    full = prune_samples(sigma, info, t0, t1, EPS)
    carved = prune_samples(sigma_c, info_c, t0_c, t1_c, EPS)
    assert torch.equal(full[0][:, 1], carved[0][:, 1])  # the same count kept on every ray
    assert torch.equal(full[1], carved[1]) and torch.equal(full[2], carved[2])
    centre = torch.zeros(1, 3)
    assert grid.occupied(centre).item()  # the grid still holds the solid
    assert not OccupancyGrid.occupied(hidden.view(), centre).item()  # the training bits not


def test_carved_cells_are_cleared_every_refresh_and_while_the_field_is_fog():
    grid = solid_grid()
    o, d = rays_around(1000, seed=3)
    (info, t0, t1, _), x, sigma = marched(grid, o, d)

    def carve_once(hidden, carve=True):
        hidden.tally(x, sigma, info, t0, t1, EPS)
        hidden.update(carve)
        return int(hidden.carved.sum())

    hidden = HiddenCells(grid, min_hits=1, refresh=3)
    first = carve_once(hidden)  # update 1 carves
    assert first > 0 and carve_once(hidden) == first  # update 2: the counts ran on, same cells
    assert carve_once(hidden) == 0  # update 3 is a refresh: cleared, counts reset
    assert hidden.hits.sum() == 0 and hidden.seen.sum() == 0
    assert carve_once(hidden) == first
    slow = HiddenCells(grid, min_hits=2 * int(hidden.hits.max()), refresh=8)
    assert carve_once(slow) == 0 and carve_once(slow) > 0  # two windows' hits add up
    assert carve_once(HiddenCells(grid, 1, 8), carve=False) == 0  # fog: nothing carved
    assert carve_once(HiddenCells(grid, 10**6, 8)) == 0  # too few hits to judge
    with pytest.raises(ValueError, match="min_hits and refresh"):
        HiddenCells(grid, 0, 8)


@pytest.mark.parametrize("compact", [False, True])
def test_the_option_builds_hidden_cells_only_with_compaction(compact):
    from fastenerf.backends import MarcherOptions, NGPOptions
    from fastenerf.fields.occupancy_sampler import OccupancySampler

    marcher = MarcherOptions(carve_hidden=True, early_stop_eps=1e-4 if compact else 0.0)
    sampler = OccupancySampler(BOX, NGPOptions(marcher=marcher), None, torch.device("cpu"))
    assert (sampler.hidden is not None) == compact
    default = OccupancySampler(BOX, NGPOptions(), None, torch.device("cpu"))
    assert default.hidden is None and default._grid_for(True) is default.grid
