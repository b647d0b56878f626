"""Who calls a device-wide sync in a profiled step: read a `profile_step --trace` Chrome trace.

    python -m benchmarks.trace_syncs RUN/trace.json.gz [--name cudaDeviceSynchronize]
        [--before 8] [--top 10] [--out OUT.md]

For every host event called NAME (a CUDA runtime call as the profiler records it), on any
thread: the events that contain it (outermost first: a Python call under `--stacks`, a
torch op, a `record_function` stage), the BEFORE events of its thread that ended last before
it began, and the device idle gap it returned in (the gap goes to the last call that
returned inside it: after that one the host could queue work again). Calls with the same
context are counted together, most device idle first, so the line of the repository that
asks the device to drain is named (issue #17: ~0.5 ms a step of idle "at
cudaDeviceSynchronize" with no sync counted from Python).
"""

from __future__ import annotations

import argparse
import bisect
import gzip
import json
import re
from collections import defaultdict
from pathlib import Path

from fastenerf.errors import InputError

from .cli import benchmark_main, check_table_out, print_or_write_table

KERNEL_CATS = ("kernel", "gpu_memcpy", "gpu_memset")
SHOWN = 8
"""Containing events shown per context, innermost ones (a `--stacks` path is ~20 deep)."""
ADDRESS = re.compile(r" at 0x[0-9a-f]+")


def load_trace(path: Path) -> list[dict]:
    """The complete events ("ph": "X") of a Chrome trace, gzipped or not."""
    if not path.is_file():
        raise InputError(f"{path}: no such trace file")
    raw = path.read_bytes()
    try:
        text = gzip.decompress(raw) if raw[:2] == b"\x1f\x8b" else raw
        events = json.loads(text)
    except (OSError, ValueError) as e:
        raise InputError(f"{path}: not a Chrome trace ({type(e).__name__})") from None
    if isinstance(events, dict):
        events = events.get("traceEvents", [])
    if not isinstance(events, list):
        raise InputError(f"{path}: not a Chrome trace (no traceEvents list)")
    return [e for e in events if isinstance(e, dict) and e.get("ph") == "X" and "ts" in e]


def idle_gaps(events: list[dict]) -> list[tuple[float, float]]:
    """The device's idle gaps (start, end), µs: between its merged kernel intervals."""
    spans = sorted(
        (float(e["ts"]), float(e["ts"]) + float(e.get("dur", 0)))
        for e in events
        if e.get("cat") in KERNEL_CATS
    )
    merged: list[list[float]] = []
    for a, b in spans:
        if merged and a <= merged[-1][1]:
            merged[-1][1] = max(merged[-1][1], b)
        else:
            merged.append([a, b])
    return [(x[1], y[0]) for x, y in zip(merged[:-1], merged[1:], strict=True) if y[0] > x[1]]


def sync_contexts(events: list[dict], name: str, before: int) -> list[dict]:
    """One row per distinct context of the host events called `name`: calls, the device idle
    they returned in (µs, summed: each gap goes to the last call that returned inside it, the
    one after which the host could queue work again), the containing events (outermost
    first) and the `before` events of the same thread that ended last before the call
    (oldest first)."""
    gaps = idle_gaps(events)
    gap_ends = [g[1] for g in gaps]
    threads: dict[tuple, list[dict]] = defaultdict(list)
    for e in events:
        if e.get("cat") not in KERNEL_CATS:
            threads[(e.get("pid"), e.get("tid"))].append(e)
    calls: list[tuple[float, tuple]] = []  # (end, context key) of every call
    rows: dict[tuple, dict] = {}
    for evs in threads.values():
        evs.sort(key=lambda e: (float(e["ts"]), -float(e.get("dur", 0))))
        for i, e in enumerate(evs):
            if e.get("name") != name:
                continue
            t0 = float(e["ts"])
            outer = [event_name(x) for x in evs[:i] if float(x["ts"]) <= t0 < event_end(x)]
            ended = sorted((x for x in evs[:i] if event_end(x) <= t0), key=event_end)
            lead = [event_name(x) for x in ended[-before:]] if before else []
            key = (tuple(outer), tuple(lead))
            rows.setdefault(key, {"calls": 0, "idle_us": 0.0, "in": outer, "after": lead})
            rows[key]["calls"] += 1
            calls.append((event_end(e), key))
    last: dict[int, tuple[float, tuple]] = {}  # gap -> the last call that returned in it
    for t1, key in calls:
        j = bisect.bisect_left(gap_ends, t1)
        if j < len(gaps) and gaps[j][0] <= t1 and (j not in last or last[j][0] < t1):
            last[j] = (t1, key)
    for j, (_, key) in last.items():
        rows[key]["idle_us"] += gaps[j][1] - gaps[j][0]
    return sorted(rows.values(), key=lambda r: (-r["idle_us"], -r["calls"]))


def event_name(e: dict) -> str:
    """An event's name without object addresses (they differ call to call)."""
    return ADDRESS.sub("", str(e.get("name", "")))


def event_end(e: dict) -> float:
    return float(e["ts"]) + float(e.get("dur", 0))


def markdown(rows: list[dict], name: str, top: int) -> str:
    lines = [
        f"### `{name}` calls by context ({sum(r['calls'] for r in rows)} calls)",
        "",
        "| calls | device idle after (ms) | inside (outer › inner) | after (oldest first) |",
        "|---:|---:|---|---|",
    ]
    for r in rows[:top]:
        inside = " › ".join(n[:60] for n in r["in"][-SHOWN:]) or "—"
        after = " › ".join(n[:60] for n in r["after"]) or "—"
        lines.append(f"| {r['calls']} | {r['idle_us'] / 1e3:.3f} | {inside} | {after} |")
    return "\n".join(lines) + "\n"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("trace", help="a profile_step --trace file (trace.json.gz)")
    p.add_argument("--name", default="cudaDeviceSynchronize", help="the host event to explain")
    p.add_argument("--before", type=int, default=8, help="events named before each call")
    p.add_argument("--top", type=int, default=10, help="contexts listed")
    p.add_argument("--out", help="a new .md file to write (default: print)")


def run(args: argparse.Namespace) -> int:
    if args.before < 0 or args.top < 1:
        raise InputError("--before must be >= 0 and --top >= 1")
    check_table_out(args.out)
    rows = sync_contexts(load_trace(Path(args.trace)), args.name, args.before)
    return print_or_write_table(markdown(rows, args.name, args.top), args.out)


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    return benchmark_main("trace_syncs", __doc__, add_arguments, run, argv, prog)


if __name__ == "__main__":
    raise SystemExit(main())
