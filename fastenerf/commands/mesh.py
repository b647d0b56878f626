"""`fastenerf mesh RUN_DIR --out mesh.ply`: marching-cubes mesh of a trained field (supp. F),
with vertex colours or (`--texture`) a UV atlas and a texture baked from the field."""

from __future__ import annotations

HELP = "extract a vertex-coloured or textured mesh from a trained run (marching cubes)"

MESH_SUFFIXES = (".ply", ".glb", ".obj")
TEXTURED_SUFFIXES = (".glb", ".obj")


def add_arguments(p) -> None:
    p.add_argument("run", help="run folder written by `fastenerf train`")
    p.add_argument(
        "--out",
        required=True,
        nargs="+",
        metavar="FILE",
        help="mesh file(s): .ply, .glb or .obj (with --texture: .glb, or .obj written with "
        ".mtl and .png beside it); several files share one extraction and bake",
    )
    p.add_argument(
        "--resolution",
        type=int,
        default=256,
        help="grid samples along the box's longest side (default 256)",
    )
    p.add_argument(
        "--threshold",
        type=float,
        default=10.0,
        help="density level of the surface, 1/world units (default 10)",
    )
    p.add_argument(
        "--dirs",
        type=int,
        default=8,
        help="view directions (within 60° of the inward normal) averaged per vertex colour or "
        "texel, in linear intensity (default 8)",
    )
    p.add_argument(
        "--texture",
        action="store_true",
        help="UV-atlas the mesh (xatlas) and bake the field's colour into a texture image "
        "instead of vertex colours",
    )
    p.add_argument(
        "--texture-size",
        type=int,
        default=1024,
        metavar="TEXELS",
        help="atlas side in texels (default 1024); xatlas packs about this size, larger where "
        "a noisy mesh makes many small charts (--faces helps)",
    )
    p.add_argument(
        "--faces",
        type=int,
        default=None,
        metavar="N",
        help="simplify to about N triangles (quadric error metric; small closed pieces stop "
        "short of it) before colouring; a "
        "textured mesh keeps its colour detail in the texture, and the atlas is made faster "
        "(default: no simplification)",
    )
    p.add_argument(
        "--largest",
        action="store_true",
        help="keep only the largest connected piece (drops floaters)",
    )
    p.add_argument("--png", help="also write a shaded preview image")
    p.add_argument("--device", default="auto", help="auto, cpu or cuda[:N]")
    p.add_argument("--chunk", type=int, default=1 << 18, help="points per field call")
    p.add_argument(
        "--force", action="store_true", help="replace --out / --png even if not a mesh / image"
    )


def _check_outputs(args) -> list:
    from pathlib import Path

    from ..errors import InputError

    outs = [Path(o) for o in args.out]
    allowed = TEXTURED_SUFFIXES if args.texture else MESH_SUFFIXES
    for out in outs:
        if out.suffix.lower() not in allowed:
            what = "textured mesh format (use .glb or .obj)" if args.texture else "mesh format"
            raise InputError(f"{out}: unknown {what} (use {', '.join(allowed)})")
    if args.texture and args.png:  # an OBJ's texture is <stem>.png beside it
        clash = [
            o
            for o in outs
            if o.suffix.lower() == ".obj" and o.with_suffix(".png") == Path(args.png)
        ]
        if clash:
            raise InputError(f"--png {args.png}: is the texture image of {clash[0]}")
    return outs


def run(args) -> int:
    from ..errors import InputError
    from ..mesh import color_mesh, decimate, export_mesh, field_mesh, write_mesh_png
    from ..run import load_run

    outs = _check_outputs(args)
    if args.resolution < 2 or args.dirs < 1 or args.chunk < 1:
        raise InputError("--resolution must be >= 2, --dirs and --chunk >= 1")
    if args.texture and args.texture_size < 16:
        raise InputError(f"--texture-size must be at least 16 texels, got {args.texture_size}")
    if args.faces is not None and args.faces < 4:
        raise InputError(f"--faces must be at least 4, got {args.faces}")
    from ..memory import check_memory, grid_bytes
    from ..mesh import grid_shape
    from ..outputs import IMAGE, MESH, claim_output

    for out in outs:
        claim_output(out, MESH, force=args.force)
    if args.png:
        claim_output(args.png, IMAGE, force=args.force, flag="--png")
    field, scene, _ = load_run(args.run, device=args.device)
    cfg = getattr(scene, "config", scene)  # a loaded Scene or the SceneConfig saved in the run
    shape = grid_shape(cfg.aabb, args.resolution)[0]
    grid = "x".join(map(str, shape))
    check_memory(grid_bytes(*shape), f"mesh --resolution {args.resolution} ({grid} grid)")
    mesh = field_mesh(
        field,
        aabb=cfg.aabb,
        cylinder=cfg.cylinder,
        colors=not (args.texture or args.faces),
        resolution=args.resolution,
        threshold=args.threshold,
        n_dirs=args.dirs,
        chunk=args.chunk,
        largest_only=args.largest,
    )
    print(
        f"{len(mesh.vertices):,} vertices, {len(mesh.faces):,} faces, "
        f"{'watertight' if mesh.is_watertight else 'open'}"
    )
    device = next((p.device for p in field.parameters()), None)
    if args.faces is not None and len(mesh.faces) > args.faces:
        mesh = decimate(mesh, args.faces)
        print(f"simplified to {len(mesh.vertices):,} vertices, {len(mesh.faces):,} faces")
    if args.faces is not None and not args.texture:  # coloured after the simplification
        color_mesh(mesh, field.color, args.dirs, device=device)
    written = []
    if args.texture:
        from ..texture import bake_texture, export_textured

        mesh, st = bake_texture(field.color, mesh, args.texture_size, args.dirs, device=device)
        w, h = st["texture"]
        print(
            f"texture {w}x{h}, {st['utilisation']:.0%} of it covered; "
            f"atlas {st['atlas_s']:.1f} s, bake {st['bake_s']:.1f} s"
        )
        for out in outs:
            written += export_textured(mesh, out)
    else:
        written = [export_mesh(mesh, out) for out in outs]
    print("wrote " + ", ".join(str(p) for p in written))
    if args.png:
        print(f"wrote {write_mesh_png(mesh, args.png)}")
    return 0
