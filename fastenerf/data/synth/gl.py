"""Headless OpenGL renderer for synthetic scenes (moderngl on EGL).

Draws the objects of a `SynthScene` (trimesh meshes with a texture, vertex colours or face
colours) with Lambert shading under fixed world-space lights plus ambient, and an optional
Blinn-Phong highlight per material so that colour depends on the view. Output is LINEAR RGB
float32 in [0, 1] (clamped per MSAA sample, like a sensor that saturates) over a constant
background colour.

Camera model: OpenCV intrinsics and camera-to-world poses, exactly as `fastenerf.data.rig`.
A pixel (i, j) covers [i, i+1) x [j, j+1) in OpenCV pixel coordinates, so its centre is at
+0.5 and GL's window coordinates coincide with OpenCV's; the projection flips y so that
the first row read back is the top image row. Radial distortion (k1, k2) is applied after
rendering by resampling a wider undistorted render.

Anti-aliasing: 4x MSAA rendered into float32 buffers and resolved (box average of the
samples) — edges produce events, so their coverage must be smooth in time.
"""

from __future__ import annotations

import numpy as np

from ...errors import FastenerfError
from ..rig import Intrinsics

# Fixed world-space lights (y-up): a key light from the upper front, a weaker fill from the
# other side, plus ambient; albedo 1 under all three sums to ~1, so colours stay below
# saturation except in specular highlights.
LIGHT_DIRS = np.array([[0.45, 0.8, 0.4], [-0.6, 0.25, -0.75]], dtype=np.float32)
LIGHT_DIRS /= np.linalg.norm(LIGHT_DIRS, axis=1, keepdims=True)
LIGHT_COLORS = np.array([[0.7, 0.7, 0.68], [0.3, 0.31, 0.34]], dtype=np.float32)
AMBIENT = 0.18
GAMMA = 2.2  # display colour c -> linear intensity c**2.2 (DESIGN §9)

_VERT = """
#version 330
uniform mat4 u_world_to_clip;
in vec3 in_pos;
in vec3 in_nrm;
in vec2 in_uv;
in vec3 in_col;
in vec3 in_fnrm;
out vec3 v_pos;
out vec3 v_nrm;
out vec2 v_uv;
out vec3 v_col;
flat out vec3 v_fnrm;
void main() {
    v_pos = in_pos;
    v_nrm = in_nrm;
    v_fnrm = in_fnrm;
    v_uv = in_uv;
    v_col = in_col;
    gl_Position = u_world_to_clip * vec4(in_pos, 1.0);
}
"""

_FRAG = """
#version 330
uniform vec3 u_eye;
uniform vec3 u_forward;
uniform sampler2D u_tex;
uniform bool u_use_tex;
uniform float u_ks;
uniform float u_shininess;
uniform vec3 u_light_dir[2];
uniform vec3 u_light_col[2];
uniform float u_ambient;
uniform bool u_closed;
in vec3 v_pos;
in vec3 v_nrm;
in vec2 v_uv;
in vec3 v_col;
flat in vec3 v_fnrm;
layout(location = 0) out vec4 f_color;
layout(location = 1) out vec4 f_depth;
void main() {
    vec3 v = normalize(u_eye - v_pos);
    // A closed surface is never seen from inside: drop back faces (by the outward face
    // normal, so winding does not matter), which would z-fight at creases.
    if (u_closed && dot(v_fnrm, v) < 0.0) discard;
    vec3 n = normalize(v_nrm);
    // Two-sided lighting: open meshes and thin leaves are seen from both sides.
    if (dot(n, v) < 0.0) n = -n;
    vec3 albedo = v_col;
    if (u_use_tex) albedo *= texture(u_tex, v_uv).rgb;
    vec3 c = albedo * u_ambient;
    for (int i = 0; i < 2; ++i) {
        vec3 l = u_light_dir[i];
        float ndl = max(dot(n, l), 0.0);
        c += albedo * u_light_col[i] * ndl;
        if (u_ks > 0.0 && ndl > 0.0) {
            vec3 h = normalize(l + v);
            c += u_ks * u_light_col[i] * pow(max(dot(n, h), 0.0), u_shininess);
        }
    }
    f_color = vec4(clamp(c, 0.0, 1.0), 1.0);
    f_depth = vec4(dot(v_pos - u_eye, u_forward), 0.0, 0.0, 1.0);
}
"""


