"""Whether a training step compacts its samples: on only while it pays (issue #17).

Compaction (`MarcherOptions.early_stop_eps`) runs the density network alone over every marched
sample, then the full field forward and backward over the samples compositing will use. The
pre-pass costs about a third of a sample's full pass, so compaction pays where compositing uses
well under ~70 % of the marched samples (an opaque scene, or the fog of a new field) and costs
where it uses most of them (an event-trained field that stays semi-transparent).

`CompactionSwitch` measures that share on the training renders themselves, compacting or not:
the samples compositing used are those with a non-zero weight (a ray's compositing stops where
its transmittance falls below 1e-4, which is what compaction at 1e-4 keeps), over the samples
marched. The sums stay on the device; `refresh` (at the occupancy updates) reads the sums copied
at the previous refresh (`LaggedRead`) and switches with a hysteresis band, so a share near the
threshold does not flip the step (and its CUDA graph) back and forth.
"""

from __future__ import annotations

import torch

from .capacity import LaggedRead

BAND = 0.05  # hysteresis: on below `below - BAND`, off above `below + BAND`


class CompactionSwitch:
    """On/off state of compaction, from the share of marched samples compositing uses.

    below: the share under which compaction pays (0..1); on: the state before any reading
    (on: a new field's fog stops rays early).
    """

    def __init__(self, below: float, on: bool = True):
        self.below, self.on = float(below), bool(on)
        self.share: float | None = None  # the last share read (None: none yet)
        self.switches = 0  # times the state changed
        self._sums: torch.Tensor | None = None  # (2,) float64 device: used, marched
        self._read = LaggedRead()

    def observe(self, weights: torch.Tensor, n_marched: int | torch.Tensor) -> None:
        """Add one render's samples with a non-zero weight (`weights`: (S,) float32, padding
        slots 0) and its marched samples (a Python int or a 0-dim device count) to the sums;
        no host read, and nothing allocated after the first call (capturable)."""
        with torch.no_grad():
            if self._sums is None:
                self._sums = torch.zeros(2, dtype=torch.float64, device=weights.device)
            self._sums[0].add_(torch.count_nonzero(weights))
            self._sums[1].add_(n_marched)

    def refresh(self) -> bool:
        """Read the sums copied at the previous call (if arrived), switch, copy the new sums.
        Returns whether the state changed."""
        if self._sums is None or self._read.busy():
            return False
        got = self._read.take()
        changed = False
        if got is not None and float(got[1]) > 0:
            self.share = float(got[0]) / float(got[1])
            want = self.share < self.below + (BAND if self.on else -BAND)
            changed, self.on = want != self.on, want
            self.switches += int(changed)
        self._read.start(self._sums)
        self._sums.zero_()
        return changed
