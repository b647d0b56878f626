"""`fastenerf mesh RUN_DIR --out mesh.ply`: marching-cubes mesh of a trained field (supp. F)."""

from __future__ import annotations

HELP = "extract a vertex-coloured mesh from a trained run (marching cubes)"


def add_arguments(p) -> None:
    p.add_argument("run", help="run folder written by `fastenerf train`")
    p.add_argument("--out", required=True, help="mesh file: .ply, .glb or .obj")
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
        "--dirs", type=int, default=8, help="view directions averaged per vertex colour (default 8)"
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


def run(args) -> int:
    from pathlib import Path

    from ..errors import InputError
    from ..mesh import export_mesh, field_mesh, write_mesh_png
    from ..run import load_run

    out = Path(args.out)
    if out.suffix.lower() not in (".ply", ".glb", ".obj"):
        raise InputError(f"{out}: unknown mesh format (use .ply, .glb or .obj)")
    if args.resolution < 2 or args.dirs < 1 or args.chunk < 1:
        raise InputError("--resolution must be >= 2, --dirs and --chunk >= 1")
    from ..memory import check_memory, grid_bytes
    from ..mesh import grid_shape
    from ..outputs import IMAGE, MESH, claim_output

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
        resolution=args.resolution,
        threshold=args.threshold,
        n_dirs=args.dirs,
        chunk=args.chunk,
        largest_only=args.largest,
    )
    export_mesh(mesh, out)
    print(
        f"{len(mesh.vertices):,} vertices, {len(mesh.faces):,} faces, "
        f"{'watertight' if mesh.is_watertight else 'open'}; wrote {out}"
    )
    if args.png:
        print(f"wrote {write_mesh_png(mesh, args.png)}")
    return 0