def gl_projection(intr: Intrinsics, near: float, far: float) -> np.ndarray:
    """(4, 4) float64: OpenCV camera coordinates -> GL clip coordinates.

    Window x = u and window y = v, with (u, v) the OpenCV pixel coordinates (centres at
    +0.5): ndc_x = 2u/W - 1, ndc_y = 2v/H - 1, so row 0 of the read-back image is the top.
    Depth maps z in [near, far] to ndc [-1, 1]; w = z.
    """
    w, h = intr.width, intr.height
    return np.array(
        [
            [2 * intr.fx / w, 0.0, 2 * intr.cx / w - 1.0, 0.0],
            [0.0, 2 * intr.fy / h, 2 * intr.cy / h - 1.0, 0.0],
            [0.0, 0.0, (far + near) / (far - near), -2 * far * near / (far - near)],
            [0.0, 0.0, 1.0, 0.0],
        ],
        dtype=np.float64,
    )


def mesh_arrays(mesh) -> tuple[np.ndarray, np.ndarray | None]:
    """De-indexed vertex data of one trimesh for a non-indexed draw.

    Returns (vertices (3F, 14) float32 [pos 3, normal 3, uv 2, linear colour 3, face normal 3],
    texture (h, w, 3) float32 linear or None). Face colours, vertex colours and textures
    (SimpleMaterial.image or PBR baseColorTexture with UVs) are all supported; colours are
    display space in the file and converted to linear intensity here.
    """
    faces = np.asarray(mesh.faces, dtype=np.int64)
    pos = np.asarray(mesh.vertices, dtype=np.float32)[faces].reshape(-1, 3)
    nrm = np.asarray(mesh.vertex_normals, dtype=np.float32)[faces].reshape(-1, 3)
    uv = np.zeros((len(pos), 2), np.float32)
    col = np.ones((len(pos), 3), np.float32)
    texture = None
    visual = mesh.visual
    if visual.kind == "texture":
        mat = visual.material
        image = getattr(mat, "image", None)
        if image is None:
            image = getattr(mat, "baseColorTexture", None)
        if image is not None and visual.uv is not None and len(visual.uv) == len(mesh.vertices):
            img = np.asarray(image.convert("RGB"), dtype=np.float32) / 255.0
            # trimesh UVs have v up (OpenGL); image row 0 is the top, so flip for upload.
            texture = np.ascontiguousarray(img[::-1]) ** GAMMA
            uv = np.asarray(visual.uv, dtype=np.float32)[faces].reshape(-1, 2)
            # glTF multiplies the texture by baseColorFactor; an OBJ's Kd beside map_Kd (and
            # trimesh's default grey diffuse) is ignored, as Blender does.
            col[:] = _material_color(mat, keys=("baseColorFactor",))
        else:
            col[:] = _material_color(mat)
    elif visual.kind == "vertex":
        vc = np.asarray(visual.vertex_colors, dtype=np.float32)[:, :3] / 255.0
        col = vc[faces].reshape(-1, 3) ** GAMMA
    else:  # "face" or None (trimesh's default colour)
        fc = np.asarray(visual.face_colors, dtype=np.float32)[:, :3] / 255.0
        col = np.repeat(fc, 3, axis=0) ** GAMMA
    # Face normals, oriented to the side the vertex normals point to (outward for solids).
    tri = pos.reshape(-1, 3, 3)
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    flip = (fn * nrm.reshape(-1, 3, 3).sum(1)).sum(-1) < 0
    fn[flip] *= -1
    fn = np.repeat(fn, 3, axis=0)
    data = np.concatenate([pos, nrm, uv, col, fn], axis=1).astype(np.float32)
    return np.ascontiguousarray(data), texture


