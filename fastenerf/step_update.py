"""A step's update: the backward, the optimiser's step and the skip of a non-finite one.

The field's parameters and the self-calibration's (poses, thresholds) step together, and a
non-finite loss or gradient skips the update of both. `update_plain` lets the host decide: it
reads the loss, so the step waits for the device. `update_on_device` leaves the decision on the
device (`device_step.FiniteGuard` arms the fused Adam); the host learns of it from the guard's
counters at the next stats flush. The named ranges are what `benchmarks.profile_step`
attributes time to.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch
from torch.profiler import record_function

from .device_step import FiniteGuard

if TYPE_CHECKING:
    from .self_calibration import SelfCalibration


def update_plain(
    loss: torch.Tensor, optimizer: torch.optim.Optimizer, selfcal: SelfCalibration | None
) -> float:
    """Backward and step unless the loss is not finite (it then never reaches the weights);
    returns the loss as a host float."""
    loss_value = float(loss.detach())
    if math.isfinite(loss_value):
        with record_function("backward"):
            loss.backward()
        with record_function("optimizer"):
            optimizer.step()
            if selfcal is not None:
                selfcal.step()
    return loss_value


def update_on_device(
    loss: torch.Tensor,
    optimizer: torch.optim.Optimizer,
    guard: FiniteGuard,
    selfcal: SelfCalibration | None,
) -> torch.Tensor:
    """Backward and step; the fused Adam (and the calibration) skip on a non-finite loss or
    gradient, as `guard` flags it. Returns the loss, a 0-dim device tensor."""
    with record_function("backward"):
        loss.backward()
    with record_function("optimizer"):
        found_inf = guard.check(loss, optimizer)
        optimizer.step()
        if selfcal is not None:
            selfcal.step(found_inf)
    return loss.detach()
