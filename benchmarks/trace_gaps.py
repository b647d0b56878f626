"""Why the device idles between kernels: read a `profile_step --trace` Chrome trace.

    python -m benchmarks.trace_gaps RUN/trace.json.gz [--steps N] [--top 12] [--out OUT.md]

Every idle gap of the device's timeline is put in one class by how the work that ended it
was issued (the runtime call the profiler links to it by its correlation id):

- **host late**: the launch call began after the gap began, so the device waited for the
  host to issue it; the host op the launching thread was inside at the gap's start is named;
- **queued**: the work was already issued when the device went idle (launch latency, a
  graph's start, a dependency the driver resolves): a device-side gap;
- **in graph**: between two nodes of one CUDA graph replay;
- **unlinked**: no launch call in the trace for it.

It also sums the device's own time from the trace: busy (its events' union) against the
profiled span, and kernel time by kind (`profile_step`'s kinds), every kernel counted.

The idle is per profiled step (`--steps`; default: the `steps` of the `profile_step.json`
one folder above the trace, else the whole trace as one). Issue #17: a step whose kernels
take 3.9 ms idles ~1 ms; whether that is the host (fewer launches, less Python) or the
device's own scheduling (fewer nodes) decides what to change. A `--stacks` profile slows
the host several-fold, so read a trace made without it.
"""

from __future__ import annotations

import argparse
import json
from collections import Counter, defaultdict
from pathlib import Path

from fastenerf.errors import InputError

from .cli import benchmark_main, check_table_out, print_or_write_table
from .device_gaps import merge_intervals
from .profile_step import tally_kernels
from .trace_syncs import KERNEL_CATS, event_end, event_name, load_trace

LAUNCH_CATS = ("cuda_runtime", "cuda_driver")
HOST_CATS = ("cpu_op", "user_annotation")
"""Host events that say what the launching thread was doing (Python frames are left out:
only a `--stacks` trace has them, and it is the wrong one to read)."""
CLASSES = ("host late", "queued", "in graph", "unlinked")


def _corr(e: dict) -> object:
    return (e.get("args") or {}).get("correlation")


def classify_gaps(events: list[dict]) -> list[dict]:
    """One record per idle gap of the device (all streams merged): `idle_us`, `cls` (one of
    CLASSES), `before` and `after` (the device events on either side), `launch` (the runtime
    call that issued `after`, or None) and `host` (for a host-late gap: the innermost host
    op of the launching thread running at the gap's start, or "no host op")."""
    launches = {_corr(e): e for e in events if e.get("cat") in LAUNCH_CATS and _corr(e)}
    device = sorted((e for e in events if e.get("cat") in KERNEL_CATS), key=lambda e: e["ts"])
    host: dict[tuple, list[dict]] = defaultdict(list)
    for e in events:
        if e.get("cat") in HOST_CATS:
            host[(e.get("pid"), e.get("tid"))].append(e)
    gaps: list[dict] = []
    if not device:
        return gaps
    last = device[0]  # the device event that ends latest so far
    for e in device[1:]:
        t0, t1 = event_end(last), float(e["ts"])
        if t1 > t0:
            launch = launches.get(_corr(e))
            cls, doing = _gap_class(launch, last, t0), None
            if cls == "host late":
                doing = _innermost(host[(launch.get("pid"), launch.get("tid"))], t0)
            gaps.append(
                {
                    "idle_us": t1 - t0,
                    "cls": cls,
                    "before": event_name(last),
                    "after": event_name(e),
                    "launch": event_name(launch) if launch else None,
                    "host": doing,
                }
            )
        if event_end(e) > event_end(last):
            last = e
    return gaps


def _gap_class(launch: dict | None, before: dict, t0: float) -> str:
    """The class of a gap that began at `t0`, after `before`, ended by work `launch` issued."""
    if launch is None:
        return "unlinked"
    if event_name(launch) == "cudaGraphLaunch" and _corr(before) == _corr(launch):
        return "in graph"
    return "host late" if float(launch["ts"]) >= t0 else "queued"


def _innermost(ops: list[dict], t: float) -> str:
    """The shortest of `ops` running at time `t` (µs), by name; "no host op" if none."""
    running = [e for e in ops if float(e["ts"]) <= t < event_end(e)]
    return (
        event_name(min(running, key=lambda e: float(e.get("dur", 0)))) if running else "no host op"
    )


def summary(gaps: list[dict], steps: float) -> dict:
    """Per step: idle ms and gaps by class, by (class, before › after) and, for host-late
    gaps, by what the host was doing."""
    by_cls: Counter = Counter()
    count: Counter = Counter()
    pairs: Counter = Counter()
    doing: Counter = Counter()
    for g in gaps:
        by_cls[g["cls"]] += g["idle_us"]
        count[g["cls"]] += 1
        pairs[(g["cls"], g["before"], g["after"])] += g["idle_us"]
        if g["host"] is not None:
            doing[g["host"]] += g["idle_us"]

    def ms(c: Counter) -> list[tuple]:
        return [(k, v / steps / 1e3) for k, v in c.most_common()]

    return {
        "steps": steps,
        "idle_ms": sum(by_cls.values()) / steps / 1e3,
        "classes": [(k, by_cls[k] / steps / 1e3, count[k] / steps) for k in CLASSES if count[k]],
        "pairs": ms(pairs),
        "host_doing": ms(doing),
    }


