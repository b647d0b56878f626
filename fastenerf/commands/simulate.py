"""`fastenerf simulate`: events from your own rendered frames (ESIM-style simulator)."""

from __future__ import annotations

import argparse

HELP = "simulate events from a frames file (npz: frames (N,H,W,3) linear, t (N,) seconds)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--frames",
        metavar="F.npz",
        required=True,
        help="npz with 'frames' (N, H, W, 3) linear RGB (or (N, H, W) intensity) "
        "and 't' (N,) seconds, increasing",
    )
    p.add_argument("--out", metavar="E.npz", required=True, help="events file to write")
    p.add_argument(
        "--force", action="store_true", help="replace --out even if it is not an events file"
    )
    p.add_argument(
        "--threshold",
        type=float,
        default=0.25,
        help="contrast threshold in log intensity (default 0.25)",
    )
    p.add_argument(
        "--neg-threshold",
        type=float,
        default=None,
        help="negative threshold if different (default: --threshold)",
    )
    p.add_argument(
        "--bayer",
        choices=["rggb", "mono"],
        default="rggb",
        help="rggb: each pixel sees its Bayer channel; mono: luminance",
    )
    p.add_argument(
        "--eps", type=float, default=1e-3, help="log(I + eps) guard for dark pixels (default 1e-3)"
    )
    p.add_argument(
        "--noise",
        type=float,
        default=0.0,
        help="fraction of the stream that is uniform noise events (default 0)",
    )
    p.add_argument(
        "--refractory-us",
        type=float,
        default=0.0,
        help="refractory period per pixel in µs (default 0)",
    )
    p.add_argument(
        "--mismatch", type=float, default=0.0, help="per-pixel threshold std, log units (default 0)"
    )
    p.add_argument("--seed", type=int, default=0, help="seed for mismatch and noise")
    p.add_argument(
        "--loop",
        action="store_true",
        help="closed trajectory: also simulate last frame -> first frame, one "
        "median frame interval after the last",
    )


def run(args: argparse.Namespace) -> int:
    from ..outputs import EVENTS, claim_output

    claim_output(args.out, EVENTS, force=args.force)
    import numpy as np

    from ..data.synth.simulator import EventSimulator, SimulatorConfig
    from ..errors import InputError
    from ..io import read_npz, savez
    from ..progress import progress_bar

    cfg = SimulatorConfig(
        pos_threshold=args.threshold,
        neg_threshold=args.neg_threshold,
        bayer=None if args.bayer == "mono" else "rggb",
        log_eps=args.eps,
        mismatch=args.mismatch,
        refractory_us=args.refractory_us,
        noise=args.noise,
        seed=args.seed,
    ).validate()
    z = read_npz(args.frames, ("frames", "t"), what="frames file")
    frames, t = z["frames"], z["t"]
    if frames.ndim not in (3, 4) or len(frames) < 2 or frames.dtype.kind not in "fiu":
        raise InputError(
            f"{args.frames}: 'frames' must be (N, H, W, 3) or (N, H, W) numbers, "
            f"N >= 2; got {frames.shape} {frames.dtype}"
        )
    if t.shape != (len(frames),):
        raise InputError(f"{args.frames}: 't' must have shape ({len(frames)},), got {t.shape}")
    t_us = np.asarray(t, dtype=np.float64) * 1e6
    h, w = frames.shape[1:3]
    sim = EventSimulator(w, h, cfg)
    chunk = 32
    with progress_bar(total=len(frames), desc="simulate", unit="frame") as bar:
        for i in range(0, len(frames), chunk):
            sim.add_frames(frames[i : i + chunk], t_us[i : i + chunk])
            bar.update(min(chunk, len(frames) - i))
    t_end = t_us[-1]
    if args.loop:
        period = t_us[-1] - t_us[0] + float(np.median(np.diff(t_us)))
        sim.close_loop(period)
        t_end = t_us[0] + period
    ev = sim.finish((t_us[0], t_end))
    savez(
        args.out,
        compressed=True,
        x=ev.x,
        y=ev.y,
        t=ev.t,
        p=ev.p,
        width=np.int64(w),
        height=np.int64(h),
        pos_threshold=np.float64(cfg.pos_threshold),
        neg_threshold=np.float64(cfg.neg_threshold or cfg.pos_threshold),
        log_eps=np.float64(cfg.log_eps),
        bayer=np.str_(cfg.bayer or "mono"),
    )
    dur = (t_end - t_us[0]) * 1e-6
    print(
        f"wrote {args.out}: {len(ev):,} events over {dur:g} s from {len(frames)} frames "
        f"{w}x{h} ({args.bayer})"
    )
    return 0
