"""Where a profiled GPU waits: the idle gaps between its kernels, and what the host was doing
when each one began (issue #17: the GPU busy 71-77 % of a step with no host sync counted).

`device_gaps` merges the device's kernel intervals, takes every gap between them and names
it after the innermost host event of the training thread (a `record_function` stage, a torch
op, a CUDA runtime call) running at the gap's start: the host was there when the device ran
dry. Other threads' events at the gap (a profiler's, the autograd engine's) are counted apart,
and so is the kernel that ended each gap. Times come from
torch.profiler, which puts CPU and GPU events on one clock (microseconds). The profiler's own
per-op bookkeeping slows the host, so the gaps it sees are an upper bound on the unprofiled
step's; their split between host events is what it is for.
"""

from __future__ import annotations

import bisect
import re
from collections import Counter

GAP_MIN_US = 5.0
"""Gaps shorter than this are a launch's own latency, not the host falling behind."""
SCAN_BACK = 4000
"""Host events searched backwards from a gap's start for one that contains it."""
PATH_DEPTH = 4
"""Containing host events named in a gap's path (the innermost ones): the stage or op that
made the call the device ran dry in, e.g. `grid_update › aten::item › cudaStreamSynchronize`."""
PATH_SEP = " › "
REPO_DIRS = ("fastenerf", "kernels", "benchmarks")
"""This repository's top-level folders: with Python calls profiled (`profile_step --stacks`),
a path keeps the calls in them and drops the libraries' own (torch's, Warp's)."""
LEAD_IN = 4
"""Host events named before a sync call a gap began in (`lead_in`): what made the call."""
PY_FRAME = re.compile(r"^(?P<path>\S+)\((?P<line>\d+)\): (?P<func>.+)$")


