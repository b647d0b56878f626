"""Timing helpers shared by the kernel benchmarks (DESIGN §8: medians, warm-up excluded)."""

from __future__ import annotations

import statistics
import time

import torch


def time_ms(fn, device: str, repeats: int, warmup: int = 3, inner: int = 1) -> float:
    """Median time per fn() call in ms.

    On CUDA, `inner` calls are queued back to back between two events (so the host's launch
    overhead overlaps the GPU work, as in a training loop) and the median over `repeats` such
    batches is divided by `inner`. On the CPU each call is timed with the wall clock.
    """
    for _ in range(warmup):
        fn()
    times = []
    if str(device).startswith("cuda"):
        torch.cuda.synchronize()
        for _ in range(repeats):
            a, b = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            a.record()
            for _ in range(inner):
                fn()
            b.record()
            b.synchronize()
            times.append(a.elapsed_time(b) / inner)
    else:
        for _ in range(repeats):
            t = time.perf_counter()
            fn()
            times.append((time.perf_counter() - t) * 1e3)
    return statistics.median(times)


def copy_bandwidth_gbs(device: str, n_bytes: int = 2**30) -> float:
    """Device-to-device copy rate, bytes read + written per second, in GB/s."""
    if not str(device).startswith("cuda"):
        n_bytes = 2**24
    a = torch.empty(n_bytes // 4, dtype=torch.float32, device=device).uniform_()
    b = torch.empty_like(a)
    ms = time_ms(lambda: b.copy_(a), device, repeats=10)
    return 2 * n_bytes / ms * 1e-6
