"""A training step the device paces: no host round trip per step (issue #17).

The plain step reads the loss on the host (`float(loss)`) to decide whether to update, which
makes the host wait for the whole step every step. Here that decision stays on the device:

- `FiniteGuard` flags a non-finite loss or gradient into a 0-dim device tensor and hands it to
  the optimiser as `found_inf`, the way `torch.amp.GradScaler` does: torch's fused Adam then
  skips the update (its step count included) on the device. Consecutive and total skips are
  counted on the device too.
- `PendingStats` keeps the step's statistics as device tensors and brings them to the host in
  one copy every few steps (or when a hook asks), not one `float()` per value per step; the
  trainer's own flushes start that copy and read it one flush later, never waiting for it.

The decision (update or not) and every number are the same as the plain step's; only when the
host learns them changes. The trainer uses this path where the optimiser is a fused torch Adam
(`supports_device_guard`).
"""

from __future__ import annotations

from typing import Any

import torch


def supports_device_guard(optimizer: torch.optim.Optimizer) -> bool:
    """True for a torch Adam/AdamW built with fused=True (they honour `found_inf`)."""
    fused = all(bool(g.get("fused")) for g in optimizer.param_groups)
    return fused and isinstance(optimizer, torch.optim.Adam | torch.optim.AdamW)


class FiniteGuard:
    """Device-side "skip this update" flag for a fused torch optimiser.

    params: the parameters whose gradients are checked; device: theirs.
    Counters (0-dim float32 device tensors): run (consecutive non-finite steps), skipped (all).
    """

    def __init__(self, params: list[torch.nn.Parameter], device: torch.device):
        self.params = list(params)
        self.found_inf = torch.zeros((), device=device)
        self.one = torch.ones((), device=device)
        self.run = torch.zeros((), device=device)
        self.skipped = torch.zeros((), device=device)

    def check(self, loss: torch.Tensor, optimizer: torch.optim.Optimizer) -> torch.Tensor:
        """After backward: flag a non-finite loss or gradient; arm `optimizer` to skip on it.

        Returns found_inf (0-dim, 1.0 = skip); the counters are updated in place.
        """
        torch.logical_not(torch.isfinite(loss), out=self.found_inf)  # 1.0: not finite
        grads = [p.grad for p in self.params if p.grad is not None]
        if grads:
            # sets found_inf to 1 (never adds) on any inf/NaN, so it stays 0 or 1; scaling by
            # one leaves the gradients alone
            torch._amp_foreach_non_finite_check_and_unscale_(grads, self.found_inf, self.one)
        optimizer.found_inf = self.found_inf
        optimizer.grad_scale = None
        self.run.add_(self.found_inf).mul_(self.found_inf)
        self.skipped.add_(self.found_inf)
        return self.found_inf

    def disarm(self, optimizer: torch.optim.Optimizer) -> None:
        """Forget the flag (a later plain step must not read a stale one)."""
        optimizer.found_inf = None


class PendingStats:
    """Steps' stats dicts whose tensor values are still on the device.

    `add(stats)` keeps the dict. `flush()` copies every pending tensor value to the host in one
    transfer and replaces it in place by a Python float, so every holder of the dict (hooks,
    the trainer's history) sees floats afterwards. `start()` begins that copy without waiting
    (pinned memory, an event on CUDA) and `collect()` finishes it once it has arrived: a flush
    every few steps then never waits for the steps still queued, which would leave the device
    idle while the host draws the next batches. On a CPU the copy is done at `start()`.
    """

    def __init__(self):
        self.pending: list[dict[str, Any]] = []
        self._flight: tuple | None = None  # (dicts, slots, host values, event, n_extra)

    def __len__(self) -> int:
        return len(self.pending)

    @property
    def in_flight(self) -> bool:
        return self._flight is not None

    def add(self, stats: dict[str, Any]) -> None:
        self.pending.append(stats)

    def start(self, extra: list[torch.Tensor] | None = None) -> None:
        """Start the copy of the pending values (and `extra` 0-dim tensors); one at a time."""
        assert self._flight is None, "collect the copy in flight first"
        slots, values = [], []
        for d in self.pending:
            for k, v in d.items():
                if isinstance(v, torch.Tensor):
                    slots.append((d, k))
                    values.append(device_scalar(v))
        values += [device_scalar(e) for e in extra or []]
        host, event = torch.zeros(0), None
        if values:
            row = torch.stack(values)
            on_cuda = row.device.type == "cuda"
            host = torch.empty(row.shape, dtype=row.dtype, pin_memory=on_cuda)
            host.copy_(row, non_blocking=on_cuda)
            if on_cuda:
                event = torch.cuda.Event()
                event.record()
        self._flight = (self.pending, slots, host, event, len(extra or []))
        self.pending = []

    def collect(self, wait: bool = True) -> tuple[list[dict], list[float]] | None:
        """Finish the copy in flight: (its dicts, floats in place; the extra values), or None
        when there is none or (wait=False) it has not arrived."""
        if self._flight is None:
            return None
        done, slots, host, event, n_extra = self._flight
        if event is not None:
            if not wait and not event.query():
                return None
            event.synchronize()
        vals = host.tolist()
        for (d, k), v in zip(slots, vals, strict=False):
            d[k] = v
        self._flight = None
        return done, vals[len(vals) - n_extra :] if n_extra else []

    def rotate(self, extra: list[torch.Tensor] | None = None) -> tuple | None:
        """The every-few-steps flush: finish the copy started last time if it has arrived
        (returned as `collect` does; None: nothing yet, keep gathering), then start the next."""
        got = None
        if self._flight is not None:
            got = self.collect(wait=False)
            if got is None:
                return None
        self.start(extra)
        return got

    def flush(self, extra: list[torch.Tensor] | None = None) -> tuple[list[dict], list[float]]:
        """Bring every pending value (and `extra`) to the host now, the copy in flight first.

        Returns (the flushed dicts, oldest first; the extra tensors' values).
        """
        before = self.collect(wait=True)
        self.start(extra)
        done, vals = self.collect(wait=True)
        return (before[0] + done if before else done), vals


def device_scalar(v: torch.Tensor) -> torch.Tensor:
    """v (one value) as a 0-dim float32 tensor without a gradient: v itself where it already
    is one (the usual stat: no op dispatched for it, at the step or at the flush)."""
    if v.dtype == torch.float32 and v.ndim == 0 and not v.requires_grad:
        return v
    return v.detach().float().reshape(())
