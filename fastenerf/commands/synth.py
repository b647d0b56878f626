"""`fastenerf synth`: render a built-in scene or a mesh on a turntable and simulate its events."""

from __future__ import annotations

import argparse

HELP = "make a synthetic scene: render a turntable revolution and simulate colour events"


def add_arguments(p: argparse.ArgumentParser) -> None:
    src = p.add_mutually_exclusive_group()
    src.add_argument("--scene", metavar="NAME", help="built-in scene (see --list)")
    src.add_argument("--mesh", metavar="PATH", help="your mesh (OBJ, GLB, PLY, ...), y-up")
    src.add_argument("--list", action="store_true", help="print the built-in scene names")
    p.add_argument(
        "--out",
        metavar="DIR",
        help="scene folder to write (an existing scene folder is replaced atomically)",
    )
    p.add_argument(
        "--force", action="store_true", help="replace --out even if it is not a scene folder"
    )
    p.add_argument(
        "--frames",
        type=int,
        default=1000,
        help="frames per revolution, 1 ms apart (default 1000: a 1 s loop)",
    )
    p.add_argument(
        "--size",
        metavar="WxH",
        default="346x260",
        help="sensor size (default 346x260, the DAVIS 346C)",
    )
    p.add_argument(
        "--bayer",
        choices=["rggb", "mono"],
        default="rggb",
        help="colour filter: rggb (default) or mono",
    )
    p.add_argument(
        "--threshold",
        type=float,
        default=0.25,
        help="contrast threshold, log intensity (default 0.25)",
    )
    p.add_argument(
        "--neg-threshold",
        type=float,
        default=None,
        help="negative contrast threshold when it differs (default: --threshold)",
    )
    p.add_argument(
        "--mismatch",
        type=float,
        default=0.0,
        help="per-pixel threshold mismatch: Gaussian sigma, log intensity (default 0)",
    )
    p.add_argument(
        "--noise",
        type=float,
        default=0.0,
        help="fraction of the stream that is uniform noise events (default 0)",
    )
    p.add_argument("--seed", type=int, default=0, help="noise seed (default 0)")
    p.add_argument(
        "--format",
        choices=["native", "eventnerf"],
        default="native",
        help="output layout: native scene folder (default) or EventNeRF dataset",
    )
    p.add_argument(
        "--supersample",
        type=int,
        default=1,
        help="render at N x resolution and box-filter (N² x 4 MSAA samples, ~N² x slower)",
    )
    p.add_argument(
        "--test-every",
        type=int,
        default=10,
        help="ground-truth test view every N-th frame (default 10)",
    )


def parse_size(s: str) -> tuple[int, int]:
    from ..errors import InputError

    try:
        w, h = (int(v) for v in s.lower().split("x"))
    except ValueError:
        raise InputError(f"--size must look like 346x260, got {s!r}") from None
    return w, h


def run(args: argparse.Namespace) -> int:
    from ..data.synth import list_scenes
    from ..errors import InputError

    if args.list:
        print("\n".join(list_scenes()))
        return 0
    if not (args.scene or args.mesh):
        raise InputError("give --scene NAME or --mesh PATH (or --list)")
    if not args.out:
        raise InputError("--out DIR is required")
    from ..outputs import SCENE, claim_output

    claim_output(args.out, SCENE, force=args.force)
    w, h = parse_size(args.size)
    from ..data.synth import load_mesh
    from ..data.synth.make import make_scene_result, resolve_scene, summary
    from ..data.synth.simulator import SimulatorConfig

    source = resolve_scene(args.scene) if args.scene else load_mesh(args.mesh)
    sim = SimulatorConfig(
        pos_threshold=args.threshold,
        neg_threshold=args.neg_threshold,
        bayer=None if args.bayer == "mono" else "rggb",
        mismatch=args.mismatch,
        noise=args.noise,
        seed=args.seed,
    )
    res = make_scene_result(
        source,
        args.out,
        width=w,
        height=h,
        frames=args.frames,
        bayer=None if args.bayer == "mono" else "rggb",
        threshold=args.threshold,
        noise=args.noise,
        seed=args.seed,
        test_every=args.test_every,
        fmt=args.format,
        supersample=args.supersample,
        progress=True,
        sim=sim,
    )
    print(f"wrote {res.path} ({args.format}): {summary(res)}")
    return 0
