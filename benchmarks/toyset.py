"""The mesh scene of our own making that defaults are measured on beside the built-in scenes.

A torus leaning over a capsule and a cone, coloured by position with stripes (trimesh
primitives, vertex colours), none of them a built-in scene's shapes::

    fastenerf bench toyset toyset.ply      # or: python -m benchmarks.toyset toyset.ply
    fastenerf synth --mesh toyset.ply --out DATA/toyset
"""

import argparse

import numpy as np
import trimesh
from trimesh import creation
from trimesh import transformations as tf

from fastenerf.mesh import export_mesh
from fastenerf.outputs import MESH, claim_output

from .cli import benchmark_main


def _coloured(mesh: trimesh.Trimesh, base) -> trimesh.Trimesh:
    """Stripes of `base` (RGB in [0, 1]) along a slanted direction, as vertex colours."""
    v = mesh.vertices
    stripes = 0.5 + 0.5 * np.sin(9 * v[:, 1] + 5 * v[:, 0])[:, None]
    col = np.clip(np.asarray(base) * (0.45 + 0.55 * stripes), 0, 1)
    mesh.visual.vertex_colors = (np.hstack([col, np.ones((len(col), 1))]) * 255).astype(np.uint8)
    return mesh


def toyset() -> trimesh.Trimesh:
    """The scene's mesh, y-up, within the unit cube about the origin."""
    torus = creation.torus(
        major_radius=0.55, minor_radius=0.18, major_sections=64, minor_sections=24
    )
    torus.apply_transform(tf.rotation_matrix(np.deg2rad(70), [1, 0, 0]))
    torus.apply_translation([0, 0.35, 0])
    cap = creation.capsule(height=0.7, radius=0.22, count=[24, 24])
    cap.apply_transform(tf.rotation_matrix(np.deg2rad(90), [1, 0, 0]))
    cap.apply_translation([0.45, -0.25, 0.2])
    cone = creation.cone(radius=0.3, height=0.6, sections=48)
    cone.apply_transform(tf.rotation_matrix(np.deg2rad(-90), [1, 0, 0]))
    cone.apply_translation([-0.45, -0.55, -0.15])
    parts = ((torus, (0.9, 0.35, 0.1)), (cap, (0.15, 0.45, 0.9)), (cone, (0.2, 0.8, 0.3)))
    return trimesh.util.concatenate([_coloured(m, base) for m, base in parts])


def _add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("out", help="mesh file to write (.ply keeps the vertex colours)")
    p.add_argument("--force", action="store_true", help="replace an existing mesh file")


def _run(args: argparse.Namespace) -> int:
    claim_output(args.out, MESH, force=args.force, flag="out")
    export_mesh(toyset(), args.out)  # atomically: a failed write leaves what was there
    return 0


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    return benchmark_main("toyset", __doc__, _add_arguments, _run, argv, prog=prog)


if __name__ == "__main__":
    raise SystemExit(main())
