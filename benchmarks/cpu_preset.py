"""Side-by-side CPU training of several configurations: steps/s and PSNR at equal training time.

    python -m benchmarks.cpu_preset --scene DIR [--scene DIR ...] [--seconds 60] \
        [--variant NAME[=JSON] ...] [--threads N] [--out OUT]

On a shared machine a run's speed depends on what else runs, so the variants are not run one
after another: each trains in its own thread and they take turns, ONE STEP EACH (a baton passed
by a hook), so the load falls on all of them alike. A trainer's clock counts only its own steps;
every variant trains `--seconds` of its own steps. Then every run is evaluated on 10 test views
at full size (colour-corrected PSNR, SSIM), next to the PSNR of a constant-colour image (the
score of a field that learnt nothing but the mean colour).

A variant is a built-in name (see VARIANTS) or NAME=JSON with keys: backend (default ngp),
train (TrainConfig overrides), backend_options, optimizer ("auto": the trainer's; "dense":
torch.optim.Adam over the whole table, the optimiser before issue #18), threads (torch threads
during its steps; default --threads).
Outputs in OUT: cpu_preset.json and cpu_preset.md (the table for benchmarks/RESULTS.md).
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import threading
from pathlib import Path
from typing import Any

import numpy as np
import torch

from benchmarks.cli import benchmark_main
from benchmarks.curve import load_scene_dir, make_config
from benchmarks.session import session_info, write_report
from fastenerf.commands.demo import CPU_TRAIN
from fastenerf.errors import InputError
from fastenerf.hooks import Hook, default_hooks

EVAL_VIEWS = 10

# The CPU demo's vanilla network and learning rates (`fastenerf demo --backend vanilla`).
_DEMO_VANILLA = dict(CPU_TRAIN["vanilla"])
VANILLA_DEMO = {
    "backend": "vanilla",
    "backend_options": _DEMO_VANILLA.pop("backend_options"),
    "train": _DEMO_VANILLA,
}
# ngp at the GPU's sizes, with the 2-core CPU's batch of the time (512 pixels).
GPU_SIZES = {
    "train": {"rays_per_step": 512},
    "backend_options": {
        "log2_table_size": 19,
        "n_levels": 16,
        "max_resolution": 2048,
        "grid_resolution": 128,
        "dt_min": 0.0025,
        "hidden": 64,
    },
}
# Variants other than "preset" set every key of the CPU preset (fastenerf.cpu_preset), which
# fills the options a run leaves unset.
VARIANTS: dict[str, dict[str, Any]] = {
    # the CPU preset (fastenerf.cpu_preset) and the row-sparse Adam: what `train` runs now
    "preset": {},
    # ngp on a CPU before issue #18: the GPU sizes, 512 rays, dense Adam over the whole table
    "before": {**GPU_SIZES, "optimizer": "dense"},
    # the CPU demo's ngp options before issue #18 (it trained vanilla instead)
    "before-demo": {
        "train": {"rays_per_step": 512},
        "backend_options": {
            "log2_table_size": 16,
            "n_levels": 16,
            "max_resolution": 512,
            "grid_resolution": 64,
            "dt_min": 0.02,
            "hidden": 64,
        },
        "optimizer": "dense",
    },
    # the preset with dense torch Adam: the optimiser's share
    "preset-dense": {"optimizer": "dense"},
    # the GPU sizes with today's optimiser (RowSparseAdam: the table is over its threshold)
    "gpu-sizes": GPU_SIZES,
    "vanilla-demo": VANILLA_DEMO,
}


class Baton:
    """Turns for n threads in a ring: `wait(i)` blocks until it is i's turn."""

    def __init__(self, n: int):
        self.cond = threading.Condition()
        self.active = list(range(n))
        self.turn = 0

    def wait(self, i: int) -> None:
        with self.cond:
            self.cond.wait_for(lambda: self.turn == i)

    def _advance(self, i: int) -> None:
        later = [j for j in self.active if j > i]
        self.turn = (later or self.active or [-1])[0]
        self.cond.notify_all()

    def pass_on(self, i: int) -> None:
        with self.cond:
            self._advance(i)

    def leave(self, i: int) -> None:
        with self.cond:
            self.active.remove(i)
            if self.turn == i:
                self._advance(i)


