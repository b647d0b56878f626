"""How many host-side ops one training step issues: aten ops, autograd nodes and Warp launches.

    python -m benchmarks.step_ops --scene DIR [--steps 32] [--warmup 272] [--rays 64] \
        [--step-mode device|plain] [--no-amp] [--variant NAME[=JSON]] [--device cpu] \
        [--baseline OLD/step_ops.json] [--out OUT]

Where the GPU waits on the host (benchmarks.profile_step: device busy well below the step's
wall time), the step's cost is the number of things the host issues, each a few µs of Python,
dispatch and launch: this counts them per step, by the named ranges of the step (the trainer's
grid_update, sample_rays, render > march / prune / field / composite, loss, backward,
optimizer; "other": outside every range, e.g. the step's stats), each op in its innermost
range only (render's row: its ops outside march / prune / field / composite):
- aten ops: every `aten::` event of torch.profiler, and the top-level ones (not called by
  another aten op: what Python, an autograd node or autocast dispatched);
- autograd nodes: the backward functions the engine ran;
- Warp launches: calls of kernels/common.py's launcher (named `warp::KERNEL` in the trace).
The counts do not depend on the batch or the sizes, so a few rays (`--rays`) on a CPU give the
GPU's top-level counts (nested ones follow the device's kernels: a CPU's fallbacks nest more):
the trainer is the "fast" preset's (benchmarks.cpu_preset.build; on a CPU at the CPU preset's
sizes, `--variant gpu-sizes` for the GPU's), the step device-paced with a fused Adam
(`--step-mode device`, what `auto` picks on CUDA) under bf16 autocast (`--no-amp` leaves it
off on a CPU, as the trainer does). The default warm-up passes
the occupancy grid's warm-up (256 steps); `--steps` a multiple of the sampler's block (16) and
of the grid's update interval (16) spreads their per-block work evenly.
`--baseline` puts an earlier run's counts (its step_ops.json) beside this one's.

Outputs in OUT: step_ops.json and step_ops.md.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
from collections import Counter
from pathlib import Path
from typing import Any

from benchmarks.cli import benchmark_main
from benchmarks.cpu_preset import build, parse_variant
from benchmarks.curve import load_scene_dir
from benchmarks.session import jsonable, session_info
from fastenerf.errors import InputError
from fastenerf.hooks import Hook
from fastenerf.io import atomic_path, write_json
from fastenerf.run import resolve_device

# The step's named ranges, outer before inner (render holds march, prune, field, composite).
STAGES = (
    "grid_update",
    "sample_rays",
    "render",
    "march",
    "prune",
    "field",
    "composite",
    "loss",
    "backward",
    "optimizer",
)
SUB_STAGES = ("march", "prune", "field", "composite")
OTHER = "other"
KINDS = ("aten", "aten_top", "autograd", "warp")
WARP_PREFIX = "warp::"
NODE_PREFIX = "autograd::engine::evaluate_function: "
DEFAULT_RAYS = 64


@contextlib.contextmanager
def named_launches():
    """Every Warp launch (kernels/common.py's `Launcher`) as a `warp::NAME` profiler range."""
    from torch.profiler import record_function

    from fastenerf.kernels.common import Launcher

    plain = Launcher.__call__

    def named(self, dim, t, args):
        with record_function(WARP_PREFIX + getattr(self.kernel, "key", "kernel")):
            plain(self, dim, t, args)

    Launcher.__call__ = named
    try:
        yield
    finally:
        Launcher.__call__ = plain


def event_kind(ev) -> str | None:
    """ "aten_top", "aten", "autograd", "warp" or None (ranges and everything else)."""
    name = ev.name
    if name.startswith("aten::"):
        parent = ev.cpu_parent
        return "aten" if parent is not None and parent.name.startswith("aten::") else "aten_top"
    if name.startswith(NODE_PREFIX):
        return "autograd"
    if name.startswith(WARP_PREFIX):
        return "warp"
    return None


def _stage_of(ev, ranges: list) -> str:
    """The innermost named range holding ev: its parents on its thread, else (an autograd
    thread's op) the innermost range whose span holds it."""
    p = ev.cpu_parent
    while p is not None:
        if p.name in STAGES:
            return p.name
        p = p.cpu_parent
    s, e = ev.time_range.start, ev.time_range.end
    best = None
    for r in ranges:
        if r.time_range.start <= s and e <= r.time_range.end:
            if best is None or r.time_range.start >= best.time_range.start:
                best = r
    return best.name if best is not None else OTHER


def count_events(events, steps: int) -> dict[str, Any]:
    """Per-step counts {stage: {kind: n}}, and {stage: {name: n}} of the top-level aten ops,
    the autograd nodes and the Warp kernels."""
    ranges = [ev for ev in events if ev.name in STAGES]
    counts = {s: Counter() for s in (*STAGES, OTHER)}
    ops = {s: Counter() for s in (*STAGES, OTHER)}
    for ev in events:
        kind = event_kind(ev)
        if kind is None:
            continue
        stage = _stage_of(ev, ranges)
        counts[stage][kind] += 1
        if kind == "aten_top":
            counts[stage]["aten"] += 1
            ops[stage][ev.name] += 1
        elif kind in ("warp", "autograd"):
            ops[stage][ev.name.removeprefix(NODE_PREFIX)] += 1
    per = {s: {k: c[k] / steps for k in KINDS} for s, c in counts.items()}
    per["total"] = {k: sum(per[s][k] for s in (*STAGES, OTHER)) for k in KINDS}
    top = {s: {k: v / steps for k, v in c.most_common()} for s, c in ops.items() if c}
    return {"per_step": per, "ops_per_step": top}


class CountSteps(Hook):
    """After `warmup` steps, profiles `steps` steps with named Warp launches, then stops the
    run; `result` holds the per-step counts."""

    def __init__(self, warmup: int, steps: int):
        self.warmup, self.steps = warmup, steps
        self.count = 0
        self.stack: contextlib.ExitStack | None = None
        self.result: dict[str, Any] | None = None

    def on_start(self, trainer) -> None:
        if self.warmup == 0:
            self._begin()

    def _begin(self) -> None:
        from torch.profiler import ProfilerActivity, profile

        self.stack = contextlib.ExitStack()
        self.stack.enter_context(named_launches())
        self.prof = self.stack.enter_context(profile(activities=[ProfilerActivity.CPU]))

    def after_step(self, trainer, stats: dict[str, Any]) -> None:
        self.count += 1
        if self.count == self.warmup:
            self._begin()
        elif self.count == self.warmup + self.steps:
            self.stack.close()
            self.stack = None
            self.result = count_events(self.prof.events(), self.steps)
            trainer.request_stop()

    def on_end(self, trainer, summary: dict[str, Any]) -> None:
        if self.stack is not None:
            self.stack.close()


def _spec(args: argparse.Namespace) -> tuple[str, dict]:
    """The variant to build: --variant (default: the preset) with --rays and --step-mode."""
    name, spec = parse_variant(args.variant) if args.variant else ("fast", {})
    train = dict(spec.get("train") or {})
    train["step_mode"] = args.step_mode
    if args.rays is not None or "rays_per_step" not in train:
        train["rays_per_step"] = args.rays or DEFAULT_RAYS
    return name, {**spec, "train": train}


def markdown(res: dict, base: dict | None = None) -> str:
    m = res["session"]["machine"]["name"]
    title = f"### Host ops per training step — {res['scene']}, {res['variant']}, {m}"
    lines = [
        title,
        "",
        f"{res['steps']} steps after {res['warmup']} warm-up steps; step {res['step_mode']}, "
        f"amp {'bf16' if res['amp'] else 'off'}; per step: aten ops (all / top-level), "
        "autograd nodes, Warp launches" + ("; baseline → now" if base else "") + ".",
        "",
        "| stage | aten ops | top-level aten | autograd nodes | Warp launches |",
        "|---|---:|---:|---:|---:|",
    ]
    for stage in (*STAGES, OTHER, "total"):
        now = res["per_step"][stage]
        was = base["per_step"].get(stage) if base else None
        if not any(now.values()) and not (was and any(was.values())):
            continue
        cells = [f"{was[k]:.1f} → {now[k]:.1f}" if was else f"{now[k]:.1f}" for k in KINDS]
        label = f"  ↳ {stage}" if stage in SUB_STAGES else stage
        label = f"**{label}**" if stage == "total" else label
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    lines.append("")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    if args.steps < 1 or args.warmup < 0:
        raise InputError("--steps must be >= 1 and --warmup >= 0")
    if args.rays is not None and args.rays < 1:
        raise InputError("--rays must be >= 1")
    base = _read_baseline(args.baseline)
    device = resolve_device(args.device)
    scene = load_scene_dir(args.scene)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    name, spec = _spec(args)
    trainer = build(scene, "run", spec, 300.0, out, str(device))
    trainer.amp = not args.no_amp  # bf16 autocast as on CUDA, on the CPU too
    hook = CountSteps(args.warmup, args.steps)
    trainer.run(hooks=[hook], progress=False)
    if hook.result is None:
        raise InputError(f"the run ended after {trainer.step_count} steps, before the count")
    res = {
        **hook.result,
        "scene": Path(args.scene).resolve().name,
        "variant": name,
        "spec": spec,
        "step_mode": trainer.step_mode,
        "amp": trainer.amp,
        "steps": args.steps,
        "warmup": args.warmup,
        "rays_per_step": trainer.cfg.rays_per_step,
        "session": session_info(device, args.commit),
    }
    write_json(out / "step_ops.json", jsonable(res))
    with atomic_path(out / "step_ops.md") as tmp:
        tmp.write_text(markdown(res, base))
    print(markdown(res, base))
    return 0


def _read_baseline(path: str | None) -> dict | None:
    if path is None:
        return None
    try:
        base = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise InputError(f"--baseline {path}: not readable ({e})") from None
    if not isinstance(base, dict) or not isinstance(base.get("per_step"), dict):
        raise InputError(f"--baseline {path}: not a step_ops.json")
    return base


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scene", required=True, help="scene folder")
    p.add_argument("--warmup", type=int, default=272, help="steps before the count")
    p.add_argument("--steps", type=int, default=32, help="counted steps")
    p.add_argument("--rays", type=int, default=None, help=f"pixels per step ({DEFAULT_RAYS})")
    p.add_argument("--step-mode", default="device", choices=["device", "plain"])
    p.add_argument("--no-amp", action="store_true", help="no bf16 autocast")
    p.add_argument("--device", default="cpu")
    p.add_argument(
        "--variant",
        metavar="NAME[=JSON]",
        help="a benchmarks.cpu_preset variant (built-in name or NAME=JSON) instead of the preset",
    )
    p.add_argument("--baseline", help="an earlier step_ops.json to compare with")
    p.add_argument("--out", default="runs/bench/step_ops")
    p.add_argument("--commit", default=None, help="git commit to record")


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    return benchmark_main("step_ops", __doc__, add_arguments, run, argv, prog, out_folder=True)


if __name__ == "__main__":
    sys.exit(main())
