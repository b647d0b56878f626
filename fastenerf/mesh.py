"""Mesh extraction from a radiance field (supplement F).

Density on a regular grid (chunked, no autograd) -> marching cubes (scikit-image) at a density
threshold -> a trimesh with vertex colours: the field's colour at each vertex, averaged (in
linear intensity) over several viewing directions that look at the surface from outside.
Export by suffix (.ply / .glb / .obj); a PNG preview through the synthetic-data GL renderer
(`fastenerf.data.synth.gl`, EGL), or matplotlib where no EGL context can be made.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import torch

from .clip import Cylinder, clip_aabb, cylinder_mask
from .errors import InputError

GAMMA = 2.2  # display colour c -> linear intensity c**2.2 (DESIGN §9)

DensityFn = Callable[[torch.Tensor], torch.Tensor]
ColorFn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


def grid_shape(aabb: Sequence[float], resolution: int) -> tuple[tuple[int, int, int], float]:
    """Cubic voxels: `resolution` samples along the box's longest side.

    Returns ((nx, ny, nz), spacing in world units); samples at min + i·spacing.
    """
    lo, hi = np.asarray(aabb[:3], np.float64), np.asarray(aabb[3:], np.float64)
    ext = hi - lo
    spacing = float(ext.max()) / (resolution - 1)
    n = np.maximum(np.ceil(ext / spacing - 1e-9).astype(int) + 1, 2)
    return (int(n[0]), int(n[1]), int(n[2])), spacing


@torch.no_grad()
def density_grid(
    density_fn: DensityFn,
    aabb: Sequence[float],
    resolution: int = 256,
    chunk: int = 1 << 18,
    device: torch.device | str | None = None,
    cylinder: Cylinder | None = None,
    progress: bool = True,
) -> tuple[np.ndarray, float]:
    """σ sampled on the grid of `grid_shape`: ((nx, ny, nz) float32 [x, y, z], spacing).

    density_fn: world points (N, 3) float32 -> σ (N,); called with at most `chunk` points.
    Points outside `cylinder` are not evaluated (σ = 0 there).
    """
    from .progress import progress_bar

    (nx, ny, nz), spacing = grid_shape(aabb, resolution)
    lo = torch.tensor(aabb[:3], dtype=torch.float32, device=device)
    total = nx * ny * nz
    out = np.empty(total, np.float32)
    dims = torch.tensor([ny * nz, nz, 1], device=device)
    sizes = torch.tensor([nx, ny, nz], device=device)
    for s in progress_bar(
        range(0, total, chunk), desc="density grid", unit="chunk", enabled=progress
    ):
        idx = torch.arange(s, min(s + chunk, total), device=device)
        ijk = (idx[:, None] // dims) % sizes  # C order: x slowest, z fastest
        x = lo + ijk.to(torch.float32) * spacing
        if cylinder is not None:
            inside = cylinder_mask(x, cylinder)
            sig = torch.zeros(len(x), dtype=torch.float32, device=device)
            if inside.any():
                sig[inside] = density_fn(x[inside]).reshape(-1).float()
        else:
            sig = density_fn(x).reshape(-1).float()
        out[s : s + len(idx)] = sig.cpu().numpy()
    return out.reshape(nx, ny, nz), spacing


def hemisphere_dirs(n: int) -> np.ndarray:
    """(n, 3) unit directions spread (Fibonacci) over the cap within 60° of +z."""
    i = np.arange(n) + 0.5
    cos_t = 1.0 - (1.0 - math.cos(math.radians(60))) * i / n
    sin_t = np.sqrt(1.0 - cos_t**2)
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    return np.stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t], -1)


@torch.no_grad()
def vertex_colors(
    color_fn: ColorFn,
    vertices: np.ndarray,
    normals: np.ndarray,
    n_dirs: int = 8,
    chunk: int = 1 << 16,
    device=None,
    progress: bool = True,
    desc: str = "vertex colours",
) -> np.ndarray:
    """Display-space colour (V, 3) in [0, 1] per vertex: color_fn(x, d) averaged in linear
    intensity over `n_dirs` rays d that hit the vertex from outside (within 60° of −normal).
    `desc` labels the progress bar."""
    from .progress import progress_bar

    local = hemisphere_dirs(n_dirs)  # around +z; rotate +z onto -normal per vertex
    nrm = -normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    a = np.where(np.abs(nrm[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    t1 = np.cross(nrm, a)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(nrm, t1)
    acc = np.zeros((len(vertices), 3), np.float64)
    step = max(1, chunk // n_dirs)
    for s in progress_bar(range(0, len(vertices), step), desc=desc, unit="chunk", enabled=progress):
        sl = slice(s, s + step)
        d = (
            local[None, :, :1] * t1[sl, None]
            + local[None, :, 1:2] * t2[sl, None]
            + local[None, :, 2:] * nrm[sl, None]
        )  # (v, K, 3) unit
        x = np.repeat(vertices[sl, None], d.shape[1], axis=1)
        c = color_fn(
            torch.as_tensor(x.reshape(-1, 3), dtype=torch.float32, device=device),
            torch.as_tensor(d.reshape(-1, 3), dtype=torch.float32, device=device),
        )
        c = c.float().clamp(0, 1).cpu().numpy().astype(np.float64).reshape(d.shape)
        acc[sl] = (c**GAMMA).mean(1)
    return (acc ** (1.0 / GAMMA)).astype(np.float32)


def extract_mesh(
    density_fn: DensityFn,
    color_fn: ColorFn | None,
    aabb: Sequence[float],
    resolution: int = 256,
    threshold: float = 10.0,
    chunk: int = 1 << 18,
    n_dirs: int = 8,
    cylinder: Cylinder | None = None,
    device=None,
    largest_only: bool = False,
    progress: bool = True,
):
    """Marching-cubes mesh of the level set σ = `threshold` (1/world units) inside `aabb`.

    density_fn: world points (N, 3) float32 -> σ (N,); color_fn: (x (N, 3), unit dirs d (N, 3))
    -> display-space colour (N, 3) in [0, 1], or None for no colours. aabb: [xmin, ymin, zmin,
    xmax, ymax, zmax] world units (shrunk to the cylinder's box when `cylinder` is given; σ is
    0 outside the cylinder). resolution: samples along the longest side (cubic voxels).
    The grid is padded with σ = 0 so that the surface closes where it meets the box.
    Returns a `trimesh.Trimesh` in world units, faces wound outward, vertex colours RGBA.
    """
    import trimesh
    from skimage.measure import marching_cubes

    if resolution < 2:
        raise InputError(f"mesh resolution must be at least 2, got {resolution}")
    if not math.isfinite(threshold) or threshold <= 0:
        raise InputError(f"mesh threshold must be a positive density, got {threshold}")
    try:
        box = clip_aabb(aabb, cylinder)
    except ValueError as e:
        raise InputError(str(e)) from None
    vol, spacing = density_grid(density_fn, box, resolution, chunk, device, cylinder, progress)
    bad = ~np.isfinite(vol)
    if bad.any():  # a diverged field: treat NaN as empty and +inf as solid, and say so
        print(f"warning: density is NaN/inf at {int(bad.sum())} of {vol.size} grid points")
        vol = np.nan_to_num(vol, nan=0.0, posinf=np.finfo(np.float32).max, neginf=0.0)
    if vol.max() < threshold:
        raise InputError(
            f"no surface: density never reaches the threshold {threshold:g} "
            f"(max σ = {vol.max():.4g}); lower --threshold"
        )
    vol = np.pad(vol, 1, constant_values=0.0)
    verts, faces, _, _ = marching_cubes(
        vol,
        level=threshold,
        spacing=(spacing,) * 3,
        gradient_direction="descent",
        allow_degenerate=False,
    )
    verts = verts - spacing + np.asarray(box[:3])  # undo the padding, to world units
    mesh = trimesh.Trimesh(verts, faces, process=True)
    if mesh.volume < 0:  # keep normals pointing out of the dense side
        mesh.invert()
    if largest_only and len(mesh.faces):
        parts = mesh.split(only_watertight=False)
        mesh = max(parts, key=lambda m: len(m.faces))
    if color_fn is not None:
        color_mesh(mesh, color_fn, n_dirs, device=device, progress=progress)
    return mesh


def color_mesh(mesh, color_fn: ColorFn, n_dirs: int = 8, device=None, progress: bool = True):
    """Give `mesh` (in place, and returned) RGBA vertex colours from `vertex_colors`."""
    import trimesh

    if len(mesh.vertices):
        col = vertex_colors(
            color_fn,
            np.asarray(mesh.vertices),
            np.asarray(mesh.vertex_normals),
            n_dirs,
            device=device,
            progress=progress,
        )
        rgba = np.concatenate([np.round(col * 255), np.full((len(col), 1), 255)], 1)
        mesh.visual = trimesh.visual.ColorVisuals(mesh, vertex_colors=rgba.astype(np.uint8))
    return mesh


def decimate(mesh, faces: int):
    """`mesh` simplified towards `faces` triangles (quadric error metric, through
    fast-simplification; many small closed pieces cannot all reach it); the mesh itself when
    it has no more. Colours are not kept: colour the result."""
    import trimesh

    if faces < 4:
        raise InputError(f"cannot decimate to {faces} faces (at least 4)")
    if len(mesh.faces) <= faces:
        return mesh
    out = mesh.simplify_quadric_decimation(face_count=int(faces))
    out = trimesh.Trimesh(out.vertices, out.faces, process=True)
    if len(out.faces) and out.volume < 0:
        out.invert()
    return out


def field_mesh(
    field,
    aabb: Sequence[float] | None = None,
    cylinder: Cylinder | None = None,
    colors: bool = True,
    **kwargs,
):
    """`extract_mesh` on a `fastenerf.fields.base.Field` (its density and color, its device);
    `colors=False` leaves out the vertex colours (a texture is baked instead).

    A field with an occupancy grid (ngp) is meshed as it renders: σ = 0 in cells the grid holds
    empty. Otherwise cells no training camera saw would keep the field's initial fog, which
    crosses the threshold in a small enough box (ngp starts at σ = 9 / box side).
    """
    if aabb is None:
        aabb = [float(v) for v in torch.as_tensor(field.aabb).reshape(-1).tolist()]
    device = next((p.device for p in field.parameters()), torch.device("cpu"))
    kwargs.setdefault("device", device)
    density = field.density
    grid = getattr(field, "grid", None)
    if grid is not None and hasattr(grid, "occupied"):

        def density(x: torch.Tensor) -> torch.Tensor:
            return torch.where(grid.occupied(x).to(x.device), field.density(x), 0.0)

    color = field.color if colors else None
    return extract_mesh(density, color, aabb, cylinder=cylinder, **kwargs)


def export_mesh(mesh, path: str | Path) -> Path:
    """Write `mesh` as .ply, .glb or .obj (by suffix), atomically."""
    from .io import atomic_path

    path = Path(path)
    kinds = {".ply": "ply", ".glb": "glb", ".obj": "obj"}
    kind = kinds.get(path.suffix.lower())
    if kind is None:
        raise InputError(f"{path}: unknown mesh format (use .ply, .glb or .obj)")
    with atomic_path(path) as tmp:
        mesh.export(tmp, file_type=kind)
    return path


def preview_camera(
    mesh,
    width: int = 640,
    height: int = 480,
    azimuth_deg: float = 35.0,
    elevation_deg: float = 25.0,
    fov_deg: float = 40.0,
):
    """(Intrinsics, c2w (4, 4)) of a camera that frames the mesh's bounding sphere, y up."""
    from .data.rig import Intrinsics, look_at

    center = np.asarray(mesh.bounds, np.float64).mean(0)
    radius = max(float(np.linalg.norm(np.asarray(mesh.vertices) - center, axis=1).max()), 1e-6)
    f = 0.5 * width / math.tan(math.radians(fov_deg) / 2)
    dist = radius / math.sin(math.radians(fov_deg) / 2 * min(1.0, height / width)) * 1.15
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    eye = center + dist * np.array(
        [math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)]
    )
    c2w = look_at(eye[None], center[None], np.array([0.0, 1.0, 0.0]))[0]
    return Intrinsics(f, f, width / 2, height / 2, width, height), c2w


