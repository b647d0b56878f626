"""What data-parallel training costs: the gradient all-reduce against a training step (#21).

    python -m benchmarks.allreduce [--ranks 2] [--backends ngp vanilla] [--out FILE.json]
    torchrun --standalone --nproc-per-node N -m benchmarks.allreduce --device cuda --out FILE.json

For each backend at its default configuration (the field `fastenerf train` builds, the
device's default batch): the parameters' sizes (ngp: the hash table), the median time of one
`fastenerf.data_parallel.GradientAverager.reduce()` over the ranks (gloo on the CPU, nccl on
CUDA: exactly what a data-parallel step adds), the median time of one training step of one
process (rank 0, the others waiting), and of one data-parallel step of all ranks together.
`scaling` = one process's step time / the data-parallel step time: the data-parallel run
trains N x the batch per step, so its throughput is N x scaling times one process's (issue
#21's target for vanilla on N GPUs: scaling >= 0.8).

Without torchrun the command starts `--ranks` processes itself (file rendezvous, one torch
thread each on the CPU). The scene is `--scene` or a tiny synthetic one made in a temporary
folder (64x48; the step's cost depends on the batch, not on the image size).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import torch
import torch.distributed as dist

from benchmarks.cli import benchmark_main
from benchmarks.session import jsonable, session_info
from fastenerf.backends import BACKEND_NAMES
from fastenerf.config import train_preset
from fastenerf.data_parallel import GradientAverager, make_data_parallel
from fastenerf.distributed import World, barrier, destroy, init, world_from_env
from fastenerf.hooks import Hook
from fastenerf.io import write_json


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--ranks", type=int, default=2, help="processes to start without torchrun")
    p.add_argument(
        "--backends", nargs="+", choices=list(BACKEND_NAMES), default=list(BACKEND_NAMES)
    )
    p.add_argument("--device", default="auto", help="auto (cuda:LOCAL_RANK or cpu), cpu")
    p.add_argument("--scene", default=None, help="scene folder (default: a tiny synthetic one)")
    p.add_argument("--preset", choices=["fast", "eventnerf"], default="fast", help="default fast")
    p.add_argument("--rays", type=int, default=None, help="pixels per step (default: device's)")
    p.add_argument("--reps", type=int, default=20, help="timed all-reduces")
    p.add_argument("--steps", type=int, default=5, help="timed training steps")
    p.add_argument("--warmup", type=int, default=2, help="untimed steps first (kernel builds)")
    p.add_argument("--out", default="runs/bench/allreduce.json", help="JSON file to write")


class StepTimes(Hook):
    """The training clock's increment of each step after `warmup` steps, in ms."""

    def __init__(self, warmup: int):
        self.warmup, self.ms, self.last = warmup, [], 0.0

    def on_start(self, trainer) -> None:
        self.last = trainer.train_seconds

    def after_step(self, trainer, stats: dict[str, Any]) -> None:
        if trainer.step_count > self.warmup:
            self.ms.append(1e3 * (trainer.train_seconds - self.last))
        self.last = trainer.train_seconds


def make_trainer(scene, backend: str, args, device: torch.device, out: Path):
    from fastenerf.train import Trainer

    cfg = train_preset(
        args.preset,
        backend,
        steps=args.warmup + args.steps,
        rays_per_step=args.rays,
        device=str(device),
        eval_every_s=0,
        checkpoint_every_s=0,
    )
    trainer = Trainer(scene, cfg, out)
    trainer.sync_clock = True  # the device's step time, not the host's queueing
    return trainer


def time_allreduce(trainer, world: World, reps: int) -> list[float]:
    """ms of each `GradientAverager.reduce()` of the field's parameters (gradients random)."""
    params = [p for g in trainer.optimizer.param_groups for p in g["params"]]
    avg = GradientAverager(params, world, trainer.device)
    ms = []
    for i in range(reps + 2):
        for p in params:
            p.grad = torch.randn_like(p)
        trainer.sync()
        barrier()
        t = time.perf_counter()
        avg.reduce(finite=True)
        trainer.sync()
        if i >= 2:  # the first two set up the connections' buffers
            ms.append(1e3 * (time.perf_counter() - t))
    return ms


