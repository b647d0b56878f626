"""Steady-state time of one training step, timed on the device, for option variants side by side.

    python -m benchmarks.step_time --scene DIR [--scene DIR ...] [--variant NAME=JSON ...] \
        [--warmup 1000] [--steps 320] [--budget-s 60] [--device auto] [--out OUT]

Per scene, each variant in turn in one process (`benchmarks.cpu_preset.build`: the fast preset
with the variant's "train" and "backend_options"; none given: `default={}`): --warmup steps
(kernel compilation, the occupancy grid's carving, graph captures), then --steps steps between
two CUDA events with no host wait between them (on a CPU, the wall clock around them). The
trainer runs its one loop with only the timing hook (no evaluation, no checkpoint), its
schedules on a --budget-s clock: with pose refinement, 1000 steps of ~9 ms are inside the
coarse-to-fine phase (the dearer one). Reported: ms/step, its ratio to the scene's first
variant, samples per ray (and marched per ray where compaction keeps fewer), the step mode and
the CUDA-graph captures / replays (a variant that fell back to an eager step says so).

Outputs in OUT: step_time.json and step_time.md (the table for benchmarks/RESULTS.md).
"""

from __future__ import annotations

import argparse
import gc
import time
from pathlib import Path
from typing import Any

import torch

from benchmarks.cli import add_run_arguments, benchmark_main
from benchmarks.cpu_preset import build, parse_variant
from benchmarks.curve import load_scene_dir
from benchmarks.session import jsonable, session_info, write_report
from fastenerf.errors import InputError
from fastenerf.hooks import Hook
from fastenerf.io import write_json
from fastenerf.progress import progress_bar
from fastenerf.run import resolve_device


class TimeSteps(Hook):
    """After `warmup` steps, times `steps` steps (CUDA events on the device with no host wait
    between them; the wall clock on a CPU), then stops the run; `ms` holds ms/step."""

    def __init__(self, warmup: int, steps: int, progress: bool = True):
        self.warmup, self.steps = warmup, steps
        self.ms: float | None = None
        self._start: Any = None
        self.bar = progress_bar(total=warmup + steps, desc="steps", enabled=progress)

    def on_start(self, trainer) -> None:
        trainer.sync_clock = trainer.step_mode == "plain"  # a device-paced step is not waited on
        if self.warmup == 0:
            self._begin(trainer)

    def after_step(self, trainer, stats: dict[str, Any]) -> None:
        self.bar.update(1)
        if trainer.step_count == self.warmup:
            self._begin(trainer)
        elif trainer.step_count == self.warmup + self.steps:
            self.ms = self._elapsed_ms(trainer) / self.steps
            trainer.request_stop()

    def _begin(self, trainer) -> None:
        trainer.sync()
        if trainer.device.type == "cuda":
            self._start = torch.cuda.Event(enable_timing=True)
            self._start.record()
        else:
            self._start = time.perf_counter()

    def _elapsed_ms(self, trainer) -> float:
        if trainer.device.type == "cuda":
            end = torch.cuda.Event(enable_timing=True)
            end.record()
            end.synchronize()
            return self._start.elapsed_time(end)
        return 1e3 * (time.perf_counter() - self._start)

    def on_end(self, trainer, summary: dict[str, Any]) -> None:
        self.bar.close()


def measure(trainer, warmup: int, steps: int, quiet: bool) -> dict[str, Any]:
    """Warm `trainer` up, time `steps` steps; returns the row of one scene and variant."""
    hook = TimeSteps(warmup, steps, progress=not quiet)
    trainer.run(hooks=[hook])
    if hook.ms is None:
        raise InputError(f"the run ended after {trainer.step_count} steps, before the timing")
    hist = trainer.history[-steps:]

    def mean(key: str) -> float | None:
        vals = [float(h[key]) for h in hist if key in h]
        return sum(vals) / len(vals) if vals else None

    graph = trainer.graph
    return {
        "ms_per_step": hook.ms,
        "samples_per_ray": mean("samples_per_ray"),
        "marched_per_ray": mean("marched_per_ray"),
        "step_mode": trainer.step_mode,
        "captures": None if graph is None else graph.captures,
        "replays": None if graph is None else graph.replays,
        "graph_failure": None if graph is None else graph.failure,
        "progress": trainer.progress(),
    }


