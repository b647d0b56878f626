"""Textured mesh against the field it was baked from: PSNR of renders, texture size, bake time.

    python -m benchmarks.mesh_texture RUN_DIR --out OUT [--resolution 256] [--threshold 10] \
        [--texture-size 1024] [--dirs 8] [--faces N] [--views 10] [--scale 1] [--device auto]

The run's field is meshed as `fastenerf mesh` does (marching cubes at `--threshold`), given
vertex colours, then (simplified to `--faces` triangles, if given) UV-atlased and baked into a
texture (`fastenerf mesh --texture [--faces N]`). From the
scene's test poses (every k-th, at most `--views`; an orbit of the scene where the run's scene
folder has no test views or is gone) the field is rendered as `fastenerf render` does, and the
textured and the vertex-coloured mesh are drawn unlit (each surface in its baked colour) by
the synthetic-data GL renderer over the scene's background. Reported: PSNR of each mesh
render against the field's render over whole images and over the pixels the field holds
opaque (opacity > 0.5), the texture's size and coverage, and the seconds of each stage.

Outputs in OUT: mesh_texture.json, mesh_texture.md (the table), mesh_texture.png (the first
view: field | textured mesh | vertex colours | 4x |textured − field|) and mesh.glb (the
textured mesh).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.cli import benchmark_main
from benchmarks.session import session_info, write_report
from fastenerf.errors import InputError
from fastenerf.io import write_image


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("run_dir", metavar="RUN_DIR", help="a training run folder")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--resolution", type=int, default=256, help="marching-cubes grid (256)")
    p.add_argument("--threshold", type=float, default=10.0, help="surface density (10)")
    p.add_argument("--texture-size", type=int, default=1024, help="atlas side, texels (1024)")
    p.add_argument("--dirs", type=int, default=8, help="view directions per texel (8)")
    p.add_argument("--faces", type=int, default=None, help="simplify before the atlas (none)")
    p.add_argument("--views", type=int, default=10, help="test views compared, at most (10)")
    p.add_argument("--scale", type=float, default=1.0, help="render size / sensor size (1)")
    p.add_argument("--device", default="auto", help="auto, cpu or cuda[:N]")


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    """PSNR (dB, peak 1) between display images (..., 3), over `mask` (...) pixels if given."""
    d = (np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2
    mse = float(d.mean()) if mask is None else float(d[mask].mean()) if mask.any() else math.nan
    return -10.0 * math.log10(max(mse, 1e-12)) if math.isfinite(mse) else math.nan


def view_poses(scene, sc, n: int) -> tuple[np.ndarray, str]:
    """(c2w (V, 4, 4), "test" or "orbit"): every k-th test pose, at most n of them."""
    c2w = getattr(scene, "test_c2w", None)
    if c2w is not None and len(c2w):
        k = max(1, math.ceil(len(c2w) / n))
        return np.asarray(c2w)[::k][:n], "test"
    from fastenerf.commands.render import orbit_poses

    return orbit_poses(sc, n, getattr(scene, "root", None), getattr(scene, "poses", None)), "orbit"


def field_renders(field, c2w, intr, sc, bg, chunk: int) -> tuple[np.ndarray, np.ndarray]:
    """The field's display renders (V, H, W, 3) and opacities (V, H, W), as `fastenerf render`."""
    from fastenerf.render import render_image

    rgb, opa = [], []
    for pose in c2w:
        out = render_image(field, pose, intr, near=sc.near, background=bg, chunk=chunk)
        rgb.append(out["rgb"].clamp(0, 1).cpu().numpy())
        opa.append(out["opacity"].cpu().numpy())
    return np.stack(rgb), np.stack(opa)


