"""Which rows of a parameter table a backward pass wrote gradient into (for a row-sparse
optimiser, `fastenerf.optim.RowSparseAdam`).

A hash-grid step reads a few thousand rows of a table of up to millions; finding them again in
the dense gradient (a nonzero search over rows × features floats) costs a pass over the whole
gradient. Instead the hash grid's backward kernel marks each row it scatters into in a one-byte
mask (`mask[row] = 1`, a plain store: every writer stores the same value). `take()` lists the
marked rows in increasing order (so the optimiser's gathers and scatters walk the table
forwards) and clears the mask: a scan of one byte per row, a small fraction of one pass of
dense Adam (which reads and writes ~40 bytes per row several times).

A tracker is attached to the table tensor itself (`track_rows`); `hash_grid_encode` marks into
the tracker of the table it is given, when it has one.
"""

from __future__ import annotations

import torch

ATTR = "_fastenerf_row_tracker"


class RowTracker:
    """Rows of a (n_rows, F) table written by the backward passes since the last `take()`.

    mask: (n_rows,) uint8 on the table's device, 1 for a written row; `passes`: backward
    passes that marked rows since the last `take()`.
    """

    def __init__(self, n_rows: int, device: torch.device | str):
        self.n_rows = int(n_rows)
        self.mask = torch.zeros(self.n_rows, dtype=torch.uint8, device=device)
        self.passes = 0

    def take(self) -> torch.Tensor:
        """The marked rows, (K,) int64 increasing, and a clear mask for the next step."""
        rows = torch.nonzero(self.mask)[:, 0] if self.passes else self.mask.new_zeros(0).long()
        if self.passes:
            self.mask.zero_()
        self.passes = 0
        return rows

    def clear(self) -> None:
        """Forget what was marked (a backward whose step was not taken)."""
        self.take()

    def to(self, device) -> RowTracker:
        self.mask = self.mask.to(device)
        return self


def track_rows(table: torch.Tensor) -> RowTracker:
    """The tracker of `table` (rows = its first dimension), created and attached on first use."""
    tracker = getattr(table, ATTR, None)
    if tracker is None or tracker.n_rows != table.shape[0]:
        tracker = RowTracker(table.shape[0], table.device)
        setattr(table, ATTR, tracker)
    elif tracker.mask.device != table.device:
        tracker.to(table.device)
    return tracker


def tracker_of(table: torch.Tensor) -> RowTracker | None:
    """The tracker attached to `table` (None if untracked or on another device)."""
    tracker = getattr(table, ATTR, None)
    if tracker is None or tracker.mask.device != table.device:
        return None
    return tracker