def measure(backend: str, scene, args, world: World, scratch: Path) -> dict[str, Any]:
    """One backend's sizes and times (on rank 0; the other ranks return {})."""
    device = world.device if args.device == "auto" else torch.device(args.device)
    tr = make_trainer(scene, backend, args, device, scratch / f"{backend}-r{world.rank}-a")
    sizes = {n: p.numel() for n, p in tr.field.named_parameters()}
    reduce_ms = time_allreduce(tr, world, args.reps)
    single: list[float] = []
    if world.is_main:  # one process alone: the others wait at the barrier
        hook = StepTimes(args.warmup)
        tr.run([hook], progress=False)
        single = hook.ms
    barrier()
    dp = make_trainer(scene, backend, args, device, scratch / f"{backend}-r{world.rank}-b")
    sync = make_data_parallel(dp, world)
    hook = StepTimes(args.warmup)
    dp.run([hook, sync], progress=False)
    if not world.is_main:
        return {}
    step, dp_step, red = (statistics.median(x) for x in (single, hook.ms, reduce_ms))
    table = sizes.get("table", 0)
    return {
        "preset": tr.cfg.preset,
        "rays_per_step_per_rank": tr.cfg.rays_per_step,
        "params": sum(sizes.values()),
        "param_bytes": 4 * sum(sizes.values()),
        "table_params": table,
        "allreduce_ms": red,
        "allreduce_ms_all": reduce_ms,
        "step_ms": step,
        "step_ms_all": single,
        "dp_step_ms": dp_step,
        "dp_step_ms_all": hook.ms,
        "allreduce_over_step": red / step,
        "scaling": step / dp_step,
    }


def worker(args, world: World) -> dict[str, Any] | None:
    """Every rank's part; rank 0 returns the result."""
    from fastenerf.data.formats import load_scene_folder

    if world.device.type == "cpu" or args.device == "cpu":
        torch.set_num_threads(1)
    with tempfile.TemporaryDirectory(prefix=f"allreduce-r{world.rank}-") as tmp:
        scene_dir = args.scene or str(Path(tmp) / "scene")
        if args.scene is None:
            from fastenerf.data.synth import DEFAULT_SCENE, make_scene

            make_scene(DEFAULT_SCENE, scene_dir, width=64, height=48, frames=100)
        scene = load_scene_folder(scene_dir)
        results = {b: measure(b, scene, args, world, Path(tmp)) for b in args.backends}
    if not world.is_main:
        return None
    device = world.device if args.device == "auto" else torch.device(args.device)
    return {
        **session_info(device),
        "world_size": world.size,
        "process_group": dist.get_backend(),
        "load_average": list(os.getloadavg()),
        "backends": results,
    }


def _spawned(rank: int, size: int, rdzv: str, args) -> None:
    world = init("gloo", rank=rank, world_size=size, init_method=rdzv)
    try:
        result = worker(args, world)
        if result is not None:
            write_json(args.out, jsonable(result))
    finally:
        destroy()


def run(args: argparse.Namespace) -> int:
    env = world_from_env()
    if env.distributed:  # under torchrun
        world = init()
        try:
            result = worker(args, world)
        finally:
            destroy()
        if result is None:
            return 0
        write_json(args.out, jsonable(result))
    else:
        import torch.multiprocessing as mp

        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory() as tmp:
            mp.start_processes(
                _spawned,
                args=(args.ranks, f"file://{tmp}/rdzv", args),
                nprocs=args.ranks,
                start_method="spawn",
            )
        result = json.loads(Path(args.out).read_text())
    for b, r in result["backends"].items():
        print(
            f"{b}: {r['params'] / 1e6:.2f} M params; all-reduce {r['allreduce_ms']:.2f} ms over "
            f"{result['world_size']} ranks ({result['process_group']}); step {r['step_ms']:.1f} ms "
            f"alone, {r['dp_step_ms']:.1f} ms data-parallel (scaling {r['scaling']:.2f})"
        )
    print(f"wrote {args.out}")
    return 0


def main(argv: list[str] | None = None) -> int:
    return benchmark_main("allreduce", __doc__, add_arguments, run, argv)


if __name__ == "__main__":
    sys.exit(main())