def run(args: argparse.Namespace) -> int:
    from fastenerf.data.rig import Intrinsics
    from fastenerf.mesh import decimate, field_mesh, render_views
    from fastenerf.run import load_run, scene_background
    from fastenerf.texture import bake_texture, export_textured

    if args.views < 1 or args.scale <= 0 or args.texture_size < 16 or args.dirs < 1:
        raise InputError("--views and --dirs must be >= 1, --scale > 0, --texture-size >= 16")
    out = Path(args.out)
    field, scene, cfg = load_run(args.run_dir, device=args.device)
    sc = getattr(scene, "config", scene)
    device = next((p.device for p in field.parameters()), None)
    info = session_info(device)

    t0 = time.perf_counter()
    mesh = field_mesh(
        field, sc.aabb, sc.cylinder, resolution=args.resolution, threshold=args.threshold,
        n_dirs=args.dirs,
    )  # fmt: skip
    if device is not None and device.type == "cuda":
        torch.cuda.synchronize(device)
    t_mesh = time.perf_counter() - t0
    t0 = time.perf_counter()
    simple = decimate(mesh, args.faces) if args.faces else mesh
    t_simplify = time.perf_counter() - t0
    textured, st = bake_texture(field.color, simple, args.texture_size, args.dirs, device=device)
    if device is not None and device.type == "cuda":
        torch.cuda.synchronize(device)
    glb = export_textured(textured, out / "mesh.glb")[0]

    c2w, pose_kind = view_poses(scene, sc, args.views)
    intr = Intrinsics.from_config(sc.intrinsics, sc.width, sc.height)
    intr = intr.scaled(args.scale) if args.scale != 1.0 else intr
    bg = scene_background(sc)
    t0 = time.perf_counter()
    ref, opacity = field_renders(field, c2w, intr, sc, bg, cfg.chunk)
    t_field = time.perf_counter() - t0
    bg_display = tuple(bg) if bg is not None else (0.0, 0.0, 0.0)
    t0 = time.perf_counter()
    tex_img = render_views(textured, intr, c2w, bg_display)
    t_gl = (time.perf_counter() - t0) / len(c2w)
    vc_img = render_views(mesh, intr, c2w, bg_display)
    solid = opacity > 0.5

    res = {
        "session": info,
        "run": str(args.run_dir),
        "settings": {k: v for k, v in vars(args).items() if k not in ("run_dir", "out")},
        "poses": pose_kind,
        "views": len(c2w),
        "image": [intr.width, intr.height],
        "mesh": {"vertices": len(mesh.vertices), "faces": len(mesh.faces), "seconds": t_mesh},
        "texture": {
            "size": st["texture"],
            "coverage": st["utilisation"],
            "atlas_s": st["atlas_s"],
            "bake_s": st["bake_s"],
            "atlas_vertices": len(textured.vertices),
            "faces": len(textured.faces),
            "simplify_s": t_simplify,
            "glb_bytes": glb.stat().st_size,
        },
        "psnr": {
            "textured": psnr(tex_img, ref),
            "textured_object": psnr(tex_img, ref, solid),
            "vertex_colours": psnr(vc_img, ref),
            "vertex_colours_object": psnr(vc_img, ref, solid),
        },
        "seconds": {"field_render_per_view": t_field / len(c2w), "gl_render_per_view": t_gl},
    }
    diff = np.clip(4 * np.abs(tex_img[0] - ref[0]), 0, 1)
    write_image(out / "mesh_texture.png", np.concatenate([ref[0], tex_img[0], vc_img[0], diff], 1))
    write_report(out, "mesh_texture", res, markdown(res))
    return 0


def markdown(res: dict) -> str:
    """The result as a Markdown table with its setting line."""
    p, t, m, s = res["psnr"], res["texture"], res["mesh"], res["settings"]
    w, h = t["size"]
    return "\n".join(
        [
            f"Mesh vs field, {res['views']} {res['poses']} views at "
            f"{res['image'][0]}x{res['image'][1]}, grid {s['resolution']}, threshold "
            f"{s['threshold']:g}, {s['dirs']} directions per texel "
            f"({res['session']['machine'].get('name', '?')}).",
            "",
            "| colours | PSNR (dB) | PSNR object (dB) | size | time (s) |",
            "|---|---|---|---|---|",
            f"| texture | {p['textured']:.2f} | {p['textured_object']:.2f} | {w}x{h} texels, "
            f"{t['coverage']:.0%} covered, {t['faces']:,} faces, GLB "
            f"{t['glb_bytes'] / 2**20:.1f} MiB | simplify {t['simplify_s']:.1f} + atlas "
            f"{t['atlas_s']:.1f} + bake {t['bake_s']:.1f} |",
            f"| vertex | {p['vertex_colours']:.2f} | {p['vertex_colours_object']:.2f} | "
            f"{m['vertices']:,} vertices, {m['faces']:,} faces | mesh {m['seconds']:.1f} |",
            "",
        ]
    )


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    return benchmark_main("mesh_texture", __doc__, add_arguments, run, argv, prog, out_folder=True)


if __name__ == "__main__":
    sys.exit(main())