def device_time(events: list[dict], steps: float) -> dict:
    """Per step, from the trace's device events: `busy_ms` (their union), `span_ms` (first
    start to last end), `device_ms` (kernel, copy and memset time by kind) and
    `other_kernels` (`profile_step.tally_kernels`'s: what no kind claims)."""
    device = [e for e in events if e.get("cat") in KERNEL_CATS]
    if not device:
        return {"busy_ms": 0.0, "span_ms": 0.0, "device_ms": {}, "other_kernels": {}}
    spans = merge_intervals([(float(e["ts"]), event_end(e)) for e in device])
    tally = tally_kernels([(event_name(e), float(e.get("dur", 0)) / 1e3) for e in device], steps)
    return {
        "busy_ms": sum(b - a for a, b in spans) / steps / 1e3,
        "span_ms": (spans[-1][1] - spans[0][0]) / steps / 1e3,
        "device_ms": tally["device_ms"],
        "other_kernels": tally["other_kernels"],
    }


def short_kernel(name: str) -> str:
    """A PyTorch kernel's name without the namespaces that make its first 100 characters
    alike (`void at::native::(anonymous namespace)::...`)."""
    for noise in ("void ", "at::native::", "(anonymous namespace)::", "c10::"):
        name = name.replace(noise, "")
    return name


def markdown(s: dict, top: int, busy: dict | None = None) -> str:
    lines = [
        f"### Device idle by cause: {s['idle_ms']:.3f} ms a step over {s['steps']:g} steps",
        "",
        "| class | idle ms/step | gaps/step |",
        "|---|---:|---:|",
    ]
    lines += [f"| {c} | {ms:.3f} | {n:.1f} |" for c, ms, n in s["classes"]]
    lines += ["", "| class | kernel before › kernel after | idle ms/step |", "|---|---|---:|"]
    lines += [f"| {c} | `{b[:60]}` › `{a[:60]}` | {v:.3f} |" for (c, b, a), v in s["pairs"][:top]]
    if s["host_doing"]:
        lines += ["", "| host op at a host-late gap | idle ms/step |", "|---|---:|"]
        lines += [f"| `{k[:80]}` | {v:.3f} |" for k, v in s["host_doing"][:top]]
    if busy and busy["span_ms"] > 0:
        share = 100 * busy["busy_ms"] / busy["span_ms"]
        lines += [
            "",
            f"Device busy {busy['busy_ms']:.3f} of {busy['span_ms']:.3f} ms a step ({share:.0f} %"
            " of the profiled span, under the profiler).",
            "",
            "| device time by op | ms/step |",
            "|---|---:|",
        ]
        lines += [f"| {k} | {v:.3f} |" for k, v in busy["device_ms"].items()]
        lines += ["", '| "torch other" kernel | ms/step | launches/step |', "|---|---:|---:|"]
        lines += [
            f"| `{short_kernel(k)[:100]}` | {v['ms']:.3f} | {v['launches']:.1f} |"
            for k, v in list(busy["other_kernels"].items())[:top]
        ]
    return "\n".join(lines) + "\n"


def profiled_steps(trace: Path) -> float:
    """The profiled steps of the `profile_step.json` beside the trace's run folder (with
    several variants, the one whose folder holds the trace), else 1."""
    run = trace.resolve().parent
    try:
        meta = json.loads((run.parent / "profile_step.json").read_text())
        rows = meta.get("variants") or [meta]
        mine = [r for r in rows if str(r.get("backend", "")).endswith(f"variant {run.name}")]
        steps = float((mine or rows)[0].get("steps", 1))
    except (OSError, ValueError, AttributeError, IndexError, TypeError):
        return 1.0
    return steps if steps > 0 else 1.0


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "trace", help="a profile_step --trace file (trace.json.gz), made without --stacks"
    )
    p.add_argument("--steps", type=float, default=None, help="profiled steps in the trace")
    p.add_argument("--top", type=int, default=12, help="rows listed per table")
    p.add_argument("--out", help="a new .md file to write (default: print)")


def run(args: argparse.Namespace) -> int:
    if args.top < 1 or (args.steps is not None and not args.steps > 0):
        raise InputError("--top must be >= 1 and --steps > 0")
    check_table_out(args.out)
    path = Path(args.trace)
    events = load_trace(path)
    steps = args.steps if args.steps is not None else profiled_steps(path)
    md = markdown(summary(classify_gaps(events), steps), args.top, device_time(events, steps))
    return print_or_write_table(md, args.out)


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    return benchmark_main("trace_gaps", __doc__, add_arguments, run, argv, prog)


if __name__ == "__main__":
    raise SystemExit(main())
