"""`fastenerf train-many`: several scenes (x backends), one run folder each, spread over ranks.

    fastenerf train-many A B C --out DIR --backends ngp vanilla --minutes 2
    torchrun --standalone --nproc-per-node 4 -m fastenerf.cli train-many A B C --out DIR ...

Each (scene, backend) is an ordinary run folder, DIR/runs/<scene>-<backend>/, trained by the
one training loop with `fastenerf train`'s hooks plus a final quick evaluation. Under torchrun
every rank trains its share (`fastenerf.distributed.my_share`) on cuda:LOCAL_RANK (or the
CPU); after a barrier, rank 0 writes DIR/train_many.json and DIR/train_many.md (scene,
backend, steps, train seconds, quick PSNR, which rank). `--resume` continues the runs that
have a checkpoint and skips the finished ones; without it an existing run is refused.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

HELP = "train several scenes/backends, one run folder each, shared out over torchrun's ranks"
SUMMARY = "train_many"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scenes", nargs="+", metavar="SCENE_DIR", help="native scene folders")
    p.add_argument(
        "--out",
        metavar="DIR",
        required=True,
        help="folder for runs/<scene>-<backend>/ and the summary train_many.json / .md",
    )
    p.add_argument(
        "--backends", nargs="+", choices=["ngp", "vanilla"], default=["ngp"], help="default ngp"
    )
    p.add_argument("--preset", choices=["eventnerf", "fast"], default=None, help="default fast")
    budget = p.add_mutually_exclusive_group()
    budget.add_argument("--minutes", type=float, help="training-time budget of each run")
    budget.add_argument("--steps", type=int, help="step budget of each run")
    p.add_argument(
        "--resume", action="store_true", help="continue unfinished runs, skip finished ones"
    )
    p.add_argument("--seed", type=int, default=None, help="random seed (default 0)")
    p.add_argument("--rays", type=int, default=None, dest="rays_per_step", help="pixels per step")
    p.add_argument("--lr", type=float, default=None, help="initial learning rate")
    p.add_argument(
        "--device", default=None, help="auto (default: cuda:LOCAL_RANK or the CPU), cpu, ..."
    )
    p.add_argument("--options", metavar="JSON", default=None, help="backend options as JSON")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")


def plan(args: argparse.Namespace) -> list[dict]:
    """The jobs, in a fixed order (the same on every rank): scenes x backends."""
    from ..errors import InputError

    labels: list[str] = []
    for s in args.scenes:
        path = Path(s)
        if not path.is_dir():
            raise InputError(f"{s}: no such scene folder")
        name = path.absolute().name
        label, k = name, 2
        while label in labels:  # two folders of one name (a/scene, b/scene)
            label, k = f"{name}-{k}", k + 1
        labels.append(label)
    runs = Path(args.out) / "runs"
    pairs = [(lab, s, b) for lab, s in zip(labels, args.scenes, strict=True) for b in args.backends]
    return [
        {"index": i, "label": lab, "scene": s, "backend": b, "run_dir": str(runs / f"{lab}-{b}")}
        for i, (lab, s, b) in enumerate(pairs)
    ]


def check_existing(jobs: list[dict], resume: bool) -> None:
    """Without --resume, refuse before any training if a job's run folder holds a run."""
    from ..errors import InputError
    from ..run import CHECKPOINT

    if resume:
        return
    held = [j["run_dir"] for j in jobs if (Path(j["run_dir"]) / CHECKPOINT).exists()]
    if held:
        raise InputError(
            f"{held[0]}: already holds a training run ({len(held)} of the {len(jobs)} runs do); "
            "pass --resume to continue them or choose another --out"
        )


def job_cost(args: argparse.Namespace):
    """Expected seconds of a job for `my_share`'s balance: a time budget is exact; without
    one, round-robin (None)."""
    if args.minutes is None:
        return None
    return lambda job: 60.0 * args.minutes


