"""Pixels per step from a target of samples per step (`samples_per_step`, issue #17).

DESIGN §4 names ~256 k samples a training step on a GPU (instant-ngp's rule: the rays a step
draws follow the samples per ray the occupancy grid leaves), where a fixed number of pixels
(two rays each, at t0 and t1) trains on as many samples as the grid leaves them: few once it
is carved and many more while the field is fog. `BatchSize` sets the pixels per step so that
2 x pixels x samples per ray ≈ target:

    pixels = clamp(round(target / (2 · samples_per_ray) / QUANTUM) · QUANTUM, lo, hi)

- The sampler draws `block` steps' batches at once, so the size changes only where a block is
  drawn (`decide`), from the mean samples per ray of the block LAG blocks back: the device-paced
  step's stats reach the host up to two flushes late, and a decision made from data both a run
  and its resume hold is the same in both (the per-block sums are in the checkpoint).
- Sizes are multiples of QUANTUM pixels and move only when off by more than HYSTERESIS: every
  new size is a new CUDA-graph capture and new sample buffers.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

QUANTUM = 1024
"""Pixels: the sizes a run steps through (a few graph captures, not one per block)."""
HYSTERESIS = 0.2
"""A new size only where the wanted one is off by more than this fraction."""


def pixels_for(target: float, samples_per_ray: float, lo: int, hi: int) -> int:
    """Pixels per step whose rays (two a pixel) make ~`target` samples at `samples_per_ray`,
    a multiple of QUANTUM within [lo, hi]."""
    ideal = target / (2.0 * max(samples_per_ray, 1e-6))
    n = int(round(ideal / QUANTUM)) * QUANTUM
    return min(hi, max(lo, n))


def lag_blocks(block: int, flush_every: int) -> int:
    """Blocks between the one a decision reads and the one it sizes: step stats arrive up to
    two flushes of `flush_every` steps late, plus one block of margin."""
    return math.ceil(2 * flush_every / block) + 2


class BatchSize:
    """The pixels per step a run's sampler draws (see the module docstring).

    target: samples per step; lo, hi: the fewest and most pixels per step (hi: the config's
    rays_per_step, what the memory check allowed); block: steps drawn at once (the sampler's
    prefetch); lag: blocks between a decision and the block it reads (`lag_blocks`).
    """

    def __init__(self, target: int, lo: int, hi: int, block: int, lag: int):
        if not (0 < lo <= hi) or block < 1 or lag < 1:
            raise ValueError(f"BatchSize: bad bounds {lo}, {hi}, block {block}, lag {lag}")
        self.target, self.lo, self.hi = float(target), int(lo), int(hi)
        self.block, self.lag = int(block), int(lag)
        self.sums: dict[int, list[float]] = {}  # block -> [sum of samples per ray, steps]

    def observe(self, stats: Iterable[dict]) -> None:
        """Take host-side step stats ("step", counted from 1, and "samples_per_ray")."""
        for s in stats:
            spr = s.get("samples_per_ray")
            if spr is None or not math.isfinite(float(spr)):
                continue
            entry = self.sums.setdefault((int(s["step"]) - 1) // self.block, [0.0, 0])
            entry[0] += float(spr)
            entry[1] += 1

    def decide(self, steps_done: int, pixels: int) -> int | None:
        """At the block that starts after `steps_done` steps: its pixels per step, or None to
        keep `pixels` (the block LAG back not measured, or the size within HYSTERESIS)."""
        src = steps_done // self.block - self.lag
        for b in [b for b in self.sums if b < src]:  # read once: never needed again
            del self.sums[b]
        entry = self.sums.get(src)
        if entry is None or entry[1] == 0:
            return None
        n = pixels_for(self.target, entry[0] / entry[1], self.lo, self.hi)
        return n if abs(n - pixels) > HYSTERESIS * pixels else None

    def state_dict(self) -> dict:
        return {"sums": {str(b): list(v) for b, v in self.sums.items()}}

    def load_state_dict(self, state: dict) -> None:
        self.sums = {int(b): [float(v[0]), int(v[1])] for b, v in state["sums"].items()}
