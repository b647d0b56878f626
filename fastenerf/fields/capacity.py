"""How many sample slots a training step's fixed-capacity march gets (issue #17).

`march_rays_fixed` writes into buffers of a capacity fixed by the caller, so nothing waits for
the device to learn how many samples a batch has. The capacity follows what the marcher wanted:
every step's `n_wanted` goes into a running maximum on the device; at each occupancy update the
host starts a non-blocking copy of that maximum and, at the next update, reads the copy that has
long arrived. The capacity then becomes the maximum times `headroom`, rounded up to `quantum`
slots (so it changes rarely), and shrinks only once the want falls well below it (optionally
for several updates in a row: each change recaptures the training step's CUDA graph).

A step whose batch wants more than the capacity loses the rays that do not fit (the marcher
flags them; the loss leaves their pixels out and the trainer reports the share): never silently.
"""

from __future__ import annotations

import collections
import math

import torch


class LaggedRead:
    """A device tensor read on the host one call late, so the host never waits for it.

    `start(t)` queues a non-blocking copy of `t` (in stream order: what `t` holds once the work
    queued so far has run); `take()` returns that copy once it has arrived, and only once.
    """

    def __init__(self):
        self._host: torch.Tensor | None = None
        self._ready: torch.cuda.Event | None = None
        self._fresh = False  # a copy was started and not yet taken

    def busy(self) -> bool:
        """A copy is still in flight."""
        return self._fresh and self._ready is not None and not self._ready.query()

    def take(self) -> torch.Tensor | None:
        """The copy started last, on the host, if it has arrived and was not taken; else None."""
        if not self._fresh or self.busy():
            return None
        self._fresh = False
        return self._host

    def start(self, t: torch.Tensor) -> None:
        """Queue a copy of `t` to the host (pinned memory on CUDA)."""
        on_cuda = t.device.type == "cuda"
        if self._host is None or self._host.shape != t.shape or self._host.dtype != t.dtype:
            self._host = torch.empty_like(t, device="cpu", pin_memory=on_cuda)
        self._host.copy_(t, non_blocking=on_cuda)
        self._ready = None
        if on_cuda:
            self._ready = torch.cuda.Event()
            self._ready.record()
        self._fresh = True


class SampleCapacity:
    """Sample-buffer capacity of a training march: a Python int the host never waits for.

    quantum: capacities are multiples of it (samples); headroom: capacity / observed maximum;
    shrink_below: the capacity shrinks when the largest of the last `shrink_patience`
    readings (each the maximum want since the update before) falls below this share of it,
    to that reading's size, and only by `min_shrink` quanta or more. Growing is at once.
    """

    # Growing back by one quantum then needs the want to rise a whole quantum: with 1, a want
    # near a quantum's edge shrinks and grows the buffer (and recaptures the step) at every
    # refresh (benchmarks/RESULTS.md, twenty-eighth session).
    min_shrink = 2
    # The host readings kept for the run's record until someone takes them (the error-vs-time
    # curve points do): at 16 steps a reading, well over an hour of a GPU run between points.
    keep_readings = 1 << 14

    def __init__(
        self,
        quantum: int = 1 << 15,
        headroom: float = 1.1,
        shrink_below: float = 0.85,
        shrink_patience: int = 1,
    ):
        self.quantum, self.headroom, self.shrink_below = int(quantum), headroom, shrink_below
        self.shrink_patience = int(shrink_patience)
        self.capacity: int | None = None  # None: size the next march exactly (one host read)
        self._max: torch.Tensor | None = None  # device running max of n_wanted
        self._read = LaggedRead()  # its copy on the host, maybe in flight
        self._recent: collections.deque[int] = collections.deque(maxlen=self.shrink_patience)
        self._readings: collections.deque[int] = collections.deque(maxlen=self.keep_readings)

    def size_for(self, wanted: int) -> int:
        """The capacity for a want of `wanted` samples: headroom, rounded up to the quantum."""
        q = self.quantum
        return max(q, int(math.ceil(wanted * self.headroom / q)) * q)

    def reset(self, wanted: int | None = None) -> None:
        """Forget the history; size from `wanted` (an exact count) or at the next march."""
        self.capacity = None if wanted is None else self.size_for(wanted)
        self._max, self._read = None, LaggedRead()
        self._recent = collections.deque(maxlen=self.shrink_patience)

    @property
    def running_max(self) -> torch.Tensor | None:
        """The device running maximum `observe` folds into (a captured step writes this very
        tensor), or None before the first march."""
        return self._max

    def use_running_max(self, t: torch.Tensor) -> None:
        """Fold into `t` from now on (the running maximum a kept CUDA graph writes, when its
        step is replayed again: `graph_step`); refresh reads and zeroes it as its own."""
        self._max = t

    def observe(self, n_wanted: torch.Tensor) -> None:
        """Fold a march's (1,) int32 device count into the running maximum (no host read)."""
        if self._max is None:
            self._max = n_wanted.detach().clone()
        else:
            torch.maximum(self._max, n_wanted, out=self._max)

    def refresh(self) -> None:
        """Apply the maximum copied at the previous call (if it has arrived), start a new copy."""
        if self._max is None or self._read.busy():
            return  # nothing seen yet, or the last copy is in flight: keep the maximum growing
        got = self._read.take()
        if got is not None:
            self.apply(int(got.item()))
        # in stream order: copy the maximum since the last copy, then start a new one
        self._read.start(self._max)
        self._max.zero_()

    def take_readings(self) -> list[int]:
        """The readings applied since the last call, oldest first (at most `keep_readings`),
        and forget them: what the capacity followed, for replaying other rules offline."""
        out = list(self._readings)
        self._readings.clear()
        return out

    def apply(self, wanted: int) -> None:
        """Size for one reading: the most samples a march wanted since the update before (a
        host int; `refresh` reads it from the device one update late)."""
        self._readings.append(wanted)
        self._recent.append(wanted)
        if self.capacity is None or wanted > self.capacity / self.headroom:
            self.capacity = self.size_for(wanted)
            return
        if len(self._recent) < self._recent.maxlen:
            return
        high = max(self._recent)
        smaller = self.size_for(high)
        if high < self.shrink_below * self.capacity and (
            smaller <= self.capacity - self.min_shrink * self.quantum
        ):
            self.capacity = smaller
