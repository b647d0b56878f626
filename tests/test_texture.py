"""Textured meshes: UV atlas, texel rasterisation, the bake from a field, GLB / OBJ export,
`fastenerf mesh --texture` and the mesh-vs-field benchmark."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from fastenerf.errors import InputError
from fastenerf.mesh import extract_mesh
from fastenerf.texture import bake_texture, dilate, export_textured, rasterize_uv


def ball_density(x: torch.Tensor) -> torch.Tensor:
    """A ball of radius 0.5 at the origin, σ = 100 inside (surface at σ = 50)."""
    return 100.0 * torch.sigmoid((0.5 - x.norm(dim=-1)) / 0.01)


def position_colour(x: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """A colour that tells where it was taken: (x + 1) / 2, the same from every direction."""
    return ((x + 1.0) / 2.0).clamp(0.0, 1.0)


@pytest.fixture(scope="module")
def ball():
    return extract_mesh(
        ball_density, None, [-1, -1, -1, 1, 1, 1], resolution=28, threshold=50.0, progress=False
    )


def sample_texture(mesh, points: np.ndarray, face_idx: np.ndarray) -> np.ndarray:
    """Bilinear texture look-up (as a GPU samples it) at surface points: (N, 3) in [0, 1]."""
    import trimesh

    mat = mesh.visual.material
    image = mat.baseColorTexture if hasattr(mat, "baseColorTexture") else mat.image
    img = np.asarray(image.convert("RGB"), np.float64) / 255.0
    h, w = img.shape[:2]
    bc = trimesh.triangles.points_to_barycentric(mesh.triangles[face_idx], points)
    uv = (np.asarray(mesh.visual.uv)[mesh.faces[face_idx]] * bc[..., None]).sum(1)
    x, y = uv[:, 0] * w - 0.5, (1.0 - uv[:, 1]) * h - 0.5
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]

    def at(i, j):
        return img[np.clip(i, 0, h - 1), np.clip(j, 0, w - 1)]

    return (
        at(y0, x0) * (1 - fx) * (1 - fy)
        + at(y0, x0 + 1) * fx * (1 - fy)
        + at(y0 + 1, x0) * (1 - fx) * fy
        + at(y0 + 1, x0 + 1) * fx * fy
    )


def test_rasterize_uv_covers_each_texel_centre_once():
    # Two triangles tiling the square [0.1, 0.9]²: every texel centre inside is covered, and
    # the barycentric coordinates give back the centre's uv.
    uv = np.array([[0.1, 0.1], [0.9, 0.1], [0.9, 0.9], [0.1, 0.9]])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    w, h = 20, 10
    face, bary = rasterize_uv(uv, faces, w, h)
    jj, ii = np.meshgrid(np.arange(w), np.arange(h))
    u, v = (jj + 0.5) / w, 1.0 - (ii + 0.5) / h
    inside = (u > 0.1) & (u < 0.9) & (v > 0.1) & (v < 0.9)
    assert np.array_equal(face >= 0, inside)
    got = (uv[faces[face[inside]]] * bary[inside][..., None]).sum(1)
    np.testing.assert_allclose(got, np.stack([u[inside], v[inside]], -1), atol=1e-6)
    assert np.all(bary[inside] >= -1e-6) and np.allclose(bary[inside].sum(1), 1)
    # A triangle with no area in texture space covers nothing (and does not divide by zero).
    face, _ = rasterize_uv(np.array([[0.2, 0.2], [0.5, 0.5], [0.8, 0.8]]), faces[:1], w, h)
    assert (face < 0).all()


def test_dilate_fills_only_near_texels():
    img = np.zeros((1, 9, 3), np.float32)
    cov = np.zeros((1, 9), bool)
    img[0, 4], cov[0, 4] = [1, 0.5, 0.25], True
    out = dilate(img, cov, 2)
    assert out[0, 2:7].tolist() == [[1, 0.5, 0.25]] * 5
    assert not out[0, [0, 1, 7, 8]].any()


def test_baked_texture_reproduces_the_field_colour(ball):
    """Bilinear look-ups at random surface points (seams and island borders included) give
    the field's colour at the point. Without the dilation, look-ups near island borders
    mix in the empty atlas."""
    import trimesh

    textured, st = bake_texture(position_colour, ball, size=128, n_dirs=2, progress=False)
    assert len(textured.faces) == len(ball.faces)
    w, h = st["texture"]
    assert textured.visual.material.image.size == (w, h) and 64 <= min(w, h) <= max(w, h) <= 256
    assert 0.3 < st["utilisation"] < 0.95
    p, fi = trimesh.sample.sample_surface(textured, 20000, seed=3)
    err = np.abs(sample_texture(textured, p, fi) - (p + 1) / 2).max(1)
    # A texel spans ~0.015 world units here, so the colour ramp moves ~0.005 across one.
    assert np.percentile(err, 99) < 0.015 and err.max() < 0.1
    bare, _ = bake_texture(position_colour, ball, size=128, n_dirs=2, dilation=0, progress=False)
    err = np.abs(sample_texture(bare, p, fi) - (p + 1) / 2).max(1)
    assert np.percentile(err, 99) > 0.1


def test_texel_colour_is_seen_from_outside(ball):
    """A colour that depends on the view: white for rays travelling inwards."""

    def inward_white(x, d):
        return ((d * x).sum(-1) < 0).float()[:, None].expand(-1, 3)

    textured, _ = bake_texture(inward_white, ball, size=64, n_dirs=4, progress=False)
    img = np.asarray(textured.visual.material.image)
    covered = img.any(-1)  # dilated islands; the empty atlas stays black
    assert covered.mean() > 0.3 and (img[covered] == 255).all()


def test_simplified_mesh_keeps_its_shape_and_the_texture_its_colour(ball):
    import trimesh

    from fastenerf.mesh import decimate

    assert decimate(ball, len(ball.faces)) is ball
    coarse = decimate(ball, 400)
    assert 300 <= len(coarse.faces) <= 400 < len(ball.faces) / 4
    r = np.linalg.norm(coarse.vertices, axis=1)
    assert np.abs(r - 0.5).max() < 0.03 and coarse.volume > 0
    assert abs(coarse.volume / ball.volume - 1) < 0.05
    # The colour ramp survives on the coarse geometry: the texture holds it, not the vertices.
    textured, _ = bake_texture(position_colour, coarse, size=128, n_dirs=1, progress=False)
    p, fi = trimesh.sample.sample_surface(textured, 5000, seed=2)
    err = np.abs(sample_texture(textured, p, fi) - (p + 1) / 2).max(1)
    assert np.percentile(err, 99) < 0.015
    with pytest.raises(InputError, match="at least 4"):
        decimate(ball, 2)


def test_textured_glb_and_obj_load_with_uvs_and_image(ball, tmp_path):
    import trimesh

    textured, st = bake_texture(position_colour, ball, size=64, n_dirs=1, progress=False)
    glb = export_textured(textured, tmp_path / "ball.glb")
    obj = export_textured(textured, tmp_path / "m" / "ball.obj")
    assert glb == [tmp_path / "ball.glb"]
    assert sorted(p.name for p in obj) == ["ball.mtl", "ball.obj", "ball.png"]
    assert "map_Kd ball.png" in (tmp_path / "m" / "ball.mtl").read_text()
    for path in (glb[0], tmp_path / "m" / "ball.obj"):
        back = trimesh.load(path, force="mesh")
        assert back.visual.kind == "texture" and len(back.faces) == len(ball.faces)
        assert back.visual.uv.shape == (len(back.vertices), 2)
        mat = back.visual.material
        image = mat.baseColorTexture if hasattr(mat, "baseColorTexture") else mat.image
        assert image.size == tuple(st["texture"])
        np.testing.assert_array_equal(
            np.asarray(image.convert("RGB")), textured.visual.material.image
        )
        p, fi = trimesh.sample.sample_surface(back, 2000, seed=1)
        err = np.abs(sample_texture(back, p, fi) - (p + 1) / 2).max(1)
        assert np.median(err) < 0.02  # UVs survive the round trip
    with pytest.raises(InputError, match="textured mesh"):
        export_textured(textured, tmp_path / "ball.ply")
    assert not list(tmp_path.glob(".*tmp*"))  # no temporaries left behind


def test_textured_mesh_renders_like_its_colours(ball):
    """The unlit GL render of the texture matches the render of the vertex colours, and both
    show the field's colour ramp (left of the image darker in red than the right)."""
    from fastenerf.data.rig import Intrinsics, look_at
    from fastenerf.errors import FastenerfError
    from fastenerf.mesh import render_views, vertex_colors

    textured, _ = bake_texture(position_colour, ball, size=128, n_dirs=1, progress=False)
    vc = vertex_colors(
        position_colour,
        np.asarray(ball.vertices),
        np.asarray(ball.vertex_normals),
        1,
        progress=False,
    )
    coloured = ball.copy()
    rgba = np.concatenate([np.round(vc * 255), np.full((len(vc), 1), 255)], 1)
    coloured.visual.vertex_colors = rgba.astype(np.uint8)
    intr = Intrinsics(60.0, 60.0, 32.0, 24.0, 64, 48)
    c2w = look_at(np.array([[0.0, 0.0, 2.5]]), np.zeros((1, 3)), np.array([0.0, 1.0, 0.0]))
    try:
        a = render_views(textured, intr, c2w, (0.0, 0.0, 0.0))[0]
        b = render_views(coloured, intr, c2w, (0.0, 0.0, 0.0))[0]
    except FastenerfError as e:  # no EGL on this machine
        pytest.skip(str(e))
    solid = a.sum(-1) > 0.05
    assert solid[24, 32] and not solid[0, 0]
    assert np.abs(a - b)[solid].mean() < 0.01
    # Unlit: the centre pixel sees the point (0, 0, 0.5), colour (0.5, 0.5, 0.75).
    np.testing.assert_allclose(a[24, 32], [0.5, 0.5, 0.75], atol=0.02)
    assert a[24, 26, 0] < a[24, 38, 0] - 0.05 and a[18, 32, 1] > a[30, 32, 1] + 0.05