def markdown(res: dict[str, Any]) -> str:
    """The results as a markdown table (scene, variant, ms/step, ratio, samples, mode)."""
    s = res["session"]
    cpu = " (CPU numbers: no GPU time)" if s["machine"]["cpu_numbers"] else ""
    lines = [
        f"# Step time on {s['machine']['name']}{cpu}, commit {s['git_commit']}",
        "",
        f"{res['steps']} steps timed after {res['warmup']} warm-up steps, budget clock "
        f"{res['budget_s']:.0f} s; ratio: against the scene's first variant, same process.",
        "",
        "| scene | variant | ms/step | ratio | samples/ray (marched) | mode (captures) |",
        "|---|---|---:|---:|---:|---|",
    ]
    for r in res["rows"]:
        spr = "–" if r["samples_per_ray"] is None else f"{r['samples_per_ray']:.1f}"
        if r["marched_per_ray"] is not None:
            spr += f" ({r['marched_per_ray']:.1f})"
        mode = r["step_mode"] + ("" if r["captures"] is None else f" ({r['captures']})")
        if r["graph_failure"]:
            mode += f", capture failed: {r['graph_failure']}"
        lines.append(
            f"| {r['scene']} | {r['variant']} | {r['ms_per_step']:.2f} | "
            f"{r['ratio']:.3f} | {spr} | {mode} |"
        )
    return "\n".join(lines) + "\n"


def run(args: argparse.Namespace) -> int:
    if args.steps < 1 or args.warmup < 0:
        raise InputError("--steps must be >= 1 and --warmup >= 0")
    if not args.budget_s > 0:
        raise InputError(f"--budget-s must be > 0, got {args.budget_s}")
    variants = [parse_variant(v) for v in (args.variant or ["default={}"])]
    names = [n for n, _ in variants]
    if len(set(names)) != len(names):
        raise InputError(f"--variant: names must differ, got {names}")
    device = resolve_device(args.device)
    scenes = [(Path(d), load_scene_dir(d)) for d in args.scene]  # every folder checked first
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    res: dict[str, Any] = dict(warmup=args.warmup, steps=args.steps, budget_s=args.budget_s)
    res.update(session=session_info(device, args.commit), rows=[])
    for path, scene in scenes:
        first = None
        for name, spec in variants:
            trainer = build(scene, f"run_{path.name}_{name}", spec, args.budget_s, out, str(device))
            row = measure(trainer, args.warmup, args.steps, args.quiet)
            first = row["ms_per_step"] if first is None else first
            row.update(scene=path.resolve().name, variant=name, spec=spec)
            row["ratio"] = row["ms_per_step"] / first
            res["rows"].append(row)
            del trainer
            gc.collect()  # a trainer's cycles hold its graphs and buffers until collected
            if device.type == "cuda":
                torch.cuda.empty_cache()
            write_json(out / "step_time.json", jsonable(res))  # each row as it comes
    write_report(out, "step_time", res, markdown(res))
    return 0


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scene", action="append", required=True, help="scene folder (repeatable)")
    p.add_argument(
        "--variant",
        action="append",
        metavar="NAME=JSON",
        help='options of one variant, e.g. refine={"train":{"refine_poses":true}} (repeatable)',
    )
    p.add_argument("--warmup", type=int, default=1000, help="steps before the timed ones")
    p.add_argument("--steps", type=int, default=320, help="steps timed")
    p.add_argument("--budget-s", type=float, default=60.0, help="the schedules' budget (s)")
    add_run_arguments(p, "runs/bench/step_time")


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    return benchmark_main("step_time", __doc__, add_arguments, run, argv, prog, out_folder=True)


if __name__ == "__main__":
    raise SystemExit(main())
