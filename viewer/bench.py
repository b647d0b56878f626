"""Viewer frame rate: render only vs render + upload + draw, on a headless EGL context.

`bench_viewer(RUN_DIR or field)` orbits the camera once around the scene over `frames`
frames at `size` and reports frames per second for:
- render: `render_raw` + shading to 8 bits (what the viewer computes per frame), synchronised;
- full: the same plus the display path (texture upload through the pinned buffer on CUDA,
  a textured quad drawn into a framebuffer, `glFinish`), i.e. what a window shows;
`bench_upload(size)` times the display path alone, pinned vs pageable host memory.

`--chunk` renders with several ray-chunk sizes (rays per `Field.render` call) and reports each;
`--no-gl` measures the render path alone (a machine without an EGL driver).

    python -m fastenerf.viewer.bench RUN_DIR [--size 800x600] [--frames 100] \
        [--chunk 65536 262144] [--no-gl] [--out RESULT.json]
"""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path

import numpy as np
import torch


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def bench_viewer(
    run_dir_or_field,
    size: tuple[int, int] = (800, 600),
    frames: int = 100,
    warmup: int = 3,
    mode: str = "rgb",
    chunk: int | None = None,
    gl: bool = True,
    cone_angle: float | None | str = "default",
) -> dict:
    """Frames per second of the viewer at `size` (W, H) pixels; see the module docstring.

    chunk: rays per render call (default the viewer's, `ViewSettings.chunk`); gl: False skips
    the display path (render-only numbers; the full_* and upload_* keys are then absent);
    cone_angle: the view's cone floor (`ViewSettings.cone_angle`; "default": the viewer's).
    """
    from fastenerf.render import field_device

    from .blit import FrameTexture, Offscreen, headless_context
    from .camera import fov_y_of, intrinsics_for_fov
    from .frame import ViewSettings, render_raw, shade
    from .source import ViewSource

    if isinstance(run_dir_or_field, (str, Path)):
        src = ViewSource.from_run(run_dir_or_field)
    else:
        src = ViewSource.from_field(run_dir_or_field)
    f = src.field
    dev = field_device(f)
    fov = fov_y_of(src.intrinsics) if src.intrinsics is not None else 50.0
    intr = intrinsics_for_fov(size[0], size[1], fov)
    s = ViewSettings(mode=mode, near=src.near, background=src.background)
    if chunk is not None:
        s.chunk = int(chunk)
    if cone_angle != "default":
        s.cone_angle = cone_angle
    ctx = headless_context() if gl else None
    tex = FrameTexture(ctx) if gl else None
    off = Offscreen(ctx, size) if gl else None

    def run(n: int, full: bool) -> float:
        cam = src.default_camera()
        t = time.perf_counter()
        for _ in range(n):
            cam.orbit(2 * math.pi / max(frames, 1), 0.0)
            img = shade(render_raw(f, cam.c2w, intr, s), s, alpha=dev.type == "cuda")
            if full:
                tex.upload(img)
                off.draw(tex)
                ctx.finish()
            else:
                _sync(dev)
        return time.perf_counter() - t

    run(warmup, gl)
    t_render = run(frames, False)
    res = {
        "size": list(size),
        "frames": frames,
        "device": str(dev),
        "mode": mode,
        "chunk": s.chunk,
        "view_cone_angle": s.cone_angle,
        "render_fps": frames / t_render,
        "render_ms": 1e3 * t_render / frames,
    }
    if not gl:
        return res
    t_full = run(frames, True)
    up = bench_upload(size, frames=max(frames, 50), device=dev, ctx=ctx)
    off.release()
    tex.release()
    ctx.release()
    return {
        **res,
        "gl_renderer": up["gl_renderer"],
        "full_fps": frames / t_full,
        "full_ms": 1e3 * t_full / frames,
        **{k: v for k, v in up.items() if k.startswith("upload")},
    }