def _material_color(mat, keys=("baseColorFactor", "diffuse")) -> np.ndarray:
    """Linear base colour of a trimesh material from the first of `keys` it has (else white)."""
    for key in keys:
        c = getattr(mat, key, None)
        if c is not None:
            c = np.asarray(c, dtype=np.float32)[:3]
            return (c / 255.0 if c.max() > 1.0 else c) ** GAMMA
    return np.ones(3, np.float32)


class GLRenderer:
    """Renders a `SynthScene` from OpenCV cameras into linear RGB float32 images.

    One EGL context per renderer, reused across frames; frames are drawn in batches whose
    read-back goes through one pixel-buffer object (one sync per batch, not per frame).

    intrinsics: the sensor (k1/k2 ≠ 0 renders wider and resamples); scene: a SynthScene;
    samples: MSAA samples; near/far: clip distances in world units; batch: frames per
    read-back; supersample: s renders at s x the resolution and box-filters (s² x MSAA
    samples per pixel, ~s² x the time); lit: False draws each surface in its own colour
    (texture x vertex colour, no lights or highlights), for meshes whose colours were baked
    from a radiance field and so already hold the scene's light.
    """

    def __init__(
        self,
        intrinsics: Intrinsics,
        scene=None,
        samples: int = 4,
        near: float = 0.05,
        far: float = 100.0,
        batch: int = 16,
        supersample: int = 1,
        lit: bool = True,
    ):
        import moderngl

        try:
            self.ctx = moderngl.create_standalone_context(backend="egl")
        except Exception as e:  # no EGL display / driver: tell the user in one line
            raise FastenerfError(f"cannot create a headless EGL OpenGL context ({e})") from None
        self.out_intr = intrinsics
        self.canvas, self._remap = _undistorted_canvas(intrinsics)
        self.ss = max(1, int(supersample))
        self.intr = self.canvas.scaled(self.ss) if self.ss > 1 else self.canvas
        self.samples = max(0, min(samples, self.ctx.max_samples))
        self.near, self.far, self.batch = near, far, max(1, batch)
        self.prog = self.ctx.program(vertex_shader=_VERT, fragment_shader=_FRAG)
        self.prog["u_light_dir"].write(LIGHT_DIRS.tobytes())
        self.prog["u_light_col"].write((LIGHT_COLORS * lit).tobytes())
        self.prog["u_ambient"].value = AMBIENT if lit else 1.0
        self.prog["u_tex"].value = 0
        self._frame_bytes = self.intr.width * self.intr.height * 3 * 4
        self._pbo = self.ctx.buffer(reserve=self._frame_bytes * self.batch)
        self._targets: dict[bool, tuple] = {}
        self._draws: list = []
        self._resources: list = []
        self.background_linear = np.zeros(3, np.float32)
        if scene is not None:
            self.set_scene(scene)

    def set_scene(self, scene) -> None:
        """Upload a scene's meshes and textures (replacing any previous scene)."""
        self._release_scene()
        for obj in scene.objects:
            data, tex = mesh_arrays(obj.mesh)
            vbo = self.ctx.buffer(data.tobytes())
            vao = self.ctx.vertex_array(
                self.prog,
                [(vbo, "3f 3f 2f 3f 3f", "in_pos", "in_nrm", "in_uv", "in_col", "in_fnrm")],
            )
            texture = None
            if tex is not None:
                texture = self.ctx.texture(
                    (tex.shape[1], tex.shape[0]), 3, tex.astype(np.float16).tobytes(), dtype="f2"
                )
                texture.build_mipmaps()
                # Trilinear; anisotropic filtering costs 3-5x per frame on llvmpipe.
                texture.filter = (self.ctx.LINEAR_MIPMAP_LINEAR, self.ctx.LINEAR)
                texture.repeat_x = texture.repeat_y = True
            self._resources += [r for r in (vbo, vao, texture) if r is not None]
            self._draws.append((vao, texture, obj.material))
        self.background_linear = np.asarray(scene.background, np.float32) ** GAMMA

    def render(self, c2w: np.ndarray, depth: bool = False):
        """Render views at camera-to-world poses `c2w` (N, 4, 4) or (4, 4), OpenCV.

        Returns rgb (N, H, W, 3) float32 linear in [0, 1] (or (H, W, 3) for one pose), and with
        `depth=True` also (N, H, W) float32 camera z in world units (0 where nothing is hit;
        edge pixels average the samples).
        """
        c2w = np.asarray(c2w, dtype=np.float64)
        single = c2w.ndim == 2
        c2w = c2w.reshape(-1, 4, 4)
        rgbs, depths = [], []
        for i in range(0, len(c2w), self.batch):
            r, d = self._render_batch(c2w[i : i + self.batch], depth)
            rgbs.append(r)
            depths.append(d)
        rgb = np.concatenate(rgbs)
        dep = np.concatenate(depths) if depth else None
        if self.ss > 1:  # box filter: each output pixel averages its s x s sub-pixels
            rgb, dep = self._downsample(rgb, dep)
        if self._remap is not None:
            rgb = self._remap(rgb)
            dep = self._remap(dep[..., None])[..., 0] if depth else None
        if single:
            rgb = rgb[0]
            dep = dep[0] if depth else None
        return (rgb, dep) if depth else rgb

    def _downsample(self, rgb: np.ndarray, dep: np.ndarray | None):
        n, s = len(rgb), self.ss
        h, w = self.canvas.height, self.canvas.width
        rgb = rgb.reshape(n, h, s, w, s, 3).mean((2, 4), dtype=np.float32)
        if dep is not None:
            d = dep.reshape(n, h, s, w, s)
            hits = (d > 0).sum((2, 4))
            dep = np.where(hits > 0, d.sum((2, 4)) / np.maximum(hits, 1), 0).astype(np.float32)
        return rgb, dep

    def _framebuffers(self, depth: bool):
        """(MSAA framebuffer, resolved framebuffer[, depth read-back buffer]), made on first use.

        Depth is a second colour attachment (camera z), only attached when asked for: it
        costs ~20% per frame on llvmpipe.
        """
        if depth not in self._targets:
            c, size, s = self.ctx, (self.intr.width, self.intr.height), self.samples
            n = 2 if depth else 1
            ms = c.framebuffer(
                [c.renderbuffer(size, 4, samples=s, dtype="f4") for _ in range(n)],
                c.depth_renderbuffer(size, samples=s),
            )
            res = c.framebuffer([c.renderbuffer(size, 4, dtype="f4") for _ in range(n)])
            pbo = c.buffer(reserve=size[0] * size[1] * 16 * self.batch) if depth else None
            self._targets[depth] = (ms, res, pbo)
        return self._targets[depth]

    def _render_batch(self, c2w: np.ndarray, depth: bool):
        ctx = self.ctx
        proj = gl_projection(self.intr, self.near, self.far)
        w, h = self.intr.width, self.intr.height
        ms_fbo, fbo, pbo_depth = self._framebuffers(depth)
        bg = self.background_linear.tolist()
        ctx.enable(ctx.DEPTH_TEST)
        ctx.disable(ctx.CULL_FACE)
        for b, pose in enumerate(c2w):
            world_to_clip = (proj @ np.linalg.inv(pose)).astype(np.float32)
            ms_fbo.use()
            # Background with alpha 0, surfaces with alpha 1: after the resolve (sample average)
            # alpha is the coverage, which recovers depth at edge pixels.
            ms_fbo.clear(*bg, 0.0, depth=1.0)
            self.prog["u_world_to_clip"].write(world_to_clip.T.tobytes())
            self.prog["u_eye"].value = tuple(pose[:3, 3])
            self.prog["u_forward"].value = tuple(pose[:3, 2])
            for vao, texture, mat in self._draws:
                self.prog["u_use_tex"].value = texture is not None
                self.prog["u_ks"].value = float(mat.specular)
                self.prog["u_shininess"].value = float(mat.shininess)
                self.prog["u_closed"].value = bool(getattr(mat, "closed", False))
                if texture is not None:
                    texture.use(0)
                vao.render()
            ctx.copy_framebuffer(fbo, ms_fbo)  # MSAA resolve (sample average)
            fbo.read_into(
                self._pbo,
                components=3,
                attachment=0,
                dtype="f4",
                write_offset=b * self._frame_bytes,
            )
            if depth:
                fbo.read_into(
                    pbo_depth,
                    viewport=(0, 0, w, h),
                    components=4,
                    attachment=1,
                    dtype="f4",
                    write_offset=b * w * h * 16,
                )
        n = len(c2w)
        rgb = np.frombuffer(self._pbo.read(size=n * self._frame_bytes), np.float32)
        rgb = rgb.reshape(n, h, w, 3)
        dep = None
        if depth:
            zc = np.frombuffer(pbo_depth.read(size=n * w * h * 16), np.float32).reshape(n, h, w, 4)
            cover = zc[..., 3]
            # Resolved R = cover * z + (1 - cover) * background red; invert for z.
            dep = (zc[..., 0] - (1.0 - cover) * bg[0]) / np.maximum(cover, 1e-6)
            dep[cover < 1e-6] = 0.0
        return rgb, dep

    def _release_scene(self) -> None:
        for r in self._resources:
            r.release()
        self._resources, self._draws = [], []

    def release(self) -> None:
        """Free the GL objects and the context."""
        if getattr(self, "ctx", None) is not None:
            self._release_scene()
            self.ctx.release()
            self.ctx = None

    def __enter__(self) -> GLRenderer:
        return self

    def __exit__(self, *exc) -> None:
        self.release()


