"""Built-in synthetic scenes, generated from code with trimesh (nothing is stored).

Every scene fits inside the unit sphere, world y-up, over a constant background colour.
Colours (textures, vertex colours, `background`) are DISPLAY space in [0, 1]; the renderer
converts them to linear intensity with c**2.2 (DESIGN §9).

Scenes, each stressing one thing:
  blocks  (default) high-contrast procedural textures on a box, a sphere, a cylinder and a
          turntable plate: many strong edges, the easy case.
  plant   thin structures: a branching stem of cylinders of radius 0.006-0.02 with small
          leaves, in a striped pot.
  shiny   view-dependent colour: glossy spheres and a torus with strong Blinn-Phong
          highlights on a matte chequered plate.
  lattice thin structures again, but regular: a cube frame of thin coloured struts with
          node spheres (aliasing and disocclusion everywhere).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

from ...errors import InputError

DEFAULT_SCENE = "blocks"

# Saturated display-space colours for high-contrast textures.
PALETTE = np.array(
    [
        [0.92, 0.12, 0.10],  # red
        [0.98, 0.80, 0.10],  # yellow
        [0.10, 0.30, 0.90],  # blue
        [0.10, 0.70, 0.25],  # green
        [0.96, 0.96, 0.94],  # white
        [0.06, 0.06, 0.08],  # black
        [0.98, 0.48, 0.05],  # orange
        [0.55, 0.15, 0.75],  # purple
    ],
    dtype=np.float32,
)


@dataclass
class Material:
    """Shading of one object: Lambert albedo (from the mesh's visual) + Blinn-Phong.

    specular: highlight strength (linear intensity at the highlight's peak, 0 = matte);
    shininess: Blinn-Phong exponent (larger = smaller, sharper highlight);
    closed: the mesh (with the object's other parts) bounds a solid, so a face is drawn only
    from its outer side (its normal's side). Without this, the hidden inner side of a wall
    z-fights with the surface it meets at a crease (a cap's rim), which flickers from frame to
    frame and fires spurious events. Open surfaces (leaves, plates) keep it False: both
    sides are drawn and lit.
    """

    specular: float = 0.0
    shininess: float = 32.0
    closed: bool = False


SOLID = Material(closed=True)  # matte, closed


@dataclass
class SceneObject:
    mesh: trimesh.Trimesh
    material: Material = field(default_factory=Material)


@dataclass
class ViewSetup:
    """Turntable camera framing the scene: distance from `target` (world units), elevation
    above the horizontal plane, horizontal field of view, and the point looked at (the
    turntable's centre; on the y axis)."""

    radius: float = 4.0
    elevation_deg: float = 25.0
    hfov_deg: float = 40.0
    target: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def intrinsics(self, width: int, height: int):
        """Square-pixel pinhole intrinsics for a `width` x `height` sensor (no distortion)."""
        from ..rig import Intrinsics

        f = 0.5 * width / np.tan(np.deg2rad(self.hfov_deg) / 2)
        return Intrinsics(float(f), float(f), width / 2, height / 2, width, height)


@dataclass
class SynthScene:
    """Meshes with materials, a background colour (display space) and a camera setup."""

    name: str
    objects: list[SceneObject]
    background: tuple[float, float, float] = (0.25, 0.25, 0.27)
    view: ViewSetup = field(default_factory=ViewSetup)

    def bounds(self) -> np.ndarray:
        """(2, 3) axis-aligned bounds of all objects, world units."""
        b = np.array([o.mesh.bounds for o in self.objects])
        return np.stack([b[:, 0].min(0), b[:, 1].max(0)])

    def radius(self) -> float:
        """Largest distance of any vertex from the origin (<= 1 for valid scenes)."""
        return float(max(np.linalg.norm(o.mesh.vertices, axis=1).max() for o in self.objects))

    def to_trimesh(self) -> trimesh.Scene:
        """The geometry as a trimesh.Scene (e.g. to export it as GLB)."""
        return trimesh.Scene([o.mesh for o in self.objects])


# --------------------------------------------------------------------------- textures


def checker_texture(cells: int = 6, size: int = 384, seed: int = 0) -> np.ndarray:
    """(size, size, 3) uint8: a chequerboard whose cells take random palette colours."""
    rng = np.random.default_rng(seed)
    colors = PALETTE[rng.integers(0, len(PALETTE), (cells, cells))]
    idx = np.arange(size) * cells // size
    return _to_u8(colors[idx[:, None], idx[None, :]])


def stripe_texture(n: int = 8, size: int = 256, vertical: bool = True, seed: int = 1) -> np.ndarray:
    """(size, size, 3) uint8: `n` bands of palette colours (vertical bands vary along u)."""
    rng = np.random.default_rng(seed)
    colors = PALETTE[rng.permutation(len(PALETTE))[np.arange(n) % len(PALETTE)]]
    band = np.arange(size) * n // size
    img = colors[band][None, :, :] if vertical else colors[band][:, None, :]
    return _to_u8(np.broadcast_to(img, (size, size, 3)))


def ball_texture(size: int = 512, segments: int = 8) -> np.ndarray:
    """(size, 2*size, 3) uint8 lat-long texture: coloured segments with white polar caps."""
    h, w = size, 2 * size
    u = (np.arange(w) + 0.5) / w
    v = (np.arange(h) + 0.5) / h
    seg = PALETTE[[0, 1, 2, 3, 6, 7, 0, 2][:segments]][(u * segments).astype(int) % segments]
    img = np.broadcast_to(seg[None], (h, w, 3)).copy()
    img[(v < 0.12) | (v > 0.88)] = PALETTE[4]
    img[(np.abs(v - 0.5) < 0.025)] = PALETTE[5]
    return _to_u8(img)


def _to_u8(img: np.ndarray) -> np.ndarray:
    return (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)


# --------------------------------------------------------------------------- geometry


def parametric_mesh(
    fn: Callable,
    nu: int,
    nv: int,
    texture: np.ndarray | None = None,
    uv_repeat: tuple[float, float] = (1.0, 1.0),
) -> trimesh.Trimesh:
    """A grid surface p(u, v), u, v in [0, 1], with analytic normals and UVs.

    fn(u, v) -> (points (..., 3), normals (..., 3)) on arrays of u, v. The seam (u = 0 and
    u = 1) is duplicated so the texture does not wrap backwards across it.
    """
    u, v = np.meshgrid(np.linspace(0, 1, nu + 1), np.linspace(0, 1, nv + 1))
    p, n = fn(u, v)
    i = np.arange(nv)[:, None] * (nu + 1) + np.arange(nu)[None, :]
    a, b, c, d = i, i + 1, i + nu + 1, i + nu + 2
    faces = np.concatenate(
        [np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)]
    )
    mesh = trimesh.Trimesh(p.reshape(-1, 3), faces, vertex_normals=n.reshape(-1, 3), process=False)
    if texture is not None:
        uv = np.stack([u.ravel() * uv_repeat[0], v.ravel() * uv_repeat[1]], -1)
        _set_texture(mesh, uv, texture)
    return mesh


def _set_texture(mesh: trimesh.Trimesh, uv: np.ndarray, texture: np.ndarray) -> None:
    from PIL import Image

    # White diffuse: trimesh's default grey would be exported as a glTF baseColorFactor.
    mat = trimesh.visual.material.SimpleMaterial(
        image=Image.fromarray(texture), diffuse=[255, 255, 255, 255]
    )
    mesh.visual = trimesh.visual.TextureVisuals(uv=uv, material=mat)


def sphere(
    radius: float, center=(0, 0, 0), texture: np.ndarray | None = None, n: int = 64
) -> trimesh.Trimesh:
    """UV sphere; u is longitude, v latitude from the south (v = 0) to the north pole."""

    def fn(u, v):
        th, ph = 2 * np.pi * u, np.pi * v
        nrm = np.stack([np.sin(ph) * np.sin(th), -np.cos(ph), np.sin(ph) * np.cos(th)], -1)
        return nrm * radius + np.asarray(center), nrm

    return parametric_mesh(fn, 2 * n, n, texture)


def cylinder(
    radius: float,
    height: float,
    center=(0, 0, 0),
    texture: np.ndarray | None = None,
    cap_color=None,
    n: int = 128,
    uv_repeat=(1.0, 1.0),
    flat: bool = False,
) -> list[trimesh.Trimesh]:
    """Textured side (u around, v up) plus two flat caps (vertex-coloured), axis along y;
    `flat` shades the side as an n-sided prism.

    An object on the turntable axis needs many sections `n`: a polygon's rim wiggles as it
    turns (by r (1 - cos(pi / n))), and a wiggle that crosses an MSAA sample flickers the
    pixel, which the log amplifies into bursts of spurious events at dark edges.
    """
    c = np.asarray(center, dtype=np.float64)

    def side(u, v):
        th = 2 * np.pi * u
        nrm = np.stack([np.sin(th), np.zeros_like(th), np.cos(th)], -1)
        p = nrm * radius + np.stack([0 * u, (v - 0.5) * height, 0 * u], -1)
        return p + c, nrm

    sides = parametric_mesh(side, n, 4, texture, uv_repeat)
    if flat:  # a prism: one outward normal per facet
        sides.unmerge_vertices()  # vertex i now belongs to face i // 3
        fn = sides.face_normals.copy()
        out = sides.triangles_center - c
        fn[(fn[:, [0, 2]] * out[:, [0, 2]]).sum(-1) < 0] *= -1
        sides.vertex_normals = np.repeat(fn, 3, axis=0)
    parts = [sides]
    for sgn in (-1.0, 1.0):
        cap = disc(radius, c + [0, sgn * height / 2, 0], normal_sign=sgn, n=n)
        cap.visual.vertex_colors = _to_u8(
            np.broadcast_to(
                np.asarray(cap_color if cap_color is not None else PALETTE[4]),
                (len(cap.vertices), 3),
            )
        )
        parts.append(cap)
    return parts


def disc(
    radius: float, center, normal_sign: float = 1.0, n: int = 512, texture: np.ndarray | None = None
) -> trimesh.Trimesh:
    """Flat disc in the xz plane facing ±y; UVs are planar (the texture spans its diameter)."""
    th = np.linspace(0, 2 * np.pi, n, endpoint=False)
    ring = np.stack([np.sin(th), np.zeros(n), np.cos(th)], -1) * radius
    verts = np.concatenate([[[0, 0, 0]], ring]) + np.asarray(center, dtype=np.float64)
    faces = np.stack([np.zeros(n, int), 1 + np.arange(n), 1 + (np.arange(n) + 1) % n], -1)
    if normal_sign < 0:
        faces = faces[:, ::-1]
    nrm = np.tile([0.0, normal_sign, 0.0], (n + 1, 1))
    mesh = trimesh.Trimesh(verts, faces, vertex_normals=nrm, process=False)
    if texture is not None:
        local = verts - np.asarray(center)
        uv = 0.5 + 0.5 * np.stack([local[:, 0], -local[:, 2]], -1) / radius
        _set_texture(mesh, uv, texture)
    return mesh


def textured_box(
    extents, center=(0, 0, 0), texture: np.ndarray | None = None, rotation_y_deg: float = 0.0
) -> trimesh.Trimesh:
    """Box whose six faces each carry the whole texture (flat normals, unshared corners)."""
    ext = np.asarray(extents, dtype=np.float64) / 2
    verts, nrms, uvs, faces = [], [], [], []
    for axis in range(3):
        for sgn in (-1.0, 1.0):
            a1, a2 = [k for k in range(3) if k != axis]
            corners = np.zeros((4, 3))
            corners[:, axis] = sgn * ext[axis]
            corners[:, a1] = np.array([-1, 1, 1, -1]) * ext[a1]
            corners[:, a2] = np.array([-1, -1, 1, 1]) * ext[a2]
            base = len(verts) * 4
            verts.append(corners)
            nrm = np.zeros(3)
            nrm[axis] = sgn
            nrms.append(np.tile(nrm, (4, 1)))
            uvs.append(np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=np.float64))
            faces += [[base, base + 1, base + 2], [base, base + 2, base + 3]]
    mesh = trimesh.Trimesh(
        np.concatenate(verts), np.array(faces), vertex_normals=np.concatenate(nrms), process=False
    )
    if texture is not None:
        _set_texture(mesh, np.concatenate(uvs), texture)
    rot = trimesh.transformations.rotation_matrix(np.deg2rad(rotation_y_deg), [0, 1, 0])
    mesh.apply_transform(trimesh.transformations.translation_matrix(center) @ rot)
    return mesh


def rod(p0, p1, radius: float, color, sections: int = 8) -> trimesh.Trimesh:
    """Thin vertex-coloured cylinder from p0 to p1 (world units)."""
    m = trimesh.creation.cylinder(
        radius=radius, segment=np.array([p0, p1], dtype=np.float64), sections=sections
    )
    m.visual.vertex_colors = _to_u8(np.broadcast_to(np.asarray(color), (len(m.vertices), 3)))
    return m


def ball(center, radius: float, color, subdivisions: int = 3) -> trimesh.Trimesh:
    """Vertex-coloured icosphere."""
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    m.apply_translation(center)
    m.visual.vertex_colors = _to_u8(np.broadcast_to(np.asarray(color), (len(m.vertices), 3)))
    return m


def torus(
    major: float,
    minor: float,
    center=(0, 0, 0),
    axis_deg=(90.0, 0.0),
    color=(0.9, 0.7, 0.2),
    n: int = 64,
) -> trimesh.Trimesh:
    """Vertex-coloured torus; built around y, then rotated by `axis_deg` (about x, then y)."""

    def fn(u, v):
        a, b = 2 * np.pi * u, 2 * np.pi * v
        nrm = np.stack([np.sin(a) * np.cos(b), np.sin(b), np.cos(a) * np.cos(b)], -1)
        ctr = np.stack([np.sin(a), 0 * a, np.cos(a)], -1) * major
        return ctr + minor * nrm, nrm

    m = parametric_mesh(fn, n, n // 2)
    m.visual.vertex_colors = _to_u8(np.broadcast_to(np.asarray(color), (len(m.vertices), 3)))
    tf = trimesh.transformations
    rot = tf.rotation_matrix(np.deg2rad(axis_deg[1]), [0, 1, 0]) @ tf.rotation_matrix(
        np.deg2rad(axis_deg[0]), [1, 0, 0]
    )
    m.apply_transform(tf.translation_matrix(center) @ rot)
    return m


def _merge(meshes: list[trimesh.Trimesh]) -> trimesh.Trimesh:
    """One draw call for many vertex-coloured parts."""
    return trimesh.util.concatenate(meshes)


# --------------------------------------------------------------------------- scenes


def _blocks() -> SynthScene:
    plate_tex = stripe_texture(12, 512, vertical=True, seed=3)
    objs = [
        SceneObject(
            textured_box(
                [0.62, 0.62, 0.62], (-0.3, -0.2, -0.22), checker_texture(5, 320), rotation_y_deg=30
            ),
            SOLID,
        ),
        SceneObject(
            sphere(0.3, (0.34, -0.2, 0.22), ball_texture(256)), Material(0.15, 40, closed=True)
        ),
    ]
    objs += [
        SceneObject(m, SOLID)
        for m in cylinder(
            0.16,
            0.72,
            (0.3, -0.14, -0.38),
            stripe_texture(6, 256, vertical=False, seed=5),
            cap_color=PALETTE[1],
            uv_repeat=(3.0, 1.0),
        )
    ]
    # A square slab, not a round plate: a rim that is symmetric about the turntable axis
    # stands still in the image and only flickers at the rasteriser's sub-pixel precision.
    slab = textured_box([1.1, 0.05, 1.1], (0, -0.545, 0), _radial_texture(plate_tex))
    objs.append(SceneObject(slab, SOLID))
    return SynthScene(
        "blocks",
        objs,
        background=(0.26, 0.26, 0.3),
        view=ViewSetup(3.3, 25.0, 40.0, (0.0, -0.1, 0.0)),
    )


def _radial_texture(stripes: np.ndarray) -> np.ndarray:
    """Wrap a stripe image around the centre: alternating coloured sectors and rings."""
    s = stripes.shape[0]
    yy, xx = np.mgrid[0:s, 0:s] + 0.5
    ang = (np.arctan2(yy - s / 2, xx - s / 2) / (2 * np.pi) + 0.5) * s
    r = np.hypot(yy - s / 2, xx - s / 2) / (s / 2)
    img = stripes[0][(ang.astype(int) % s)]
    img[(r % 0.25) < 0.04] = 240
    return img


def _plant() -> SynthScene:
    rng = np.random.default_rng(7)
    stems, leaves = [], []
    stem_color = np.array([0.35, 0.25, 0.12])

    def grow(p0, d, length, radius, depth):
        p1 = p0 + d * length
        stems.append(rod(p0, p1, radius, stem_color * rng.uniform(0.8, 1.2), sections=8))
        if depth == 0:
            for _ in range(2):
                leaves.append(_leaf(p1, rng))
            return
        for _ in range(rng.integers(2, 4)):
            nd = d + rng.normal(0, 0.55, 3)
            nd[1] = abs(nd[1]) + 0.25  # grow upwards
            nd /= np.linalg.norm(nd)
            grow(p1, nd, length * rng.uniform(0.6, 0.8), max(radius * 0.65, 0.006), depth - 1)

    grow(np.array([0.0, -0.5, 0.0]), np.array([0.0, 1.0, 0.0]), 0.4, 0.02, 4)
    # An octagonal pot with a terracotta / white zigzag / ticks pattern: it sits on the
    # turntable axis, so a round pot or a ring pattern would never produce (true) events.
    yy, xx = np.mgrid[0:256, 0:512] / np.array([256.0, 512.0])[:, None, None]
    zig = np.abs(((xx * 16) % 2) - 1)  # triangle wave around the pot
    pot_tex = np.broadcast_to(_to_u8(np.array([0.85, 0.45, 0.25])), (256, 512, 3)).copy()
    pot_tex[np.abs(yy - (0.35 + 0.3 * zig)) < 0.06] = _to_u8(PALETTE[4])
    pot_tex[(yy > 0.85) & ((xx * 24) % 1 < 0.4)] = _to_u8(PALETTE[5])
    objs = [SceneObject(_merge(stems), SOLID), SceneObject(_merge(leaves), Material(0.08, 20))]
    objs += [
        SceneObject(m, SOLID)
        for m in cylinder(0.26, 0.34, (0, -0.66, 0), pot_tex, (0.2, 0.12, 0.06), n=8, flat=True)
    ]
    scene = _fit(SynthScene("plant", objs, background=(0.3, 0.3, 0.33)), 0.97)
    b = scene.bounds()
    scene.view = ViewSetup(3.5, 20.0, 40.0, (0.0, float(b[:, 1].mean()), 0.0))
    return scene


def _leaf(base, rng) -> trimesh.Trimesh:
    """A small flat elliptic leaf attached at `base`, in a random orientation."""
    n = 10
    th = np.linspace(0, 2 * np.pi, n, endpoint=False)
    size = rng.uniform(0.05, 0.09)
    local = np.stack([np.cos(th) * size * 0.45, 0 * th, (np.sin(th) + 1.0) * size], -1)
    verts = np.concatenate([[[0, 0, size]], local])
    faces = np.stack([np.zeros(n, int), 1 + np.arange(n), 1 + (np.arange(n) + 1) % n], -1)
    rot = trimesh.transformations.random_rotation_matrix(rng.random(3))
    m = trimesh.Trimesh(verts, faces, process=False)
    m.apply_transform(trimesh.transformations.translation_matrix(base) @ rot)
    green = np.array([0.2, 0.62, 0.15]) * rng.uniform(0.6, 1.3) + rng.normal(0, 0.04, 3)
    m.visual.vertex_colors = _to_u8(np.broadcast_to(np.clip(green, 0, 1), (len(verts), 3)))
    return m


def _shiny() -> SynthScene:
    objs = [
        SceneObject(
            ball((-0.34, -0.22, 0.2), 0.27, (0.75, 0.08, 0.06), 4), Material(0.9, 90, closed=True)
        ),
        SceneObject(
            ball((0.36, -0.24, 0.14), 0.25, (0.08, 0.2, 0.7), 4), Material(0.9, 60, closed=True)
        ),
        SceneObject(
            ball((0.0, -0.3, -0.4), 0.2, (0.85, 0.85, 0.82), 4), Material(0.7, 150, closed=True)
        ),
        SceneObject(
            torus(0.28, 0.08, (0.0, 0.2, 0.0), (90.0, 35.0), (0.75, 0.55, 0.12)),
            Material(0.8, 40, closed=True),
        ),
        SceneObject(
            textured_box([1.1, 0.05, 1.1], (0, -0.525, 0), checker_texture(8, 256, 4)), SOLID
        ),
    ]
    return SynthScene(
        "shiny",
        objs,
        background=(0.18, 0.18, 0.2),
        view=ViewSetup(3.2, 25.0, 40.0, (0.0, -0.12, 0.0)),
    )


def _lattice() -> SynthScene:
    h = 0.5
    corners = np.array([[x, y, z] for x in (-h, h) for y in (-h, h) for z in (-h, h)])
    edges = [
        (i, j)
        for i in range(8)
        for j in range(i + 1, 8)
        if np.abs(corners[i] - corners[j]).sum() == 2 * h
    ]
    rods = [
        rod(corners[i], corners[j], 0.014, PALETTE[k % 8], sections=8)
        for k, (i, j) in enumerate(edges)
    ]
    # Diagonals on the four side faces and one through the middle: crossing thin struts.
    for k, (a, b) in enumerate([(0, 6), (1, 7), (2, 4), (3, 5), (0, 3), (4, 7)]):
        rods.append(rod(corners[a], corners[b], 0.01, PALETTE[(k + 3) % 8], sections=8))
    nodes = [ball(c, 0.035, PALETTE[4], 2) for c in corners]
    objs = [
        SceneObject(_merge(rods), SOLID),
        SceneObject(_merge(nodes), Material(0.5, 30, closed=True)),
        SceneObject(ball((0.1, 0, 0.06), 0.18, PALETTE[1], 4), Material(0.3, 30, closed=True)),
    ]
    return _fit(
        SynthScene("lattice", objs, background=(0.24, 0.24, 0.27), view=ViewSetup(3.4, 25.0, 40.0)),
        0.95,
    )


def _fit(scene: SynthScene, radius: float) -> SynthScene:
    """Scale about the origin so that the scene's radius is at most `radius`."""
    r = scene.radius()
    if r > radius:
        for o in scene.objects:
            o.mesh.apply_scale(radius / r)
    return scene


_SCENES: dict[str, Callable[[], SynthScene]] = {
    "blocks": _blocks,
    "plant": _plant,
    "shiny": _shiny,
    "lattice": _lattice,
}


def list_scenes() -> list[str]:
    """Names of the built-in scenes; the first is the default."""
    return [DEFAULT_SCENE] + [n for n in _SCENES if n != DEFAULT_SCENE]


def build_scene(name: str = DEFAULT_SCENE) -> SynthScene:
    """Generate built-in scene `name` (deterministic)."""
    if name not in _SCENES:
        raise InputError(f"unknown scene '{name}' (built-in scenes: {', '.join(list_scenes())})")
    return _SCENES[name]()


def load_mesh(path: str | Path, radius: float = 0.9) -> SynthScene:
    """A user's mesh file (OBJ, GLB/GLTF, PLY, STL, ...) as a scene inside the unit sphere.

    The mesh keeps its textures / vertex colours / face colours and is assumed y-up; it is
    centred on its bounding box and scaled so its farthest vertex is `radius` from the origin.
    An unreadable file or one without triangles raises one-line `InputError`.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: mesh file not found")
    try:
        loaded = trimesh.load(path)
    except Exception as e:  # trimesh raises many types for broken files
        msg = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise InputError(f"{path}: cannot read mesh ({msg})") from None
    if isinstance(loaded, trimesh.Scene):
        meshes = [g for g in loaded.dump() if isinstance(g, trimesh.Trimesh)]
    else:
        meshes = [loaded] if isinstance(loaded, trimesh.Trimesh) else []
    meshes = [m for m in meshes if len(m.faces) > 0]
    if not meshes:
        raise InputError(
            f"{path}: no triangles in this file (point clouds and lines cannot be rendered)"
        )
    verts = np.concatenate([m.vertices for m in meshes])
    if not np.all(np.isfinite(verts)):
        raise InputError(f"{path}: mesh has NaN or inf vertex coordinates")
    center = (verts.min(0) + verts.max(0)) / 2
    scale = np.linalg.norm(verts - center, axis=1).max()
    if scale <= 0:
        raise InputError(f"{path}: mesh is degenerate (all vertices coincide)")
    tf = trimesh.transformations.scale_matrix(
        radius / scale
    ) @ trimesh.transformations.translation_matrix(-center)
    for m in meshes:
        m.apply_transform(tf)
    # Frame the bounding sphere: its angular radius is ~85% of the vertical half fov of a
    # 4:3 sensor at 40 degrees horizontal fov.
    return SynthScene(
        path.stem,
        [SceneObject(m, Material(closed=_is_closed(m))) for m in meshes],
        view=ViewSetup(radius / np.sin(np.deg2rad(13.0)), 25.0, 40.0),
    )


def _is_closed(mesh: trimesh.Trimesh) -> bool:
    """Watertight with consistent winding once duplicated (UV-seam) vertices are merged."""
    m = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    m.merge_vertices(merge_tex=True, merge_norm=True)
    return bool(m.is_watertight and m.is_winding_consistent and m.volume > 0)