def run(args: argparse.Namespace) -> int:
    from ..distributed import FAN_OUT_TIMEOUT_S, gather, my_share, process_group
    from ..errors import InputError
    from ..hooks import StopOnSignal
    from ..outputs import bench_kind, claim_output

    out = claim_output(args.out, bench_kind(SUMMARY), force=None)
    jobs = plan(args)
    check_existing(jobs, args.resume)
    # gloo for any device: the fan-out only meets at a barrier and hands rank 0 small dicts.
    with process_group("gloo", timeout_s=FAN_OUT_TIMEOUT_S) as world:
        mine = my_share(jobs, world, job_cost(args))
        names = ", ".join(f"{j['label']}-{j['backend']}" for j in mine) or "none"
        print(f"rank {world.rank}/{world.size}: {len(mine)} of {len(jobs)} runs ({names})")
        sys.stdout.flush()
        stop = StopOnSignal()  # one for all: after a Ctrl-C no further run starts
        results = [train_job(job, args, world, stop) for job in mine]
        everyone = gather(results, world)
    if everyone is None:
        return 0
    rows = sorted((r for share in everyone for r in share), key=lambda r: r["index"])
    paths = write_summary(out, rows, world.size, args)
    print(markdown_table(rows))
    print(f"wrote {paths[0]} and {paths[1]}")
    failed = [r for r in rows if r["status"] == "failed"]
    if failed:
        raise InputError(
            f"{len(failed)} of {len(rows)} runs failed; first: {failed[0]['label']}-"
            f"{failed[0]['backend']}: {failed[0]['error']}"
        )
    return 0


def train_job(job: dict, args: argparse.Namespace, world, stop) -> dict:
    """Train (or resume, or skip when finished) one job's run; its row of the summary.

    A job that fails (bad scene, diverged) is a row with status "failed" and the one-line
    error; the other jobs go on.
    """
    from ..data.formats import load_scene_folder
    from ..errors import FastenerfError
    from ..fan_out import fan_out_hooks
    from ..run import CHECKPOINT, read_progress
    from ..train import Trainer
    from .train import build_config

    row = {**job, "rank": world.rank, "status": "failed", "error": None}
    row.update(steps=None, train_seconds=None, psnr=None)
    run_dir = Path(job["run_dir"])
    resume = bool(args.resume and (run_dir / CHECKPOINT).exists())
    name = f"{job['label']}-{job['backend']}"
    try:
        ns = argparse.Namespace(**{**vars(args), "out": str(run_dir), "resume": resume})
        ns.backend = job["backend"]
        cfg = build_config(ns)
        if args.device is None:  # this rank's GPU, also for a run another rank started
            cfg.device = str(world.device)
        progress = read_progress(run_dir) if resume else {}
        if progress.get("finished") and budget_met(cfg, progress):
            print(f"rank {world.rank}: {name} finished before: skipped", flush=True)
            row.update(status="skipped", steps=progress.get("step"), error=None)
            row.update(train_seconds=progress.get("train_seconds"))
            row.update(psnr=progress.get("last_eval_psnr"))
            return row
        if stop.received:
            row.update(status="interrupted")
            return row
        scene = load_scene_folder(job["scene"])
        trainer = Trainer(scene, cfg, run_dir, resume=resume)
        print(f"rank {world.rank}: training {name} on {trainer.device}", flush=True)
        bars = not args.no_progress and world.size == 1
        summary = trainer.run(fan_out_hooks(trainer, stop, bars))
    except FastenerfError as e:
        print(f"rank {world.rank}: {name} failed: {e}", flush=True)
        row["error"] = str(e)
        return row
    status = "resumed" if resume else "trained"
    if summary["failure"] or summary["interrupted"]:
        status = "failed" if summary["failure"] else "interrupted"
    row.update(status=status, error=summary["failure"], steps=summary["steps"])
    row.update(train_seconds=summary["train_seconds"], psnr=summary["last_eval_psnr"])
    return row


def budget_met(cfg, progress: dict) -> bool:
    """Whether a run's last checkpoint (progress.json) already spent the budget of `cfg`."""
    if cfg.steps is not None and progress.get("step", 0) < cfg.steps:
        return False
    return cfg.minutes is None or progress.get("train_seconds", 0.0) >= 60.0 * cfg.minutes


def write_summary(out: Path, rows: list[dict], world_size: int, args) -> tuple[Path, Path]:
    from ..io import atomic_path, write_json

    budget = {"minutes": args.minutes, "steps": args.steps}
    j = write_json(
        out / f"{SUMMARY}.json",
        {"world_size": world_size, "budget": budget, "runs": rows},
    )
    md = out / f"{SUMMARY}.md"
    with atomic_path(md) as tmp:
        tmp.write_text(markdown_table(rows) + "\n")
    return j, md


def markdown_table(rows: list[dict]) -> str:
    """The summary as a Markdown table, one row per run."""

    def num(x, fmt):
        return "—" if x is None else format(x, fmt)

    lines = [
        "| scene | backend | status | steps | train s | quick PSNR (dB) | rank |",
        "| --- | --- | --- | ---: | ---: | ---: | ---: |",
    ]
    for r in rows:
        lines.append(
            f"| {r['label']} | {r['backend']} | {r['status']} | {num(r['steps'], 'd')} | "
            f"{num(r['train_seconds'], '.1f')} | {num(r['psnr'], '.2f')} | {r['rank']} |"
        )
    return "\n".join(lines)
