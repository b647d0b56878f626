"""`fastenerf train`: train a radiance field on a scene folder's events."""

from __future__ import annotations

import argparse
import json

HELP = "train a radiance field (ngp or vanilla backend) from a scene folder's events"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene", metavar="SCENE_DIR", help="native scene folder (scene.json + events)")
    p.add_argument("--out", metavar="RUN_DIR", required=True, help="run folder to write")
    p.add_argument(
        "--backend",
        choices=["ngp", "vanilla"],
        default=None,
        help="field backend (default ngp; on --resume: the run's)",
    )
    p.add_argument(
        "--preset",
        choices=["eventnerf", "fast"],
        default=None,
        help="eventnerf: the reference's settings; fast (default): ours for speed",
    )
    budget = p.add_mutually_exclusive_group()
    budget.add_argument("--minutes", type=float, help="training-time budget (eval excluded)")
    budget.add_argument("--steps", type=int, help="step budget")
    p.add_argument("--resume", action="store_true", help="continue the run in RUN_DIR")
    p.add_argument("--seed", type=int, default=None, help="random seed (default 0)")
    p.add_argument(
        "--rays",
        type=int,
        default=None,
        dest="rays_per_step",
        help="pixels per step, each rendered at t0 and t1 (default: by preset/device)",
    )
    p.add_argument("--lr", type=float, default=None, help="initial learning rate")
    p.add_argument("--device", default=None, help="auto (default), cpu, cuda, cuda:1, ...")
    p.add_argument(
        "--options",
        metavar="JSON",
        default=None,
        help='backend options as JSON, e.g. \'{"depth": 4, "width": 128}\'',
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument(
        "--data-parallel",
        action="store_true",
        help="under torchrun: the ranks train this one run together, each on its own "
        "--rays pixels per step (fastenerf.data_parallel)",
    )


def build_config(args: argparse.Namespace):
    """The TrainConfig the flags ask for; on --resume the run's own config with a new budget."""
    from pathlib import Path

    from ..config import TrainConfig, train_preset
    from ..errors import InputError

    options = None
    if args.options:
        try:
            options = json.loads(args.options)
        except json.JSONDecodeError as e:
            raise InputError(f"--options is not valid JSON ({e})") from None
        if not isinstance(options, dict):
            raise InputError("--options must be a JSON object")
    conf_path = Path(args.out) / "config.json"
    if args.resume and conf_path.is_file():
        from ..run import read_run_config

        cfg = TrainConfig.from_dict(read_run_config(args.out)["train"], str(conf_path))
        # Flags given now must agree with the run (the trainer checks); the budget may change.
        for key in ("backend", "preset", "seed", "rays_per_step", "lr"):
            value = getattr(args, key)
            if value is not None:
                setattr(cfg, key, value)
        if options is not None:
            cfg.backend_options = options
        if args.minutes is not None:
            cfg.minutes, cfg.steps = args.minutes, None
        if args.steps is not None:
            cfg.steps, cfg.minutes = args.steps, None
        if args.device:
            cfg.device = args.device
        return cfg.validate()
    return train_preset(
        args.preset or "fast",
        args.backend or "ngp",
        minutes=args.minutes,
        steps=args.steps,
        seed=args.seed,
        rays_per_step=args.rays_per_step,
        lr=args.lr,
        device=args.device,
        backend_options=options,
    )


def run(args: argparse.Namespace) -> int:
    from ..data.formats import load_scene_folder
    from ..errors import InputError
    from ..outputs import RUN, claim_output
    from ..train import Trainer

    claim_output(args.out, RUN, force=None)
    progress = not args.no_progress
    cfg = build_config(args)
    scene = load_scene_folder(args.scene)
    hooks = None
    if args.data_parallel:
        from ..data_parallel import data_parallel_trainer

        trainer, hooks = data_parallel_trainer(scene, cfg, args.out, args.resume, progress)
    else:
        trainer = Trainer(scene, cfg, args.out, resume=args.resume)
    c = trainer.cfg
    budget = f"{c.steps} steps" if c.steps is not None else f"{c.minutes:g} min"
    print(
        f"training {c.backend} ({c.preset}) on {scene.config.name} "
        f"{scene.config.width}x{scene.config.height}, {len(scene.events):,} events, "
        f"{budget}, device {trainer.device}"
        + (f", resuming at step {trainer.step_count}" if args.resume else "")
    )
    summary = trainer.run(hooks, progress=progress)
    if summary["failure"]:
        raise InputError(summary["failure"])
    psnr = summary["last_eval_psnr"]
    print(
        f"{summary['steps']} steps in {summary['train_seconds']:.1f} s training "
        f"(+{summary['eval_seconds']:.1f} s quick eval)"
        + (f", final loss {summary['loss']:.4g}" if summary["loss"] is not None else "")
        + (f", quick PSNR {psnr:.2f} dB" if psnr is not None else "")
    )
    print(f"wrote {args.out}/ (config.json, checkpoint.pt, metrics.jsonl, progress.json)")
    if summary["interrupted"]:
        print(f"interrupted: resume with  fastenerf train {args.scene} --out {args.out} --resume")
        return 130
    return 0
