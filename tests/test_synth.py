"""GL renderer (real EGL context), built-in scenes, and `fastenerf synth` end to end."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from PIL import Image
from scipy.spatial import ConvexHull

from fastenerf.cli import main
from fastenerf.data.events import EventIndex
from fastenerf.data.formats.native import load_scene
from fastenerf.data.rig import BAYER_RGGB, Intrinsics, Rig, look_at
from fastenerf.data.synth import (
    Material,
    SceneObject,
    SynthScene,
    build_scene,
    list_scenes,
    load_mesh,
    make_scene,
)
from fastenerf.data.synth.gl import AMBIENT, LIGHT_COLORS, LIGHT_DIRS, GLRenderer, mesh_arrays
from fastenerf.errors import InputError

BG = (0.5, 0.5, 0.5)  # display space


def quad(x0, x1, y0, y1, z, texture=None, color=None) -> trimesh.Trimesh:
    """Axis-aligned rectangle in the plane z, normal +z, UV (0,0) at (x0, y0)."""
    v = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], dtype=np.float64)
    m = trimesh.Trimesh(
        v, [[0, 1, 2], [0, 2, 3]], vertex_normals=np.tile([0, 0, 1.0], (4, 1)), process=False
    )
    if texture is not None:
        uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=np.float64)
        mat = trimesh.visual.material.SimpleMaterial(
            image=Image.fromarray(texture), diffuse=[255, 255, 255, 255]
        )
        m.visual = trimesh.visual.TextureVisuals(uv=uv, material=mat)
    elif color is not None:
        m.visual.vertex_colors = np.tile(np.r_[color, 255], (4, 1)).astype(np.uint8)
    return m


def shading(normal) -> np.ndarray:
    """Expected Lambert factor per channel (no specular) for a world normal."""
    n = np.asarray(normal, np.float64)
    return AMBIENT + (LIGHT_COLORS * np.maximum(LIGHT_DIRS @ n, 0)[:, None]).sum(0)


def front_camera(dist=3.0):
    """OpenCV camera on +z looking at the origin, world +y up in the image."""
    return look_at(np.array([[0.0, 0.0, dist]]), np.zeros((1, 3)), np.array([0.0, 1.0, 0.0]))[0]


def test_projection_covers_exactly_the_projected_rectangle():
    # Off-centre principal point and fx != fy catch mistakes in the GL projection.
    intr = Intrinsics(52.0, 47.0, 21.3, 13.7, 40, 30)
    m = quad(-0.5, 0.7, -0.3, 0.4, 0.0, color=(200, 200, 200))
    c2w = front_camera(3.0)
    with GLRenderer(intr, SynthScene("q", [SceneObject(m)], BG)) as gl:
        rgb, depth = gl.render(c2w, depth=True)
    bg = np.float32(BG[0]) ** 2.2
    inside = np.float32(200 / 255) ** 2.2 * shading([0, 0, 1])
    cover = (rgb - bg) / (inside - bg)  # fraction of each pixel the quad covers
    w2c = np.linalg.inv(c2w)
    corners = np.c_[m.vertices, np.ones(4)] @ w2c.T
    uv = intr.project(corners[:, :3])
    u0, v0 = uv.min(0)
    u1, v1 = uv.max(0)
    # Exact area of each pixel [i, i+1) x [j, j+1) inside the projected rectangle.
    ax = np.clip(np.minimum(np.arange(40) + 1, u1) - np.maximum(np.arange(40), u0), 0, 1)
    ay = np.clip(np.minimum(np.arange(30) + 1, v1) - np.maximum(np.arange(30), v0), 0, 1)
    area = ay[:, None] * ax[None, :]
    full, empty = area == 1, area == 0
    assert full.sum() > 150 and empty.sum() > 300
    np.testing.assert_allclose(cover[full], 1.0, atol=1e-3)
    np.testing.assert_allclose(cover[empty], 0.0, atol=1e-3)
    edge = ~full & ~empty
    assert np.abs(cover[edge].mean(-1) - area[edge]).max() <= 0.5  # 4x MSAA quantisation
    assert np.abs(cover[edge].mean(-1) - area[edge]).mean() < 0.15
    np.testing.assert_allclose(depth[full], 3.0, rtol=1e-4)
    assert np.all(depth[empty] == 0)
    # Supersampling x2 (16 samples per pixel) halves the coverage quantisation.
    with GLRenderer(intr, SynthScene("q", [SceneObject(m)], BG), supersample=2) as gl:
        cover2 = (gl.render(c2w) - bg) / (inside - bg)
    np.testing.assert_allclose(cover2[full], 1.0, atol=1e-3)
    np.testing.assert_allclose(cover2[empty], 0.0, atol=1e-3)
    assert np.abs(cover2[edge].mean(-1) - area[edge]).max() <= 0.25


def test_closed_material_drops_only_hidden_faces():
    intr = Intrinsics(60.0, 60.0, 32.0, 24.0, 64, 48)
    box = trimesh.creation.box([0.8, 0.6, 1.0])
    box.apply_transform(trimesh.transformations.rotation_matrix(0.4, [1, 1, 0]))
    c2w = look_at(np.array([[1.5, 1.2, 2.6]]), np.zeros((1, 3)), np.array([0.0, 1.0, 0.0]))[0]
    imgs = []
    for closed in (False, True):
        with GLRenderer(
            intr, SynthScene("c", [SceneObject(box, Material(closed=closed))], BG)
        ) as gl:
            imgs.append(gl.render(c2w))
    np.testing.assert_allclose(imgs[0], imgs[1], atol=1e-6)  # a solid looks the same
    # An open quad facing away from the camera: drawn two-sided, dropped if "closed".
    back = quad(-0.5, 0.5, -0.5, 0.5, 0.0, color=(200, 50, 50))
    behind = look_at(np.array([[0.0, 0.0, -3.0]]), np.zeros((1, 3)), np.r_[0, 1.0, 0])[0]
    bg = np.float32(BG[0]) ** 2.2
    for closed, drawn in ((False, True), (True, False)):
        with GLRenderer(
            intr, SynthScene("q", [SceneObject(back, Material(closed=closed))], BG)
        ) as gl:
            img = gl.render(behind)
        assert (np.abs(img - bg).max() > 0.05) == drawn


def test_silhouette_of_a_cube_from_a_general_pose():
    intr = Intrinsics(60.0, 60.0, 32.0, 24.0, 64, 48)
    box = trimesh.creation.box([0.8, 0.6, 1.0])
    box.apply_transform(trimesh.transformations.rotation_matrix(0.4, [1, 1, 0]))
    box.apply_translation([0.1, -0.05, 0.0])
    c2w = look_at(np.array([[1.5, 1.2, 2.6]]), np.zeros((1, 3)), np.array([0.0, 1.0, 0.0]))[0]
    with GLRenderer(intr, SynthScene("c", [SceneObject(box)], BG)) as gl:
        _, depth = gl.render(c2w, depth=True)
    hit = depth > 0
    p_cam = (np.c_[box.vertices, np.ones(8)] @ np.linalg.inv(c2w).T)[:, :3]
    hull = ConvexHull(intr.project(p_cam))  # a convex body's silhouette: hull of its corners
    yy, xx = np.mgrid[0:48, 0:64]
    centres = np.stack([xx + 0.5, yy + 0.5], -1)
    # Signed distance (pixels) of each pixel centre to the hull: max over its edges' lines.
    dist = (centres @ hull.equations[:, :2].T + hull.equations[:, 2]).max(-1)
    assert (dist < -1.0).sum() > 200
    assert hit[dist < -1.0].all()
    assert not hit[dist > 1.0].any()
    assert (dist < -0.5).sum() <= hit.sum() <= (dist < 0.75).sum()


def test_texture_orientation_and_colours():
    # Texture quadrants: top-left red, top-right green, bottom-left blue, bottom-right white.
    tex = np.zeros((64, 64, 3), np.uint8)
    tex[:32, :32] = (255, 0, 0)
    tex[:32, 32:] = (0, 255, 0)
    tex[32:, :32] = (0, 0, 255)
    tex[32:, 32:] = (255, 255, 255)
    m = quad(-1, 1, -1, 1, 0.0, texture=tex)
    intr = Intrinsics(40.0, 40.0, 32.0, 32.0, 64, 64)
    with GLRenderer(intr, SynthScene("t", [SceneObject(m)], BG)) as gl:
        rgb = gl.render(front_camera(3.0))
    s = shading([0, 0, 1])
    # The quad spans pixels ~[18.7, 45.3]; sample well inside each quadrant.
    expect = {(24, 24): (1, 0, 0), (24, 40): (0, 1, 0), (40, 24): (0, 0, 1), (40, 40): (1, 1, 1)}
    for (y, x), c in expect.items():
        np.testing.assert_allclose(rgb[y, x], np.array(c) * s, atol=2e-3, err_msg=f"{(y, x)}")


def test_vertex_and_face_colours_linearised():
    m = quad(-1, 1, -1, 1, 0.0, color=(255, 128, 0))
    f = quad(-1, 1, -1, 1, 0.0)
    f.visual.face_colors = [[0, 64, 255, 255], [255, 255, 0, 255]]
    intr = Intrinsics(40.0, 40.0, 32.0, 32.0, 64, 64)
    s = shading([0, 0, 1])
    with GLRenderer(intr, SynthScene("v", [SceneObject(m)], BG)) as gl:
        rgb = gl.render(front_camera(3.0))
        np.testing.assert_allclose(
            rgb[32, 32], np.array([1.0, (128 / 255) ** 2.2, 0.0]) * s, rtol=1e-3, atol=1e-4
        )
        np.testing.assert_allclose(rgb[2, 2], np.float32(0.5) ** 2.2, rtol=1e-4)  # background
        gl.set_scene(SynthScene("f", [SceneObject(f)], BG))
        rgb = gl.render(front_camera(3.0))
    # Face 0 (corners 0,1,2) is the lower-right triangle in the image, face 1 the upper-left.
    np.testing.assert_allclose(rgb[40, 40], np.array([0, (64 / 255) ** 2.2, 1.0]) * s, atol=1e-3)
    np.testing.assert_allclose(rgb[24, 24], np.array([1.0, 1.0, 0.0]) * s, atol=1e-3)


def test_specular_makes_colour_view_dependent():
    sph = trimesh.creation.icosphere(3, 0.5)
    sph.visual.vertex_colors = [100, 100, 100, 255]
    intr = Intrinsics(40.0, 40.0, 24.0, 24.0, 48, 48)
    views = look_at(np.array([[0, 0.5, 3.0], [3.0, 0.5, 0]]), np.zeros((2, 3)), np.r_[0, 1.0, 0])
    out = {}
    for ks in (0.0, 0.8):
        scene = SynthScene("s", [SceneObject(sph, Material(ks, 40))], BG)
        with GLRenderer(intr, scene) as gl:
            out[ks] = gl.render(views)
    assert (out[0.8] - out[0.0]).max() > 0.3  # a highlight
    assert np.all(out[0.8] >= out[0.0] - 1e-6) and out[0.8].max() <= 1.0
    # The highlight moves with the camera: the two views differ in where they gain.
    gain = (out[0.8] - out[0.0]).sum(-1)
    assert np.argmax(gain[0]) != np.argmax(gain[1])


def test_radial_distortion_moves_points_like_the_rig():
    intr = Intrinsics(40.0, 40.0, 32.0, 24.0, 64, 48, k1=-0.25, k2=0.05)
    c2w = front_camera(2.0)
    point = np.array([1.2, 0.8, 0.0])  # far off-centre (r² = 0.52), where distortion is large
    # A small flat square facing the camera: uniform shading, so brightness = coverage.
    dot = quad(
        point[0] - 0.06,
        point[0] + 0.06,
        point[1] - 0.06,
        point[1] + 0.06,
        0.0,
        color=(255, 255, 255),
    )
    with GLRenderer(intr, SynthScene("d", [SceneObject(dot)], (0.0, 0.0, 0.0))) as gl:
        rgb = gl.render(c2w)
    w = rgb.sum(-1)
    yy, xx = np.mgrid[0:48, 0:64]
    centroid = np.array([(w * (xx + 0.5)).sum(), (w * (yy + 0.5)).sum()]) / w.sum()
    p_cam = np.linalg.inv(c2w)[:3] @ np.r_[point, 1.0]
    expected = intr.project(p_cam[None])[0]
    undistorted = Intrinsics(40.0, 40.0, 32.0, 24.0, 64, 48).project(p_cam[None])[0]
    assert np.linalg.norm(expected - undistorted) > 2.0  # the test means something
    assert np.linalg.norm(centroid - expected) < 0.15


def test_builtin_scenes_fit_in_unit_sphere_and_render():
    assert list_scenes()[0] == "blocks" and len(list_scenes()) >= 3
    for name in list_scenes():
        scene = build_scene(name)
        assert scene.radius() <= 1.0, name
        intr = scene.view.intrinsics(32, 24)
        c2w = look_at(np.array([[0, 1.0, scene.view.radius]]), np.zeros((1, 3)), np.r_[0, 1.0, 0])
        with GLRenderer(intr, scene) as gl:
            rgb = gl.render(c2w)
        bg = np.asarray(scene.background, np.float32) ** 2.2
        assert (np.abs(rgb - bg).max(-1) > 0.01).mean() > 0.05, name  # something is drawn
    with pytest.raises(InputError, match="blocks"):
        build_scene("nope")


def test_synth_end_to_end_events_match_rendered_log_changes(tmp_path, capsys):
    out = tmp_path / "scene"
    rc = main(
        ["synth", "--scene", "blocks", "--out", str(out), "--size", "48x36", "--frames", "40"]
    )
    assert rc == 0
    assert str(out) in capsys.readouterr().out
    sc = load_scene(out)
    cfg = sc.config
    assert (cfg.width, cfg.height, cfg.n_views, cfg.bayer, cfg.loop) == (48, 36, 40, "rggb", True)
    assert cfg.t_end_us == 40_000 and cfg.sim_log_eps == 1e-3 and cfg.kind == "synthetic"
    assert cfg.trajectory.kind == "turntable" and cfg.trajectory.period_us == 40_000
    ev = sc.events
    assert len(ev) > 1000 and set(np.unique(ev.p)) == {-1, 1}
    assert ev.t.min() > 0 and ev.t.max() <= 40_000
    assert np.any(ev.t > 39_000)  # the loop closes: last frame -> first frame
    assert len(sc.test_c2w) == 4 and list(sc.test_t) == [0, 10_000, 20_000, 30_000]
    gt = sc.load_test_images()
    assert gt.shape == (4, 36, 48, 3)
    # Events between two frames = change of the rendered log intensity, within 2 C.
    rig = Rig.from_scene(cfg)
    np.testing.assert_allclose(rig.pose(sc.test_t), sc.test_c2w, atol=1e-9)
    scene = build_scene("blocks")
    with GLRenderer(rig.intrinsics, scene) as gl:
        frames = gl.render(rig.pose([10_000, 20_000]))
    display = (frames[0] ** (1 / 2.2) * 255 + 0.5).astype(np.uint8) / 255.0
    assert np.abs(display - gt[1]).max() < 1e-6  # the test view is that frame, display space
    yy, xx = np.mgrid[0:36, 0:48]
    chan = BAYER_RGGB[yy % 2, xx % 2]
    L = np.log(np.take_along_axis(frames, chan[None, ..., None], -1)[..., 0] + cfg.sim_log_eps)
    index = EventIndex(ev, cfg.pos_threshold, cfg.neg_threshold, t_start=0, t_end=40_000, loop=True)
    E = index.accumulate(10_000, 20_000)
    err = np.abs(E - (L[1] - L[0]))
    assert err.max() < 2 * cfg.pos_threshold
    assert np.abs(E).max() > 1.0


def test_synth_mono_noise_and_list(tmp_path, capsys):
    assert main(["synth", "--list"]) == 0
    assert capsys.readouterr().out.split() == list_scenes()
    a = make_scene("lattice", tmp_path / "a", width=32, height=24, frames=20, bayer=None)
    b = make_scene(
        "lattice", tmp_path / "b", width=32, height=24, frames=20, bayer=None, noise=0.1, seed=3
    )
    ea, eb = load_scene(a).events, load_scene(b).events
    assert load_scene(a).config.bayer is None
    assert abs((len(eb) - len(ea)) / len(eb) - 0.1) < 0.01


def test_synth_from_user_meshes(tmp_path, capsys):
    # A textured GLB (red top half, blue bottom half) and a vertex-coloured PLY.
    tex = np.zeros((32, 32, 3), np.uint8)
    tex[:16] = (230, 20, 20)
    tex[16:] = (20, 20, 230)
    box = quad(-1, 1, -1, 1, 0.0, texture=tex)
    glb = tmp_path / "quad.glb"
    box.export(glb)
    scene = load_mesh(glb)
    assert scene.radius() == pytest.approx(0.9)
    assert mesh_arrays(scene.objects[0].mesh)[1] is not None  # the texture survived the file
    with GLRenderer(Intrinsics(40.0, 40.0, 24.0, 24.0, 48, 48), scene) as gl:
        rgb = gl.render(front_camera(2.0))  # the quad spans rows ~11..37
    s = shading([0, 0, 1])
    np.testing.assert_allclose(rgb[16, 24], (np.array([230, 20, 20]) / 255) ** 2.2 * s, atol=3e-3)
    np.testing.assert_allclose(rgb[32, 24], (np.array([20, 20, 230]) / 255) ** 2.2 * s, atol=3e-3)

    ply = tmp_path / "ball.ply"
    ballm = trimesh.creation.icosphere(2, 2.0)
    ballm.apply_translation([5, 5, 5])  # normalised into the unit sphere on load
    ballm.visual.vertex_colors = np.c_[
        (np.abs(ballm.vertex_normals) * 255).astype(np.uint8),
        np.full(len(ballm.vertices), 255, np.uint8),
    ]
    ballm.export(ply)
    out = tmp_path / "from_mesh"
    assert (
        main(["synth", "--mesh", str(ply), "--out", str(out), "--size", "32x24", "--frames", "20"])
        == 0
    )
    sc = load_scene(out)
    assert len(sc.events) > 100 and sc.config.name == "ball"


def test_unreadable_mesh_is_one_line(tmp_path, capsys):
    bad = tmp_path / "bad.glb"
    bad.write_bytes(b"this is not a mesh at all")
    assert main(["synth", "--mesh", str(bad), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "bad.glb" in err
    assert (
        main(["synth", "--mesh", str(tmp_path / "missing.obj"), "--out", str(tmp_path / "o")]) == 2
    )
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "not found" in err
    empty = tmp_path / "empty.obj"
    empty.write_text("# nothing\nv 0 0 0\n")
    assert main(["synth", "--mesh", str(empty), "--out", str(tmp_path / "o")]) == 2
    assert "no triangles" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_synth_eventnerf_format(tmp_path, capsys):
    from fastenerf.data.formats.eventnerf import load_eventnerf

    assert (
        main(
            [
                "synth",
                "--scene",
                "shiny",
                "--out",
                str(tmp_path / "x"),
                "--size",
                "64x48",
                "--format",
                "eventnerf",
            ]
        )
        == 2
    )
    assert "346x260" in capsys.readouterr().err
    out = tmp_path / "enerf"
    assert (
        main(
            [
                "synth",
                "--scene",
                "shiny",
                "--out",
                str(out),
                "--frames",
                "30",
                "--format",
                "eventnerf",
            ]
        )
        == 0
    )
    assert (out / "train" / "events" / "events.npz").is_file()
    assert len(list((out / "test" / "rgb").glob("*.png"))) == 3
    sc = load_eventnerf(out)
    assert len(sc.events) > 1000 and (sc.config.width, sc.config.height) == (346, 260)
    # their trainer needs every camera inside the unit sphere; the reader restores our world
    centres = np.stack([np.loadtxt(p)[:3, 3] for p in out.glob("*/pose/*.txt")])
    assert len(centres) == 30 + 2 * 3 and np.linalg.norm(centres, axis=1).max() < 1.0
    assert np.linalg.norm(sc.poses[1][:, :3, 3], axis=1).min() > 2.0