def render_mesh(
    mesh, width: int = 640, height: int = 480, background=(1.0, 1.0, 1.0), **camera
) -> np.ndarray:
    """A shaded preview (H, W, 3) float32 display-space image of the mesh's vertex colours.

    Uses the EGL renderer of the synthetic data; falls back to matplotlib (painter's
    algorithm, lower quality) where no headless GL context can be created.
    """
    from .errors import FastenerfError

    intr, c2w = preview_camera(mesh, width, height, **camera)
    try:
        from .data.synth.gl import GLRenderer
        from .data.synth.scenes import SceneObject, SynthScene

        scene = SynthScene("mesh", [SceneObject(mesh)], background=tuple(background))
        near = 0.01 * float(np.linalg.norm(c2w[:3, 3] - mesh.bounds.mean(0)))
        with GLRenderer(intr, scene, near=near, far=near * 1000) as r:
            return np.asarray(r.render(c2w), np.float32) ** (1.0 / GAMMA)
    except (ImportError, FastenerfError):
        return _render_matplotlib(mesh, intr, c2w, background)


def render_views(mesh, intr, c2w: np.ndarray, background=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Unlit renders (N, H, W, 3) float32 display space of `mesh`'s own colours (texture or
    vertex colours, as baked from the field) from OpenCV camera-to-world poses c2w (N, 4, 4)
    with intrinsics `intr` (`fastenerf.data.rig.Intrinsics`), over a display-space background.
    Needs a headless EGL context (`FastenerfError` where none can be made)."""
    from .data.synth.gl import GLRenderer
    from .data.synth.scenes import Material, SceneObject, SynthScene

    c2w = np.asarray(c2w, np.float64).reshape(-1, 4, 4)
    dist = np.linalg.norm(c2w[:, :3, 3] - np.asarray(mesh.bounds).mean(0), axis=1).max()
    near = 0.01 * max(float(dist), 1e-6)
    scene = SynthScene("mesh", [SceneObject(mesh, Material())], background=tuple(background))
    with GLRenderer(intr, scene, near=near, far=near * 1000, lit=False) as r:
        return np.asarray(r.render(c2w), np.float32).clip(0, 1) ** (1.0 / GAMMA)


def _render_matplotlib(mesh, intr, c2w, background) -> np.ndarray:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import PolyCollection

    w2c = np.linalg.inv(c2w)
    v = np.asarray(mesh.vertices) @ w2c[:3, :3].T + w2c[:3, 3]
    uv = intr.project(v)  # the preview camera sits outside the bounding sphere: z > 0
    tri = np.asarray(mesh.faces)
    depth = v[tri, 2].mean(1)
    order = np.argsort(-depth)  # far to near
    visual = mesh.visual.to_color() if mesh.visual.kind == "texture" else mesh.visual
    vc = np.asarray(visual.vertex_colors, np.float64)[:, :3] / 255.0
    fn = np.asarray(mesh.face_normals) @ w2c[:3, :3].T
    to_light = np.array([-0.3, -0.6, -0.75]) / np.linalg.norm([-0.3, -0.6, -0.75])  # upper left
    shade = 0.35 + 0.65 * np.clip(fn @ to_light, 0, 1)
    fc = np.clip(vc[tri].mean(1) * shade[:, None], 0, 1)
    front = (fn * v[tri].mean(1)).sum(1) < 0  # faces turned towards the camera
    order = order[front[order]]  # back faces are hidden on a closed surface
    fig = plt.figure(figsize=(intr.width / 100, intr.height / 100), dpi=100)
    ax = fig.add_axes([0, 0, 1, 1])
    ax.add_collection(
        PolyCollection(uv[tri[order]], facecolors=fc[order], edgecolors="none", antialiased=False)
    )
    ax.set_xlim(0, intr.width)
    ax.set_ylim(intr.height, 0)
    ax.set_facecolor(background)
    ax.axis("off")
    fig.patch.set_facecolor(background)
    fig.canvas.draw()
    img = np.asarray(fig.canvas.buffer_rgba())[..., :3].astype(np.float32) / 255.0
    plt.close(fig)
    return img


def write_mesh_png(mesh, path: str | Path, width: int = 640, height: int = 480, **camera) -> Path:
    """`render_mesh` to a PNG, atomically."""
    from .io import write_image

    return write_image(path, render_mesh(mesh, width, height, **camera))
