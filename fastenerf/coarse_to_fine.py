"""Coarse-to-fine encodings for pose refinement (BARF, Lin et al. 2021).

Fine encoding levels give pose gradients that point every which way (the image is sharp at
the wrong place); BARF fades them in over part of training with a cosine window. Level k
gets weight w_k(α) = (1 − cos(π · clamp(α − k, 0, 1))) / 2 as α grows over the schedule.

- ngp: the hash grid's L levels; level 0 (the coarsest) is always on, α runs 1 → L;
- vanilla: the positional encoding's frequency bands (the raw x is always kept), α 0 → bands.
A field takes the weights as an attribute (`NGPField.level_weights`,
`PositionalEncoding.band_weights`); None means every level at full weight (no multiply).
While the schedule runs the attribute keeps one tensor whose values change in place, so a
captured training step (`graph_step`) reads each step's weights.
The weights act on the field's features (BARF, mode "field") or only on the gradient w.r.t.
the positions, the pose gradient's path (mode "gradient": the field learns every level from
the start; `fastenerf.fields.level_weights`).
"""

from __future__ import annotations

import functools
import math

import torch

from .fields.base import Field
from .fields.level_weights import MODES


def cosine_window(alpha: float, n: int, device=None) -> torch.Tensor:
    """(n,) float32 BARF weights of levels 0..n−1 at α (levels below α − 1 are 1).

    Computed on the host (float64, rounded once) and copied in one transfer: this runs every
    step of the schedule, where a device computation is ~7 launches. The last few are kept,
    so a repeated α (before the schedule starts, α stays at its first value) copies nothing;
    callers must not modify the tensor in place.
    """
    return _cosine_window(float(alpha), int(n), torch.device(device or "cpu"))


@functools.lru_cache(maxsize=4)
def _cosine_window(alpha: float, n: int, device: torch.device) -> torch.Tensor:
    w = [(1.0 - math.cos(math.pi * min(max(alpha - k, 0.0), 1.0))) / 2.0 for k in range(n)]
    on_cuda = device.type == "cuda"
    # pinned and non-blocking: a pageable host-to-device copy would wait for the device
    host = torch.tensor(w, dtype=torch.float32, pin_memory=on_cuda)
    return host.to(device, non_blocking=on_cuda)


def schedule_fraction(progress: float, start: float, end: float) -> float | None:
    """Where training is in the schedule, in [0, 1); None when it is over or off (end <= start)."""
    if end <= start:
        return None
    r = (progress - start) / (end - start)
    return None if r >= 1.0 else max(0.0, r)


def set_encoding_window(
    field: Field, progress: float, start: float, end: float, mode: str = "field"
) -> float | None:
    """Set the field's level weights for training `progress` in [0, 1]; returns the fraction
    of the schedule done (None once every level is on, or for a backend without levels).
    mode: "field" (BARF: the field sees the weighted levels) or "gradient" (only the gradient
    w.r.t. positions is weighted; `fastenerf.fields.level_weights`)."""
    if mode not in MODES:
        raise ValueError(f"set_encoding_window: mode must be one of {MODES}, got {mode!r}")
    r = schedule_fraction(progress, start, end)
    if field.backend == "ngp":
        n = field.grid_cfg.n_levels
        w = None if r is None else cosine_window(1 + r * (n - 1), n, _dev(field))
        field.level_weights = _in_place(field.level_weights, w)
        field.level_weights_mode = mode
    elif field.backend == "vanilla":
        n = len(field.pos_enc.freqs)
        w = None if r is None else cosine_window(r * n, n, _dev(field))
        field.pos_enc.band_weights = _in_place(field.pos_enc.band_weights, w)
        field.pos_enc.band_weights_mode = mode
    else:
        return None
    return r


def _in_place(current: torch.Tensor | None, w: torch.Tensor | None) -> torch.Tensor | None:
    """The weights `w` in the field's own tensor: `current` filled (a graph replays what it
    reads), a copy where there is none yet (`cosine_window`'s are cached and shared)."""
    if w is None:
        return None
    if current is None or current.shape != w.shape or current.device != w.device:
        return w.clone()
    return current.copy_(w)


def _dev(field: Field) -> torch.device:
    return field.aabb.device if hasattr(field, "aabb") else next(field.parameters()).device
