"""Textured mesh: a UV atlas (xatlas) and a texture baked from a radiance field's colour.

mesh (trimesh, world units) -> `uv_atlas` (charts packed into one W x H atlas; vertices are
split along chart seams) -> `rasterize_uv` (for each texel centre: the atlas triangle that
covers it and its barycentric coordinates) -> the texel's 3D point and normal by barycentric
interpolation -> its colour from the field, averaged in linear intensity over `n_dirs` view
directions within 60° of the inward normal (`fastenerf.mesh.vertex_colors`, the same rule as
the vertex colours) -> islands dilated by a few texels so that bilinear filtering and mipmaps
at chart borders read the island's colour, not the empty atlas.

Conventions: UVs in [0, 1] with v up (glTF/OBJ as trimesh holds them); the image's row 0 is
v = 1; texel (row i, col j) has its centre at u = (j + 0.5) / W, v = 1 − (i + 0.5) / H. The
texture holds display-space colours (the field's, gamma 2.2), as the vertex colours do.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from .errors import InputError
from .mesh import ColorFn, vertex_colors

# Texels of empty space that xatlas keeps around each chart: bilinear filtering at a chart's
# border then reads no other chart. Each costs a ring of texels per chart, and noisy
# marching-cubes meshes make thousands of small charts.
PADDING = 2
# Texels the bake fills around each island (nearest island texel's colour), so that filtering
# and the first mipmap levels read the island's colour, not the empty atlas. Filling only
# empty texels, it may meet the next chart's fill but never overwrites a chart.
DILATION = 4


def uv_atlas(
    vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray, size: int = 1024
) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[int, int]]:
    """Charts of a triangle mesh packed into one atlas of about `size` x `size` texels.

    vertices: (V, 3) world units; faces: (F, 3) int; normals: (V, 3) (guide the charting).
    Returns (vmap (V',) int64: the input vertex of each atlas vertex, faces (F, 3) int64 into
    the atlas vertices (same face order), uv (V', 2) float32 in [0, 1], (width, height) texels).
    """
    import xatlas

    if size < 16:
        raise InputError(f"texture size must be at least 16 texels, got {size}")
    atlas = xatlas.Atlas()
    atlas.add_mesh(
        np.ascontiguousarray(vertices, np.float32),
        np.ascontiguousarray(faces, np.uint32),
        np.ascontiguousarray(normals, np.float32),
    )
    pack = xatlas.PackOptions()
    pack.resolution = int(size)
    pack.padding = PADDING
    pack.bilinear = True  # leave room for bilinear filtering at chart borders
    atlas.generate(pack_options=pack)
    if atlas.atlas_count != 1:
        raise InputError(f"the mesh's charts do not fit one {size}x{size} atlas")
    vmap, idx, uv = atlas[0]
    return (
        vmap.astype(np.int64),
        idx.astype(np.int64),
        uv.astype(np.float32),
        (int(atlas.width), int(atlas.height)),
    )


def rasterize_uv(
    uv: np.ndarray, faces: np.ndarray, width: int, height: int, chunk: int = 1 << 22
) -> tuple[np.ndarray, np.ndarray]:
    """Which triangle covers each texel centre of a W x H atlas, and where.

    uv: (V, 2) in [0, 1], v up; faces: (F, 3) int. Returns (face (H, W) int64, −1 where no
    triangle covers the centre; bary (H, W, 3) float32 barycentric coordinates, 0 there).
    Triangles are handled in groups of similar texel-space extent, each as one array op.
    """
    face_of = np.full((height, width), -1, np.int64)
    bary = np.zeros((height, width, 3), np.float32)
    # Texel coordinates of the corners: x = u·W − 0.5, y = (1 − v)·H − 0.5, so that the
    # centre of texel (i, j) is at (x, y) = (j, i).
    p = np.stack([uv[:, 0] * width - 0.5, (1.0 - uv[:, 1]) * height - 0.5], -1).astype(np.float64)
    tri = p[faces]  # (F, 3, 2)
    lo = np.floor(tri.min(1)).astype(np.int64)
    ext = np.ceil(tri.max(1)).astype(np.int64) - lo + 1  # (F, 2) texels spanned
    side = np.maximum(ext.max(1), 1)
    bucket = np.ceil(np.log2(side)).astype(np.int64)
    for b in np.unique(bucket):
        k = 1 << int(b)
        oy, ox = np.meshgrid(np.arange(k), np.arange(k), indexing="ij")
        off = np.stack([ox.ravel(), oy.ravel()], -1)  # (k², 2) as (x, y)
        ids = np.flatnonzero(bucket == b)
        step = max(1, chunk // (k * k))
        for s in range(0, len(ids), step):
            f = ids[s : s + step]
            q = (lo[f, None, :] + off[None]).astype(np.float64)  # (n, k², 2) texel centres
            lam = _barycentric(tri[f], q)
            inside = (lam >= -1e-9).all(-1)
            inside &= (q[..., 0] >= 0) & (q[..., 0] < width) & (q[..., 1] >= 0)
            inside &= q[..., 1] < height
            n_i, k_i = np.nonzero(inside)
            x, y = q[n_i, k_i, 0].astype(np.int64), q[n_i, k_i, 1].astype(np.int64)
            face_of[y, x] = f[n_i]
            bary[y, x] = lam[n_i, k_i]
    return face_of, bary


def _barycentric(tri: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Barycentric coordinates (n, m, 3) of points q (n, m, 2) in triangles tri (n, 3, 2);
    −1 for all three where a triangle has no area in texel space."""
    a, b, c = tri[:, None, 0], tri[:, None, 1], tri[:, None, 2]
    v0, v1, v2 = b - a, c - a, q - a
    den = v0[..., 0] * v1[..., 1] - v1[..., 0] * v0[..., 1]
    ok = np.abs(den) > 1e-12
    den = np.where(ok, den, 1.0)
    l1 = (v2[..., 0] * v1[..., 1] - v1[..., 0] * v2[..., 1]) / den
    l2 = (v0[..., 0] * v2[..., 1] - v2[..., 0] * v0[..., 1]) / den
    lam = np.stack([1.0 - l1 - l2, l1, l2], -1)
    return np.where(ok[..., None], lam, -1.0)


def dilate(image: np.ndarray, covered: np.ndarray, texels: int) -> np.ndarray:
    """Fill uncovered texels within `texels` (Euclidean) of an island with the colour of the
    nearest covered texel. image: (H, W, C); covered: (H, W) bool. Returns a new image."""
    from scipy.ndimage import distance_transform_edt

    if texels <= 0 or covered.all() or not covered.any():
        return image.copy()
    dist, (iy, ix) = distance_transform_edt(~covered, return_indices=True)
    out = image[iy, ix]
    far = dist > texels
    out[far] = image[far]
    return out


def bake_texture(
    color_fn: ColorFn,
    mesh,
    size: int = 1024,
    n_dirs: int = 8,
    dilation: int = DILATION,
    chunk: int = 1 << 16,
    device=None,
    progress: bool = True,
):
    """UV-atlas `mesh` and bake the field's colour into a texture.

    color_fn: (x (N, 3), unit dirs d (N, 3)) -> display colour (N, 3) in [0, 1], as
    `fastenerf.mesh.extract_mesh` takes it. size: atlas side in texels (xatlas may pack a
    slightly different W x H). Returns (textured trimesh (vertices split at chart seams,
    same faces), stats dict: texture [W, H], texels baked, atlas/bake seconds, utilisation).
    """
    import trimesh
    from PIL import Image

    if len(mesh.faces) == 0:
        raise InputError("cannot texture an empty mesh")
    t0 = time.perf_counter()
    normals = np.asarray(mesh.vertex_normals, np.float64)
    vmap, faces, uv, (w, h) = uv_atlas(
        np.asarray(mesh.vertices), np.asarray(mesh.faces), normals, size
    )
    verts = np.asarray(mesh.vertices, np.float64)[vmap]
    vnrm = normals[vmap]
    face_of, bary = rasterize_uv(uv, faces, w, h)
    t1 = time.perf_counter()
    covered = face_of >= 0
    f = faces[face_of[covered]]  # (T, 3)
    lam = bary[covered].astype(np.float64)[..., None]  # (T, 3, 1)
    x = (verts[f] * lam).sum(1)
    n = (vnrm[f] * lam).sum(1)
    flat = np.linalg.norm(n, axis=1) < 1e-6  # vertex normals that cancel: the face's instead
    if flat.any():
        fn = np.cross(verts[f[flat, 1]] - verts[f[flat, 0]], verts[f[flat, 2]] - verts[f[flat, 0]])
        n[flat] = fn
    col = vertex_colors(color_fn, x, n, n_dirs, chunk, device, progress, desc="texels")
    img = np.zeros((h, w, 3), np.float32)
    img[covered] = col
    img = dilate(img, covered, dilation)
    t2 = time.perf_counter()
    u8 = (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)
    # White diffuse, no specular: viewers that multiply the texture by Kd (OBJ) or the base
    # colour factor (glTF) show the baked colour as it is.
    material = trimesh.visual.material.SimpleMaterial(
        image=Image.fromarray(u8),
        diffuse=[255, 255, 255, 255],
        ambient=[255, 255, 255, 255],
        specular=[0, 0, 0, 255],
        glossiness=1.0,
    )
    visual = trimesh.visual.TextureVisuals(uv=uv, material=material)
    out = trimesh.Trimesh(verts, faces, visual=visual, process=False)
    stats = {
        "texture": [w, h],
        "texels_baked": int(covered.sum()),
        "utilisation": float(covered.mean()),
        "atlas_s": t1 - t0,
        "bake_s": t2 - t1,
        "n_dirs": int(n_dirs),
    }
    return out, stats


def export_textured(mesh, path: str | Path) -> list[Path]:
    """Write a textured mesh as .glb (texture embedded) or .obj (+ .mtl + .png beside it,
    named after the OBJ), every file atomically. Returns the paths written."""
    import trimesh
    from trimesh.exchange.obj import export_obj

    from .io import atomic_path

    path = Path(path)
    kind = path.suffix.lower()
    if kind == ".glb":
        mesh = mesh.copy()
        mesh.visual.material = trimesh.visual.material.PBRMaterial(
            name=path.stem,
            baseColorTexture=mesh.visual.material.image,
            baseColorFactor=[255, 255, 255, 255],
            metallicFactor=0.0,  # baked radiance: a matte dielectric, no reflections on top
            roughnessFactor=1.0,
        )
        with atomic_path(path) as tmp:
            mesh.export(tmp, file_type="glb")
        return [path]
    if kind != ".obj":
        raise InputError(f"{path}: a textured mesh is written as .glb or .obj (+ .mtl + .png)")
    mesh = mesh.copy()
    mesh.visual.material.name = path.stem  # names the texture file <stem>.png
    text, files = export_obj(
        mesh, include_normals=True, include_texture=True, return_texture=True,
        mtl_name=f"{path.stem}.mtl",
    )  # fmt: skip
    written = []
    for name, data in files.items():  # the material and its image first, the OBJ last
        with atomic_path(path.parent / name) as tmp:
            tmp.write_bytes(data)
        written.append(path.parent / name)
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return written + [path]
