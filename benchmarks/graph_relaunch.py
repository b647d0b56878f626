"""Whether replaying one CUDA graph back to back idles the device between replays (#17).

    python -m benchmarks.graph_relaunch --scene DATA/blocks [--device cuda] [--warmup 1000]
        [--replays 200] [--out OUT]

Trains `--warmup` steps of ngp's fast preset so that its step is replayed from a graph (A),
captures the same step once more into a second graph (B, its own pool), then times, on the
device's clock (CUDA events), ms per replay of:

- **alone**: A with the device drained before each replay: the graph's own time;
- **back to back**: A replayed `--replays` times with the host free to run ahead, as in
  training, where the launch queue stays full;
- **alternating**: A and B in turn, likewise;
- **as trained**: back to back through the trainer's graphed step: the batch copied into
  the graph's inputs, A replayed, the step's stats copied out.

If back to back costs more per replay than alone, relaunching an executable graph while its
previous launch is still queued idles the device by the difference; if alternating costs
less, capturing the step twice would win it back. Why: gpu_s49's profiles find ~1 ms a step
of device idle with the host ahead of the device and no sync in the step, and the kernel
that ends most of it is a `Memset (Device)`, as a graph's first node would be.
Outputs OUT/graph_relaunch.json and .md. Needs CUDA (no graph is captured elsewhere).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch

from benchmarks.cli import add_run_arguments, benchmark_main
from benchmarks.curve import load_scene_dir, make_config
from benchmarks.session import session_info, write_report
from fastenerf.errors import InputError
from fastenerf.hooks import Hook
from fastenerf.run import resolve_device

PATTERNS = ("alone", "back to back", "alternating", "as trained")


def ms_per_call(fn: Callable[[int], None], n: int, device: torch.device) -> float:
    """Mean ms of `fn(i)` for i < n on `device`'s clock (CUDA events around the whole loop,
    the device drained before; the wall clock elsewhere), the calls free to queue."""
    if device.type != "cuda":
        t = time.perf_counter()
        for i in range(n):
            fn(i)
        return 1e3 * (time.perf_counter() - t) / n
    torch.cuda.synchronize(device)
    start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
    start.record()
    for i in range(n):
        fn(i)
    end.record()
    end.synchronize()
    return start.elapsed_time(end) / n


def ms_alone(fn: Callable[[int], None], n: int, device: torch.device) -> float:
    """Median ms of one `fn(i)` with the device drained before and after each call."""
    times = [ms_per_call(lambda _j, i=i: fn(i), 1, device) for i in range(n)]
    return statistics.median(times)


def relaunch_times(replays: dict[str, Callable[[int], None]], n: int, device) -> dict:
    """ms per replay of each of PATTERNS, whose functions `replays` gives (i: the call's
    index), and the three ratios to `alone`."""
    ms = {"alone": ms_alone(replays["alone"], n, device)}
    for name in PATTERNS[1:]:
        ms[name] = ms_per_call(replays[name], n, device)
    return {"ms": ms, "over_alone": {k: ms[k] / ms["alone"] for k in PATTERNS[1:]}}


class UntilGraphed(Hook):
    """Stops the run after `warmup` steps once its step replays a captured graph (within 64
    more steps: a capacity change may just have dropped it)."""

    def __init__(self, warmup: int):
        self.warmup, self.steps = warmup, 0

    def after_step(self, trainer, stats: dict) -> None:
        self.steps += 1
        done = self.steps >= self.warmup and trainer.graph.graph is not None
        if done or self.steps >= self.warmup + 64:
            trainer.request_stop()


def trained_graphs(scene, device: torch.device, warmup: int, run_dir: Path):
    """(trainer, A, B): a trainer `warmup` steps into a run whose step replays graph A, and
    B, a second capture of that step."""
    from fastenerf.train import Trainer

    cfg = make_config("ngp", "fast", 300.0, str(device))
    trainer = Trainer(scene, cfg, run_dir)
    graphed = trainer.graph
    if graphed is None or not graphed.capture:
        raise InputError(f"no graphed step on {device} (it needs CUDA and a capturable step)")
    trainer.run(hooks=[UntilGraphed(warmup)])
    if graphed.graph is None:
        raise InputError("the step was not captured within 64 steps after the warm-up")
    return trainer, graphed.graph, graphed.capture_copy(trainer.sampler.sample())


def run(args: argparse.Namespace) -> int:
    if args.replays < 2 or args.warmup < 0:
        raise InputError("--replays must be >= 2 and --warmup >= 0")
    device = resolve_device(args.device)
    if device.type != "cuda":
        raise InputError(f"--device {device}: graph_relaunch needs CUDA (graphs are captured)")
    scene = load_scene_dir(args.scene)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    trainer, a, b = trained_graphs(scene, device, args.warmup, out / "run")
    graphed = trainer.graph
    batch = trainer.sampler.sample()

    replays = {
        "alone": lambda _i: a.replay(),
        "back to back": lambda _i: a.replay(),
        "alternating": lambda i: (a if i % 2 == 0 else b).replay(),
        "as trained": lambda _i: graphed(batch),  # inputs in, A replayed, stats copied out
    }
    res = relaunch_times(replays, args.replays, device)
    res.update(
        scene=Path(args.scene).resolve().name,
        warmup=args.warmup,
        replays=args.replays,
        rays_per_step=trainer.cfg.rays_per_step,
        session=session_info(device, args.commit),
    )
    write_report(out, "graph_relaunch", res, markdown(res))
    return 0


def markdown(res: dict) -> str:
    ms, over = res["ms"], res["over_alone"]
    lines = [
        f"### Replaying the training step's graph — {res['scene']}, "
        f"{res['rays_per_step']} pixels a step, after {res['warmup']} steps",
        "",
        f"{res['replays']} replays each, device clock; alone: the device drained before each.",
        "",
        "| replays | ms per replay | over alone |",
        "|---|---:|---:|",
        f"| alone | {ms['alone']:.3f} | — |",
    ]
    lines += [f"| {k} | {ms[k]:.3f} | {over[k]:.3f}× |" for k in PATTERNS[1:]]
    return "\n".join(lines) + "\n"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scene", required=True, help="scene folder")
    p.add_argument("--warmup", type=int, default=1000, help="training steps before timing")
    p.add_argument("--replays", type=int, default=200, help="replays per pattern")
    add_run_arguments(p, "runs/bench/graph_relaunch")


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    return benchmark_main("graph_relaunch", __doc__, add_arguments, run, argv, prog, True)


if __name__ == "__main__":
    sys.exit(main())