def merge_intervals(spans: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """Overlapping or touching (start, end) intervals merged, in order."""
    out: list[list[float]] = []
    for s, e in sorted(spans):
        if out and s <= out[-1][1]:
            out[-1][1] = max(out[-1][1], e)
        else:
            out.append([s, e])
    return [(s, e) for s, e in out]


def containing(host: list[tuple[float, float, str]], starts: list[float], t: float) -> list[str]:
    """The names of the host events (start, end, name) that contain time t, outermost first
    (by start): `host` sorted by start, `starts` its start times."""
    return [h[2] for h in containing_events(host, starts, t)]


def containing_events(host: list[tuple], starts: list[float], t: float) -> list[tuple]:
    """`containing`'s events themselves, outermost first."""
    i = bisect.bisect_right(starts, t) - 1
    found = [host[j] for j in range(i, max(-1, i - SCAN_BACK), -1) if host[j][0] <= t < host[j][1]]
    return found[::-1]


def lead_in(host: list[tuple], starts: list[float], t: float, n: int = LEAD_IN) -> str:
    """The names of the last `n` host events that ended by time t (the calls made just
    before one that began at t), oldest first, joined by PATH_SEP; Python calls
    (`--stacks`) named as in a path, a library's left out."""
    i = bisect.bisect_right(starts, t) - 1
    done = [host[j] for j in range(i, max(-1, i - SCAN_BACK), -1) if host[j][1] <= t]
    names = [path_name(h[2]) for h in sorted(done, key=lambda h: h[1])]
    return PATH_SEP.join(x[:60] for x in [x for x in names if x is not None][-n:]) or "none"


def path_name(name: str) -> str | None:
    """A host event's name in a gap's path: a torch op or CUDA call as it is, a Python call
    ("FILE(LINE): FUNC", `--stacks`) from FILE's first folder of this repository on, None for
    a Python call elsewhere (a library's)."""
    m = PY_FRAME.match(name)
    if m is None:
        return name
    path = m["path"].replace("\\", "/")
    for root in REPO_DIRS:
        if path.startswith(f"{root}/"):
            return f"{path}({m['line']}): {m['func']}"
        i = path.find(f"/{root}/")
        if i >= 0:
            return f"{path[i + 1 :]}({m['line']}): {m['func']}"
    return None


def training_thread(host: list[tuple]) -> object:
    """The thread of most host events (start, end, name, thread): the one that runs the
    steps (a profile also holds the autograd engine's, the profiler's own threads)."""
    top = Counter(h[3] for h in host).most_common(1)
    return top[0][0] if top else None


def device_gaps(
    kernels: list[tuple],
    host: list[tuple],
    steps: int,
    top: int = 12,
) -> dict:
    """The device's idle time between its first and last kernel, per step, and its split by
    the training thread's host event running at each gap's start.

    kernels: (start_us, end_us[, name]) of every device kernel; host: (start_us, end_us,
    name[, thread]) of the host events (without threads, all are the training thread's);
    steps: the steps the window covers. Returns idle_ms (per step), gaps (per step, those of
    at least GAP_MIN_US), largest_gap_ms, idle_by_host_ms: the `top` host events' idle ms per
    step, largest first ("no host event" where none contains the start), idle_by_path_ms: the
    same by the PATH_DEPTH innermost containing events, outer first; idle_other_threads_ms:
    the same by the innermost event of another thread running at the gap's start (a sync
    there is not the step's), and idle_by_next_kernel_ms: by the kernel that ended the gap
    (what the device waited to start); idle_by_sync_lead_in_ms: the gaps that began in a
    sync call (`...Synchronize`), by that call and the LEAD_IN host events before it.
    """
    host = sorted((h if len(h) > 3 else (*h, None) for h in host), key=lambda h: (h[0], h[1]))
    main = training_thread(host)
    mine = [h for h in host if h[3] == main]
    others = [h for h in host if h[3] != main]
    gaps, after = _gaps(kernels)
    by: dict[str, float] = {}
    by_path: dict[str, float] = {}
    by_other: dict[str, float] = {}
    by_next: dict[str, float] = {}
    by_lead: dict[str, float] = {}
    starts, other_starts = [h[0] for h in mine], [h[0] for h in others]
    for (g0, g1), nxt in zip(gaps, after, strict=True):
        inside = containing_events(mine, starts, g0)
        names = [h[2] for h in inside] or ["no host event"]
        _add(by, names[-1], g1 - g0)
        if names[-1].endswith("Synchronize"):  # a wait on the device: what led to it
            _add(by_lead, f"{names[-1]} after {lead_in(mine, starts, inside[-1][0])}", g1 - g0)
        kept = [p for p in map(path_name, names) if p is not None] or names[-1:]
        _add(by_path, PATH_SEP.join(n[:80] for n in kept[-PATH_DEPTH:]), g1 - g0)
        if other := containing(others, other_starts, g0):
            _add(by_other, other[-1], g1 - g0)
        if nxt is not None:
            _add(by_next, nxt, g1 - g0)
    steps = max(1, steps)

    def ranked(d: dict[str, float], width: int) -> dict[str, float]:
        rows = sorted(d.items(), key=lambda kv: -kv[1])[:top]
        return {name[:width]: us / 1e3 / steps for name, us in rows}

    return {
        "idle_ms": sum(g1 - g0 for g0, g1 in gaps) / 1e3 / steps,
        "gaps": len(gaps) / steps,
        "largest_gap_ms": max((g1 - g0 for g0, g1 in gaps), default=0.0) / 1e3,
        "idle_by_host_ms": ranked(by, 100),
        "idle_by_path_ms": ranked(by_path, 250),
        "idle_other_threads_ms": ranked(by_other, 100),
        "idle_by_next_kernel_ms": ranked(by_next, 100),
        "idle_by_sync_lead_in_ms": ranked(by_lead, 300),
    }


def _add(d: dict[str, float], key: str, us: float) -> None:
    d[key] = d.get(key, 0.0) + us


def _gaps(kernels: list[tuple]) -> tuple[list[tuple[float, float]], list[str | None]]:
    """The gaps of at least GAP_MIN_US between the merged kernel intervals, and the name of
    the kernel starting at each gap's end (None for unnamed intervals)."""
    merged = merge_intervals([(k[0], k[1]) for k in kernels])
    first = {}
    for k in sorted(kernels, key=lambda k: k[0]):
        if len(k) > 2:
            first.setdefault(k[0], k[2])
    pairs = zip(merged[:-1], merged[1:], strict=True)
    gaps = [(a[1], b[0]) for a, b in pairs if b[0] - a[1] >= GAP_MIN_US]
    return gaps, [first.get(g1) for _, g1 in gaps]
