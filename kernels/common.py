"""Shared Warp plumbing: initialisation, device mapping, zero-copy tensor views."""

from __future__ import annotations

import functools

import torch
import warp as wp


@functools.cache
def init() -> None:
    """Initialise Warp once, quietly."""
    wp.config.quiet = True
    wp.init()


def device_of(t: torch.Tensor) -> str:
    """The Warp device string for a torch tensor ("cpu" or "cuda:N")."""
    init()
    if t.device.type == "cuda":
        return f"cuda:{t.device.index or 0}"
    return "cpu"


def to_wp(t: torch.Tensor, dtype=None, requires_grad: bool = False) -> wp.array:
    """Zero-copy Warp view of a contiguous torch tensor (no gradient tracking by Warp)."""
    init()
    if not t.is_contiguous():
        raise ValueError("to_wp needs a contiguous tensor")
    return wp.from_torch(t, dtype=dtype, requires_grad=requires_grad)


def stream_of(t: torch.Tensor):
    """Warp stream matching torch's current CUDA stream (None on CPU)."""
    if t.device.type != "cuda":
        return None
    return wp.stream_from_torch(torch.cuda.current_stream(t.device))