class TakeTurns(Hook):
    """One step, then the next variant's: the first hook of every trainer (its on_end last)."""

    def __init__(self, baton: Baton, i: int, threads: int):
        self.baton, self.i, self.threads = baton, i, threads

    def _my_turn(self) -> None:
        self.baton.wait(self.i)
        torch.set_num_threads(self.threads)

    def on_start(self, trainer) -> None:
        self._my_turn()

    def after_step(self, trainer, stats: dict[str, Any]) -> None:
        self.baton.pass_on(self.i)
        self._my_turn()

    def on_end(self, trainer, summary: dict[str, Any]) -> None:
        self.baton.leave(self.i)


def parse_variant(text: str) -> tuple[str, dict]:
    name, _, spec = text.partition("=")
    if not spec:
        if name not in VARIANTS:
            raise InputError(f"--variant {name}: unknown (built-in: {', '.join(VARIANTS)})")
        return name, VARIANTS[name]
    try:
        v = json.loads(spec)
    except json.JSONDecodeError as e:
        raise InputError(f"--variant {name}: not JSON ({e})") from None
    if not isinstance(v, dict):
        raise InputError(f"--variant {name}: must be a JSON object")
    return name, v


def build(scene, name: str, v: dict, seconds: float, out: Path, device: str = "cpu"):
    """The trainer of variant `v` in OUT/NAME (an earlier run there is replaced)."""
    from fastenerf.kernels.rows import ATTR
    from fastenerf.train import Trainer

    backend, opts = v.get("backend", "ngp"), v.get("backend_options")
    cfg = make_config(backend, "fast", seconds, device, v.get("train"), opts)
    if (out / name).exists():
        shutil.rmtree(out / name)  # this benchmark's own run folder of an earlier call
    tr = Trainer(scene, cfg, out / name)
    if v.get("optimizer", "auto") == "dense":
        table = getattr(tr.field, "table", None)
        if table is not None and hasattr(table, ATTR):
            delattr(table, ATTR)  # no row records: the backward before issue #18
        c = tr.cfg
        tr.optimizer = torch.optim.Adam(
            tr.optimizer.param_groups, lr=c.lr, betas=tuple(c.adam_betas), eps=c.adam_eps
        )
    return tr


def race(trainers: list, threads: list[int]) -> list[dict]:
    """Train all trainers in turns, one step each; returns their run summaries."""
    baton = Baton(len(trainers))
    summaries: list[dict] = [{} for _ in trainers]

    def go(i: int) -> None:
        tr = trainers[i]
        hooks = [TakeTurns(baton, i, threads[i]), *default_hooks(tr, progress=False)]
        summaries[i] = tr.run(hooks=hooks)

    workers = [threading.Thread(target=go, args=(i,)) for i in range(len(trainers))]
    for w in workers:
        w.start()
    for w in workers:
        w.join()
    return summaries


def constant_psnr(scene, views: int = EVAL_VIEWS) -> float:
    """PSNR of a constant grey image after the same colour correction, on the same views."""
    from fastenerf.evaluate import make_eval_set, quick_psnr

    gt = make_eval_set(scene, views).gt
    return quick_psnr(np.full_like(gt, 0.5), gt)