def bench_upload(
    size: tuple[int, int] = (800, 600),
    frames: int = 200,
    device="cuda",
    ctx=None,
    components: int = 3,
) -> dict:
    """Milliseconds per frame to show an (H, W, C) uint8 frame living on `device`: texture
    upload + quad draw + glFinish. On CUDA, through a reused pinned buffer (`upload_ms`) and
    through a plain `.cpu()` copy (`upload_pageable_ms`)."""
    from .blit import FrameTexture, Offscreen, headless_context

    device = torch.device(device)
    own = ctx is None
    ctx = headless_context() if own else ctx
    w, h = size
    img = torch.randint(0, 256, (h, w, components), dtype=torch.uint8, device=device)
    tex = FrameTexture(ctx)
    off = Offscreen(ctx, size)

    def show(t: FrameTexture, upload) -> float:
        upload(img)  # warm: allocations, first texture
        off.draw(t)
        ctx.finish()
        t0 = time.perf_counter()
        for _ in range(frames):
            upload(img)
            off.draw(t)
            ctx.finish()
        return 1e3 * (time.perf_counter() - t0) / frames

    want = img[..., :3].cpu().numpy()
    out = {
        "gl_renderer": ctx.info.get("GL_RENDERER", "?"),
        "upload_ms": show(tex, tex.upload),
        "upload_exact": bool(np.array_equal(gl_read(off, tex, ctx), want)),
    }
    if device.type == "cuda":

        def pageable(x):
            tex.texture.write(x.cpu().numpy())

        out["upload_pageable_ms"] = show(tex, pageable)
        try:  # optional CUDA-GL interop (Warp); only where the GL context is NVIDIA's
            from .blit import InteropTexture

            inter = InteropTexture(ctx)
            out["upload_interop_ms"] = show(inter, inter.upload)
            out["upload_interop_exact"] = bool(np.array_equal(gl_read(off, inter, ctx), want))
            inter.release()
        except Exception as e:
            out["upload_interop_error"] = f"{type(e).__name__}: {e}"[:200]
    off.release()
    tex.release()
    if own:
        ctx.release()
    return out


def gl_read(off, tex, ctx) -> np.ndarray:
    off.draw(tex)
    ctx.finish()
    return off.read()


def main(argv: list[str] | None = None) -> None:
    import argparse

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run", nargs="?", help="run folder (omit for the upload benchmark alone)")
    p.add_argument("--size", default="800x600")
    p.add_argument("--frames", type=int, default=100)
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--chunk", type=int, nargs="+", default=[None], help="rays per render call")
    p.add_argument("--no-gl", action="store_true", help="render path only (no EGL context)")
    p.add_argument(
        "--cone-angle",
        type=float,
        nargs="+",
        default=["default"],
        help="the view's cone angle floor(s) (ngp; 0: the field's own; default the viewer's)",
    )
    p.add_argument("--out", help="also write the result(s) to this JSON file")
    a = p.parse_args(argv)
    from fastenerf.errors import FastenerfError

    bad = [c for c in a.cone_angle if c != "default" and not 0 <= c <= 1]
    try:
        if bad:
            raise FastenerfError(f"--cone-angle must be in [0, 1], got {bad[0]}")
        run(a)
    except FastenerfError as e:
        print(f"viewer.bench: error: {e}", file=sys.stderr)
        raise SystemExit(2) from None


def run(a) -> None:
    import json

    size = tuple(int(v) for v in a.size.split("x"))
    if a.run:
        res = [
            bench_viewer(a.run, size, a.frames, chunk=c, gl=not a.no_gl, cone_angle=k)
            for k in a.cone_angle
            for c in a.chunk
        ]
    else:
        res = [{"size": list(size), "device": a.device, **bench_upload(size, a.frames, a.device)}]
    res = [{k: (round(v, 3) if isinstance(v, float) else v) for k, v in r.items()} for r in res]
    text = json.dumps(res if len(res) > 1 else res[0], indent=1)
    if a.out:
        from fastenerf.io import atomic_path

        with atomic_path(a.out) as tmp:
            tmp.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
