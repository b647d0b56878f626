"""Memory estimates before large allocations: refuse with the estimate instead of running out.

A command that is about to allocate in proportion to a user's number (frames x sensor size,
a grid resolution cubed, a render scale squared, n_views, rays per step) first calls
`check_memory(estimate_bytes, what)`. It raises an `InputError` (one line, exit 2) giving
the estimate and the limit when the estimate exceeds the limit, which is the memory
available now (`MemAvailable` of /proc/meminfo; the free pages elsewhere), or the stated cap
`FASTENERF_MEMORY_LIMIT` (e.g. "8G", "512M", "1.5T", or bytes) when that is lower. For a CUDA
device the limit is the device's free memory (`torch.cuda.mem_get_info`).

The estimates are lower bounds of the named arrays (what is certain to be allocated), not
peak usage: they exist to turn a request that cannot fit into a clear refusal, not to
predict the footprint of one that can.
"""

from __future__ import annotations

import math
import os
import re

from .errors import InputError

ENV_LIMIT = "FASTENERF_MEMORY_LIMIT"
_UNITS = {"": 1, "K": 1 << 10, "M": 1 << 20, "G": 1 << 30, "T": 1 << 40}


def format_bytes(n: float) -> str:
    """1536 -> "1.50 KiB"; 8e12 -> "7.28 TiB"."""
    if not math.isfinite(n):
        return "inf B"
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if abs(n) < 1024 or unit == "PiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.2f} {unit}"
        n /= 1024
    raise AssertionError  # unreachable


def parse_bytes(s: str) -> int:
    """ "8G" / "512M" / "1.5T" / "123456" (binary units, an optional "iB"/"B") -> bytes."""
    m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+)\s*([KMGT]?)(?:i?B)?\s*", s, re.IGNORECASE)
    if not m:
        raise InputError(f"{ENV_LIMIT}={s!r}: expected a size like 8G, 512M or 1000000")
    return int(float(m.group(1)) * _UNITS[m.group(2).upper()])


def available_bytes() -> int | None:
    """Host memory available now, bytes (None where the platform does not say)."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def memory_limit(device: str = "cpu") -> tuple[int | None, str]:
    """(bytes, what the limit is) for allocations on `device` ("cpu", "cuda", "cuda:1", ...)."""
    cap = os.environ.get(ENV_LIMIT)
    if str(device).startswith("cuda"):
        import torch

        free, _ = torch.cuda.mem_get_info(torch.device(device))
        avail, what = int(free), f"free on {device}"
    else:
        avail, what = available_bytes(), "available"
    if cap:
        c = parse_bytes(cap)
        if avail is None or c < avail:
            return c, f"cap {ENV_LIMIT}={cap}"
    return avail, what


def check_memory(nbytes: float, what: str, device: str = "cpu") -> None:
    """Raise `InputError` when `nbytes` (an estimate) exceeds the memory limit on `device`.

    what: the request, as the user gave it ("2000 frames at 4096x4096").
    """
    limit, desc = memory_limit(device)
    if limit is not None and nbytes > limit:
        raise InputError(
            f"{what} needs at least {format_bytes(nbytes)} of memory, more than the "
            f"{format_bytes(limit)} {desc}; ask for less"
        )


# ---------------------------------------------------------------------------- estimates


def synth_bytes(
    width: int, height: int, frames: int, test_every: int, chunk: int, supersample: int = 1
) -> int:
    """`make_scene`: the ground-truth test views (uint8 RGB, every `test_every`-th frame), a
    chunk of rendered frames (float32 RGB, at `supersample`² the pixels while rendering)
    and the simulator's per-pixel state (a few float64 maps)."""
    px = width * height
    tests = -(-frames // test_every) * px * 3
    batch = min(chunk, frames) * px * 3 * 4 * (1 + supersample**2)
    return tests + batch + px * 8 * 8


def grid_bytes(nx: int, ny: int, nz: int) -> int:
    """A density grid (float32) and marching cubes' working copy of it (float64 + masks)."""
    return nx * ny * nz * (4 + 8 + 2)


def image_bytes(width: int, height: int, views: int = 1, kept_floats: int = 9) -> int:
    """Rendering `views` images at width x height: `kept_floats` float32 per pixel kept for
    every view (eval: prediction, corrected and ground truth RGB, 9; render: the frame for
    the video, 3), plus one view's rays (origin, direction) and outputs (rgb, depth, opacity)."""
    px = width * height
    return views * px * kept_floats * 4 + px * (6 + 5) * 4


def views_bytes(n_views: int) -> int:
    """The window grid of n_views: a pose (4x4 float64 and its float32 copy, with the
    interpolation's temporaries) and a window length (int64) per grid time."""
    return (n_views + 1) * (16 * 8 * 4 + 16 * 4 + 8)


def ray_batch_bytes(n_rays: int, samples_per_ray: int, floats_per_sample: int) -> int:
    """One training step: `n_rays` pixels, each rendered at two times (t0 and t1), with
    `samples_per_ray` samples per ray and `floats_per_sample` float32 values kept per sample
    for the backward pass (positions, encodings, MLP activations)."""
    return 2 * n_rays * samples_per_ray * floats_per_sample * 4


def check_ray_batch(
    n_rays: int,
    samples_per_ray: int,
    floats_per_sample: int,
    device: str = "cpu",
    what: str = "--rays",
) -> int:
    """`check_memory` for a training step's ray batch (`ray_batch_bytes`); returns the estimate.

    n_rays: pixels per step; samples_per_ray: the most samples one ray takes (coarse + fine
    for vanilla, the marcher's cap for ngp); floats_per_sample: float32 values autograd keeps
    per sample (e.g. the MLP's width x depth plus the encoding's size); device: where the
    step runs ("cpu", "cuda", "cuda:1").
    """
    est = ray_batch_bytes(n_rays, samples_per_ray, floats_per_sample)
    check_memory(est, f"{what} {n_rays:,} ({samples_per_ray} samples per ray)", device)
    return est
