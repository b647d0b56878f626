"""Runaway pose rows put back (`refine_reset_deg`, #20).

A pose row whose correction has turned far past anything the rest need is a view whose
events, rendered through the wrong pose, pull it further still (gpu_s53: one of lattice's
1,000 rows at 1° went 0.3° → 3.7° → 9.5° in 9 s while the others stayed under 0.3°). Putting
it back to no correction, its optimiser state cleared, gives it the given pose (the prior's,
after `smooth_poses`) and a fresh start. In place and without a host read: the step's captured
graph keeps reading the same buffers.
"""

from __future__ import annotations

import torch


@torch.no_grad()
def reset_runaways(delta: torch.Tensor, state: dict, max_turn_rad: float) -> torch.Tensor:
    """Zero the rows of `delta` (G, k) [rotation vector (rad), shift (world units)] whose
    turn exceeds `max_turn_rad`, and the same rows of every (G, ·) tensor in `state` (the
    optimiser's moments, row step counts, gate averages); returns how many (0-dim device
    tensor)."""
    bad = delta[:, :3].norm(dim=-1) > max_turn_rad
    keep = (~bad)[:, None]
    delta.mul_(keep.to(delta.dtype))
    for v in state.values():
        if torch.is_tensor(v) and v.dim() == 2 and v.shape[0] == delta.shape[0]:
            v.mul_(keep.to(v.dtype))
    return bad.sum()
