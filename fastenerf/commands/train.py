"""`fastenerf train`: train a radiance field on a scene folder's events.

Every `TrainConfig` field is a flag (`win_max` -> `--win-max`) whose help is the field's
docstring (fastenerf/config.py); flags not given keep the preset's value (or, with --resume,
the run's). Bad values stop here with one line, before anything is written.
"""

from __future__ import annotations

import argparse
import json

HELP = "train a radiance field (ngp or vanilla backend) from a scene folder's events"

# TrainConfig fields with a flag of their own below (or none: backend_options is --options).
_SPECIAL = ("backend", "preset", "steps", "minutes", "backend_options", "perturb")
_ALIASES = {"rays_per_step": ["--rays"]}


def add_arguments(p: argparse.ArgumentParser) -> None:
    import dataclasses

    from ..backends import BACKEND_NAMES, MarcherOptions
    from ..config import TRAIN_PRESETS, TrainConfig
    from ..schema import add_flags, field_docs

    p.add_argument(
        "scene", metavar="SCENE_DIR", help="scene folder: native (scene.json) or EventNeRF"
    )
    p.add_argument("--out", metavar="RUN_DIR", required=True, help="run folder to write")
    p.add_argument(
        "--backend",
        choices=list(BACKEND_NAMES),
        default=None,
        help="field backend (default ngp; on --resume: the run's)",
    )
    p.add_argument(
        "--preset",
        choices=list(TRAIN_PRESETS),
        default=None,
        help="eventnerf: the reference's settings; fast (default): ours for speed",
    )
    p.add_argument(
        "--resume",
        action="store_true",
        help="continue the run in RUN_DIR; --steps / --minutes are then the run's TOTAL budget "
        "(steps and time already trained count), not additional ones",
    )
    budget = p.add_argument_group("budget (whichever of the two given; default 1 minute)")
    add_flags(budget.add_mutually_exclusive_group(), TrainConfig, ["steps", "minutes"])
    p.add_argument(
        "--options",
        metavar="JSON",
        default=None,
        help="backend options as JSON, nested by section or flat, e.g. "
        '\'{"marcher": {"cone_angle": 0}}\' or \'{"depth": 4, "width": 128}\' '
        "(see fastenerf/backends.py)",
    )
    p.add_argument(
        "--cone-angle",
        type=float,
        default=None,
        metavar="X",
        help="ngp only: " + field_docs(MarcherOptions)["cone_angle"].replace("%", "%%"),
    )
    p.add_argument(
        "--cylinder",
        metavar="R,YMIN,YMAX",
        default=None,
        help="density clip: zero density outside x²+z² <= R², YMIN <= y <= YMAX (world units, "
        "y the turntable axis); 'none' removes the scene's. Default: the scene's (an EventNeRF "
        "real scene of a released name gets the authors' clip). ngp's box shrinks to it.",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument(
        "--data-parallel",
        action="store_true",
        help="under torchrun: the ranks train this one run together, each on its own "
        "--rays pixels per step (fastenerf.data_parallel)",
    )
    knobs = p.add_argument_group(
        "training options (default: the preset's, else the scene's or device's)"
    )
    names = [f.name for f in dataclasses.fields(TrainConfig) if f.name not in _SPECIAL]
    add_flags(knobs, TrainConfig, names, aliases=_ALIASES)
    _add_perturb_flags(p)


def _add_perturb_flags(p: argparse.ArgumentParser) -> None:
    """The robustness studies' perturbations of the training data (TrainConfig.perturb)."""
    from ..config import PerturbConfig
    from ..schema import add_flags, field_docs

    group = p.add_argument_group("perturbations of the training data (robustness studies)")
    add_flags(group, PerturbConfig, ["pose_error_deg", "mount_error_deg", "noise_fraction"])
    group.add_argument(
        "--perturb-seed",
        type=int,
        default=None,
        metavar="N",
        help=field_docs(PerturbConfig)["seed"].replace("%", "%%"),
    )


def _perturb_flags(args: argparse.Namespace) -> dict:
    """{PerturbConfig field: value} of the perturbation flags given."""
    given = {
        "pose_error_deg": getattr(args, "pose_error_deg", None),
        "mount_error_deg": getattr(args, "mount_error_deg", None),
        "noise_fraction": getattr(args, "noise_fraction", None),
        "seed": getattr(args, "perturb_seed", None),
    }
    return {k: v for k, v in given.items() if v is not None}


def _train_flags(args: argparse.Namespace) -> dict:
    """{TrainConfig field: value} of the training flags given on the command line."""
    import dataclasses

    from ..config import TrainConfig

    skip = ("backend_options", "perturb")
    names = [f.name for f in dataclasses.fields(TrainConfig) if f.name not in skip]
    return {k: getattr(args, k) for k in names if getattr(args, k, None) is not None}


def _options(args: argparse.Namespace) -> dict | None:
    import dataclasses

    from ..config import TrainConfig
    from ..errors import InputError
    from ..schema import flag_name

    if not args.options:
        return None
    try:
        options = json.loads(args.options)
    except json.JSONDecodeError as e:
        raise InputError(f"--options is not valid JSON ({e})") from None
    if not isinstance(options, dict):
        raise InputError("--options must be a JSON object")
    train_keys = {f.name for f in dataclasses.fields(TrainConfig)}
    for key in options:
        if key in train_keys:
            raise InputError(
                f"--options: '{key}' is a training option, not a backend option: "
                f"use {flag_name(key)}"
            )
    return options


def check_flags(args: argparse.Namespace) -> None:
    """Refuse what the config's ranges allow but a command line cannot mean."""
    from ..errors import InputError

    if args.steps == 0 or args.minutes == 0:
        raise InputError(
            f"--{'steps' if args.steps == 0 else 'minutes'} 0: nothing to train "
            "(give a positive budget)"
        )
    if getattr(args, "device", None) and args.device != "cpu" and args.device != "auto":
        from ..config import DEVICE_PATTERN

        if DEVICE_PATTERN.match(args.device) is None:
            raise InputError(f"--device: must be auto, cpu, cuda or cuda:N, got {args.device!r}")
        import torch

        if not torch.cuda.is_available():
            raise InputError(f"--device {args.device}: CUDA is not available on this machine")
        index = int(args.device.partition(":")[2] or 0)
        if index >= torch.cuda.device_count():
            raise InputError(
                f"--device {args.device}: only {torch.cuda.device_count()} CUDA device(s)"
            )


def build_config(args: argparse.Namespace):
    """The TrainConfig the flags ask for; on --resume the run's own config with a new budget."""
    from pathlib import Path

    from ..backends import set_option
    from ..config import TrainConfig, train_preset
    from ..errors import InputError

    check_flags(args)
    options = _options(args)
    flags = _train_flags(args)
    conf_path = Path(args.out) / "config.json"
    if args.resume and conf_path.is_file():
        from ..run import read_run_config

        cfg = TrainConfig.from_dict(read_run_config(args.out)["train"], str(conf_path))
        # Flags given now must agree with the run (the trainer checks); the budget may change.
        for key, value in flags.items():
            setattr(cfg, key, value)
        if options is not None:
            cfg.backend_options = options
        if args.minutes is not None:
            cfg.steps = None
        if args.steps is not None:
            cfg.minutes = None
    else:
        backend = args.backend or "ngp"
        flags = {k: v for k, v in flags.items() if k not in ("backend", "preset")}
        cfg = train_preset(args.preset or "fast", backend, backend_options=options, **flags)
    cone = getattr(args, "cone_angle", None)  # train-many shares this without the flag
    if cone is not None:
        if cfg.backend != "ngp":
            raise InputError(f"--cone-angle: an ngp option (the backend is {cfg.backend})")
        cfg.backend_options = set_option("ngp", cfg.backend_options, "cone_angle", cone)
    for key, value in _perturb_flags(args).items():
        setattr(cfg.perturb, key, value)
    return cfg.validate()


def scene_cylinder(args: argparse.Namespace, scene, cylinder) -> None:
    """Set the loaded scene's clip: `cylinder` (parsed --cylinder: a CylinderConfig, None for
    'none', or ... when not given: then the scene's own, on --resume the run's)."""
    from pathlib import Path

    from ..config import CylinderConfig, from_dict

    sc = scene.config
    if cylinder is not ...:
        sc.cylinder = cylinder
    elif args.resume and (Path(args.out) / "config.json").is_file():
        from ..run import read_run_config

        saved = read_run_config(args.out).get("scene", {}).get("cylinder")
        sc.cylinder = None if saved is None else from_dict(CylinderConfig, saved, "run config")
    sc.validate(f"{args.scene} (with --cylinder)" if args.cylinder else str(args.scene))


def run(args: argparse.Namespace) -> int:
    from ..config import CylinderConfig
    from ..data.formats import load_scene_folder
    from ..errors import InputError
    from ..outputs import RUN, claim_output
    from ..train import Trainer

    claim_output(args.out, RUN, force=None)
    progress = not args.no_progress
    cfg = build_config(args)
    cylinder = ... if args.cylinder is None else CylinderConfig.parse(args.cylinder)
    scene = load_scene_folder(args.scene)
    scene_cylinder(args, scene, cylinder)
    hooks = None
    if args.data_parallel:
        from ..data_parallel import data_parallel_trainer

        trainer, hooks = data_parallel_trainer(scene, cfg, args.out, args.resume, progress)
    else:
        trainer = Trainer(scene, cfg, args.out, resume=args.resume)
    c = trainer.cfg
    budget = f"{c.steps} steps" if c.steps is not None else f"{c.minutes:g} min"
    cyl = scene.config.cylinder
    print(
        f"training {c.backend} ({c.preset}) on {scene.config.name} "
        f"{scene.config.width}x{scene.config.height}, {len(scene.events):,} events, "
        f"{budget}, device {trainer.device}"
        + (f", clip r={cyl.radius:g} y {cyl.y_min:g}..{cyl.y_max:g}" if cyl else "")
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