def _undistorted_canvas(intr: Intrinsics):
    """Intrinsics to render at, and a remap (or None) from that render to the sensor.

    With distortion, the undistorted canvas is grown to cover the undistorted position of
    every sensor pixel (same fx, fy); each sensor pixel then samples it bilinearly.
    """
    if not intr.distorted:
        return intr, None
    u, v = np.meshgrid(np.arange(intr.width) + 0.5, np.arange(intr.height) + 0.5)
    d = intr.pixel_to_camera(u.ravel(), v.ravel())[:, :2]  # undistorted normalised coords
    pu, pv = d[:, 0] * intr.fx, d[:, 1] * intr.fy  # pixel offsets from the principal point
    x0, x1 = np.floor(pu.min()) - 2, np.ceil(pu.max()) + 2
    y0, y1 = np.floor(pv.min()) - 2, np.ceil(pv.max()) + 2
    x0, y0 = max(x0, -2.0 * intr.width), max(y0, -2.0 * intr.height)
    x1, y1 = min(x1, 2.0 * intr.width), min(y1, 2.0 * intr.height)
    canvas = Intrinsics(intr.fx, intr.fy, -x0, -y0, int(x1 - x0), int(y1 - y0))
    # Array coordinates in the canvas image (pixel centres at integer index + 0.5).
    sx = np.clip(pu - x0 - 0.5, 0, canvas.width - 1.001)
    sy = np.clip(pv - y0 - 0.5, 0, canvas.height - 1.001)
    ix, iy = np.floor(sx).astype(np.int64), np.floor(sy).astype(np.int64)
    fx, fy = (sx - ix).astype(np.float32), (sy - iy).astype(np.float32)
    idx = iy * canvas.width + ix
    wts = [((1 - fx) * (1 - fy)), (fx * (1 - fy)), ((1 - fx) * fy), (fx * fy)]
    offs = [0, 1, canvas.width, canvas.width + 1]

    def remap(img: np.ndarray) -> np.ndarray:
        n, c = img.shape[0], img.shape[-1]
        flat = img.reshape(n, -1, c)
        out = sum(flat[:, idx + o] * wt[None, :, None] for o, wt in zip(offs, wts, strict=True))
        return out.reshape(n, intr.height, intr.width, c).astype(np.float32)

    return canvas, remap
