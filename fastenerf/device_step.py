"""A training step the device paces: no host round trip per step (issue #17).

The plain step reads the loss on the host (`float(loss)`) to decide whether to update, which
makes the host wait for the whole step every step. Here that decision stays on the device:

- `FiniteGuard` flags a non-finite loss or gradient into a 0-dim device tensor and hands it to
  the optimiser as `found_inf`, the way `torch.amp.GradScaler` does: torch's fused Adam then
  skips the update (its step count included) on the device. Consecutive and total skips are
  counted on the device too.
- `PendingStats` keeps the step's statistics as device tensors and brings them to the host in
  one copy every few steps (or when a hook asks), not one `float()` per value per step.

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

    `add(stats)` keeps the dict; `flush()` copies every pending tensor value to the host in one
    transfer and replaces it in place by a Python float, so every holder of the dict (hooks,
    the trainer's history) sees floats afterwards. Returns the flushed dicts, oldest first.
    """

    def __init__(self):
        self.pending: list[dict[str, Any]] = []

    def __len__(self) -> int:
        return len(self.pending)

    def add(self, stats: dict[str, Any]) -> None:
        self.pending.append(stats)

    def flush(self, extra: list[torch.Tensor] | None = None) -> tuple[list[dict], list[float]]:
        """Bring pending values (and `extra` 0-dim tensors) to the host in one copy.

        Returns (the flushed dicts, the extra tensors' values).
        """
        slots, values = [], []
        for d in self.pending:
            for k, v in d.items():
                if isinstance(v, torch.Tensor):
                    slots.append((d, k))
                    values.append(device_scalar(v))
        values += [device_scalar(e) for e in extra or []]
        host = torch.stack(values).tolist() if values else []
        for (d, k), v in zip(slots, host, strict=False):
            d[k] = v
        done, self.pending = self.pending, []
        return done, host[len(slots) :]


def device_scalar(v: torch.Tensor) -> torch.Tensor:
    """v (one value) as a 0-dim float32 tensor without a gradient: v itself where it already
    is one (the usual stat: no op dispatched for it, at the step or at the flush)."""
    if v.dtype == torch.float32 and v.ndim == 0 and not v.requires_grad:
        return v
    return v.detach().float().reshape(())