def score(tr, summary: dict, name: str, v: dict, scene_name: str) -> dict:
    from fastenerf.evaluate import evaluate_run

    m = evaluate_run(tr.out_dir, max_views=EVAL_VIEWS, progress=False)
    hist = tr.history[-100:]
    spr = [h["samples_per_ray"] for h in hist if "samples_per_ray" in h]
    steps, secs = summary["steps"], summary["train_seconds"]
    return {
        "scene": scene_name,
        "variant": name,
        "spec": v,
        "backend": tr.cfg.backend,
        "rays_per_step": tr.cfg.rays_per_step,
        "backend_options": tr.cfg.backend_options,
        "steps": steps,
        "train_seconds": secs,
        "steps_per_s": steps / max(secs, 1e-9),
        "samples_per_ray": float(np.mean(spr)) if spr else None,
        "psnr": m["psnr"],
        "ssim": m["ssim"],
        "sheet": m["sheet"],
    }


def run_scene(scene_dir: str, variants: list, args, out: Path) -> list[dict]:
    scene = load_scene_dir(scene_dir)
    name = Path(scene_dir).resolve().name
    trainers = [build(scene, vn, v, args.seconds, out / name) for vn, v in variants]
    threads = [int(v.get("threads", args.threads)) for _, v in variants]
    summaries = race(trainers, threads)
    const = constant_psnr(scene)
    rows = []
    for tr, s, (vn, v) in zip(trainers, summaries, variants, strict=True):
        row = score(tr, s, vn, v, name)
        row["constant_psnr"] = const
        rows.append(row)
        print(_row_md(row), flush=True)
    return rows


def _row_md(r: dict) -> str:
    spr = "—" if r["samples_per_ray"] is None else f"{r['samples_per_ray']:.1f}"
    return (
        f"| {r['scene']} | {r['variant']} | {r['steps']} | {r['steps_per_s']:.2f} | "
        f"{1e3 / max(r['steps_per_s'], 1e-9):.0f} | {spr} | {r['psnr']:.2f} | {r['ssim']:.3f} | "
        f"{r['constant_psnr']:.2f} | {r['psnr'] - r['constant_psnr']:+.2f} |"
    )


def markdown(res: dict) -> str:
    m = res["session"]["machine"]
    lines = [
        f"### CPU training side by side — {res['seconds']:g} s of training each, "
        f"{m['name']}, torch threads {res['threads']}",
        "",
        "Variants take turns one step each (the machine's load falls on all alike); PSNR and "
        f"SSIM colour-corrected on {EVAL_VIEWS} test views at full size; constant: a grey image "
        "after the same correction.",
        "",
        "| scene | variant | steps | steps/s | ms/step | samples/ray | PSNR | SSIM | constant "
        "| Δ constant |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|",
        *(_row_md(r) for r in res["rows"]),
        "",
    ]
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    if args.seconds <= 0:
        raise InputError("--seconds must be positive")
    variants = [parse_variant(t) for t in (args.variant or ["before-demo", "preset"])]
    if len({n for n, _ in variants}) != len(variants):
        raise InputError("--variant: names must differ")
    out = Path(args.out)
    session = session_info(torch.device("cpu"), args.commit)
    rows: list[dict] = []
    for scene_dir in args.scene:
        rows += run_scene(scene_dir, variants, args, out)
    res = {"seconds": args.seconds, "threads": args.threads, "rows": rows, "session": session}
    write_report(out, "cpu_preset", res, markdown(res))
    return 0


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scene", action="append", required=True, help="scene folder (repeatable)")
    p.add_argument("--seconds", type=float, default=60.0, help="training seconds per variant")
    p.add_argument(
        "--variant",
        action="append",
        metavar="NAME[=JSON]",
        help=f"built-in ({', '.join(VARIANTS)}) or NAME=JSON (default: before-demo, preset)",
    )
    p.add_argument("--threads", type=int, default=torch.get_num_threads(), help="torch threads")
    p.add_argument("--out", default="runs/bench/cpu_preset")
    p.add_argument("--commit", default=None, help="git commit to record")


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    return benchmark_main("cpu_preset", __doc__, add_arguments, run, argv, prog, out_folder=True)


if __name__ == "__main__":
    sys.exit(main())
