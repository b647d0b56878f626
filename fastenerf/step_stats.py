"""A training step's statistics: the dict each step returns, which hooks and metrics.jsonl see.

`step_stats` builds it from the step's batch, render and loss parts; `append_history` keeps
it in a trainer's bounded history. On the device-paced path (`device_step`) its values stay
0-dim device tensors until a flush, every STATS_FLUSH_EVERY steps, brings them to the host.
"""

from __future__ import annotations

from typing import Any

import torch

from .device_step import device_scalar
from .sampling import RayBatch

HISTORY_MAX = 100_000
# Device-paced steps: the stats come to the host every this many steps (one copy for all), so
# the divergence guard learns of non-finite losses at most this late (its patience is larger).
STATS_FLUSH_EVERY = 16


def step_stats(
    batch: RayBatch,
    out: dict[str, Any],
    parts: dict[str, torch.Tensor],
    loss: float | torch.Tensor,
    lr: float,
    dt: float,
    step: int,
    elapsed: float,
    on_device: bool,
) -> dict[str, Any]:
    """The stats of step `step` (counted from 1): loss, rays (rendered: two a pixel),
    rays_per_s (over the step's `dt` seconds), elapsed_s (the training clock, s), lr,
    positive_fraction (share of event pixels), the loss's `parts`, and samples_per_ray /
    marched_per_ray where the render `out` counts them. on_device: tensor values stay 0-dim
    float32 device tensors, else Python floats."""
    host = device_scalar if on_device else float
    n_rays = int(batch.rays_o.shape[0])
    positive = batch.positive_share
    positive = batch.positive.float().mean() if positive is None else positive
    stats = {
        "step": step,
        "loss": loss,
        "rays": n_rays,
        "rays_per_s": n_rays / max(dt, 1e-9),
        "elapsed_s": elapsed,
        "lr": lr,
        "positive_fraction": host(positive),
        **{k: host(v) for k, v in parts.items()},
    }
    # the samples the field ran on, and the marched ones where compaction kept fewer
    for key, name in (("n_samples", "samples_per_ray"), ("n_marched", "marched_per_ray")):
        if key in out:
            n = out[key]
            n = float(n) if torch.is_tensor(n) and not on_device else n
            stats[name] = n / n_rays  # a device count: one division, int32 -> float32
    return stats


def append_history(history: list[dict], stats: dict, skipped_steps: int) -> None:
    """Append a step's host-side `stats` to `history`, marked with the run's skipped steps
    where there are any; the oldest half goes once it holds more than HISTORY_MAX."""
    if skipped_steps:
        stats["skipped_steps"] = skipped_steps
    history.append(stats)
    if len(history) > HISTORY_MAX:
        del history[: HISTORY_MAX // 2]