def test_mesh_cli_texture(untrained_run, tmp_path):
    import trimesh

    from fastenerf.cli import main as cli

    run, level = untrained_run
    common = ["--resolution", "16", "--threshold", f"{level:.6g}", "--dirs", "1"]
    outs = [tmp_path / "t.glb", tmp_path / "obj" / "t.obj"]
    rc = cli(
        ["mesh", str(run), "--out", *map(str, outs), "--texture", "--texture-size", "32", *common]
        + ["--png", str(tmp_path / "t_preview.png")]
    )
    assert rc == 0 and (tmp_path / "t_preview.png").is_file()
    assert (tmp_path / "obj" / "t.mtl").is_file() and (tmp_path / "obj" / "t.png").is_file()
    for out in outs:
        back = trimesh.load(out, force="mesh")
        assert back.visual.kind == "texture" and back.visual.uv.shape == (len(back.vertices), 2)
        mat = back.visual.material
        image = mat.baseColorTexture if hasattr(mat, "baseColorTexture") else mat.image
        assert min(image.size) >= 16
    # Without --texture: vertex colours as before.
    assert cli(["mesh", str(run), "--out", str(tmp_path / "v.ply"), *common]) == 0
    assert trimesh.load(tmp_path / "v.ply").visual.kind == "vertex"
    assert cli(["mesh", str(run), "--out", str(tmp_path / "s.ply"), "--faces", "64", *common]) == 0
    small, full = trimesh.load(tmp_path / "s.ply"), trimesh.load(tmp_path / "v.ply")
    # (a fog of small pieces cannot all shrink to the target: fewer faces, not exactly 64)
    assert len(small.faces) < len(full.faces) / 2 and small.visual.kind == "vertex"
    # Bad requests: one line, exit 2, nothing written.
    assert cli(["mesh", str(run), "--out", str(tmp_path / "x.ply"), "--texture"]) == 2
    bad = ["--out", str(tmp_path / "y.glb"), "--texture", "--texture-size", "4"]
    assert cli(["mesh", str(run), *bad]) == 2
    clash = ["--out", str(tmp_path / "z.obj"), "--texture", "--png", str(tmp_path / "z.png")]
    assert cli(["mesh", str(run), *clash]) == 2
    assert cli(["mesh", str(run), "--out", str(tmp_path / "w.ply"), "--faces", "3"]) == 2
    assert not any((tmp_path / n).exists() for n in ("x.ply", "y.glb", "z.obj", "w.ply"))


def test_mesh_texture_benchmark(untrained_run, tmp_path):
    from benchmarks.mesh_texture import main
    from fastenerf.errors import FastenerfError

    run, level = untrained_run
    try:
        from fastenerf.data.rig import Intrinsics
        from fastenerf.data.synth.gl import GLRenderer

        GLRenderer(Intrinsics(8.0, 8.0, 4.0, 4.0, 8, 8)).release()
    except FastenerfError as e:
        pytest.skip(str(e))
    out = tmp_path / "bench"
    args = [str(run), "--out", str(out), "--resolution", "16", "--threshold", f"{level:.6g}"]
    assert main(args + ["--texture-size", "32", "--dirs", "1", "--views", "2"]) == 0
    res = json.loads((out / "mesh_texture.json").read_text())
    assert res["views"] == 2 and res["poses"] in ("test", "orbit")
    assert min(res["texture"]["size"]) >= 16 and res["texture"]["bake_s"] > 0
    # The mesh is a level set of the fog of an untrained field, so only sanity here: the
    # renders agree where nothing is drawn, and a PSNR was measured for each colouring.
    assert all(np.isfinite(res["psnr"][k]) for k in ("textured", "vertex_colours"))
    assert "| texture |" in (out / "mesh_texture.md").read_text()
    assert (out / "mesh_texture.png").is_file() and (out / "mesh.glb").is_file()
    assert main([str(run), "--out", str(out), "--views", "0"]) == 2
