"""Mesh extraction (supplement F) on analytic fields, and the cylinder clip (supplement A.2)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from fastenerf.clip import clip_aabb, clip_density, cylinder_mask
from fastenerf.config import CylinderConfig
from fastenerf.errors import InputError
from fastenerf.fields.base import Field
from fastenerf.mesh import export_mesh, extract_mesh, field_mesh, grid_shape, write_mesh_png


class BallField(Field):
    """A real Field: a ball of radius R at `center`, σ = σ_max · sigmoid((R − |x − c|) / w),
    coloured red where x > cx and blue elsewhere."""

    backend = "ball"

    def __init__(self, radius=0.5, center=(0.0, 0.0, 0.0), sigma_max=100.0, width=0.01):
        super().__init__()
        self.register_buffer("aabb", torch.tensor([-1.0, -1.0, -1.0, 1.0, 1.0, 1.0]))
        self.register_buffer("c", torch.tensor(center, dtype=torch.float32))
        self.radius, self.sigma_max, self.width = radius, sigma_max, width
        self.calls = 0

    def density(self, x):
        self.calls += 1
        return self.sigma_max * torch.sigmoid(
            (self.radius - (x - self.c).norm(dim=-1)) / self.width
        )

    def color(self, x, d):
        red = (x[:, 0] > self.c[0]).float()
        return torch.stack([red, torch.full_like(red, 0.25), 1.0 - red], -1)


@pytest.mark.parametrize("resolution", [32, 64])
def test_ball_radius_area_volume(resolution):
    R, c = 0.5, (0.2, -0.1, 0.05)
    field = BallField(R, c)
    aabb = [-0.5, -0.8, -0.6, 0.9, 0.6, 0.7]  # not a cube, not centred: checks world placement
    mesh = field_mesh(field, aabb=aabb, resolution=resolution, threshold=50.0, progress=False)
    (nx, ny, nz), h = grid_shape(aabb, resolution)
    assert max(nx, ny, nz) == resolution
    r = np.linalg.norm(mesh.vertices - np.asarray(c), axis=1)
    # σ = threshold exactly at |x - c| = R; trilinear interpolation errs by O(h²/R).
    assert abs(r.mean() - R) < 0.05 * h and r.std() < 0.1 * h
    assert abs(mesh.area / (4 * math.pi * R**2) - 1) < 0.3 * h / R
    assert abs(mesh.volume / (4 / 3 * math.pi * R**3) - 1) < 0.3 * h / R
    assert mesh.is_watertight and mesh.volume > 0  # closed, normals outward
    # Vertex colours: red on the +x side, blue on the other, alpha opaque.
    vc = np.asarray(mesh.visual.vertex_colors)
    right = mesh.vertices[:, 0] > c[0] + 0.1
    left = mesh.vertices[:, 0] < c[0] - 0.1
    assert np.all(vc[right, 0] == 255) and np.all(vc[left, 2] == 255) and np.all(vc[:, 3] == 255)


def test_colour_directions_look_at_the_surface_from_outside():
    """A view-dependent colour: white when the ray d travels inwards (d · outward normal < 0),
    black when it leaves the surface. Averaging the wrong hemisphere would give black."""
    field = BallField(0.5)

    def inward_white(x, d):
        inward = ((d * x).sum(-1) < 0).float()
        return inward[:, None].expand(-1, 3)

    mesh = extract_mesh(
        field.density,
        inward_white,
        [-1, -1, -1, 1, 1, 1],
        resolution=24,
        threshold=50.0,
        n_dirs=6,
        progress=False,
    )
    assert np.asarray(mesh.visual.vertex_colors)[:, :3].min() == 255


def test_averaging_is_in_linear_intensity():
    """Half the directions see 1, half see 0: the mean intensity 0.5 is display 0.5**(1/2.2)."""
    field = BallField(0.5)

    def half(x, d):
        n = torch.nn.functional.normalize(x, dim=-1)
        t = torch.linalg.cross(n, torch.tensor([[0.3, 0.9, 0.1]]).expand_as(n))
        return ((d * t).sum(-1) > 0).float()[:, None].expand(-1, 3)

    mesh = extract_mesh(
        field.density,
        half,
        [-1, -1, -1, 1, 1, 1],
        resolution=16,
        threshold=50.0,
        n_dirs=64,
        progress=False,
    )
    vc = np.asarray(mesh.visual.vertex_colors)[:, 0] / 255.0
    assert abs(np.median(vc) - 0.5 ** (1 / 2.2)) < 0.06


def test_cylinder_clip_shapes_the_mesh_and_skips_outside_points():
    seen = []

    def solid(x):  # dense everywhere: the clip alone makes the shape
        seen.append(x.clone())
        return torch.full((len(x),), 100.0)

    cyl = CylinderConfig(radius=0.25, y_min=-0.35, y_max=0.15)
    mesh = extract_mesh(
        solid,
        None,
        [-1, -1, -1, 1, 1, 1],
        resolution=64,
        threshold=50.0,
        cylinder=cyl,
        progress=False,
    )
    pts = torch.cat(seen)
    assert bool(cylinder_mask(pts, cyl).all())  # no field call outside the cylinder
    v = mesh.vertices
    h = grid_shape(clip_aabb([-1, -1, -1, 1, 1, 1], cyl), 64)[1]
    assert np.sqrt(v[:, 0] ** 2 + v[:, 2] ** 2).max() <= 0.25 + h
    assert v[:, 1].min() >= -0.35 - h and v[:, 1].max() <= 0.15 + h
    true_vol = math.pi * 0.25**2 * 0.5
    assert mesh.is_watertight and abs(mesh.volume / true_vol - 1) < 0.05


def test_cylinder_mask_and_clip():
    cyl = CylinderConfig(radius=0.25, y_min=-0.35, y_max=0.15)
    x = np.array(
        [
            [0.0, 0.0, 0.0],
            [0.25, 0.0, 0.0],
            [0.0, 0.15, 0.25],
            [0.0, -0.35, 0.0],
            [0.18, 0.0, 0.18],
            [0.0, 0.16, 0.0],
            [0.0, -0.36, 0.0],
            [0.3, 0.0, 0.0],
        ]
    )
    want = [True, True, True, True, False, False, False, False]  # boundaries count as inside
    assert cylinder_mask(x, cyl).tolist() == want
    assert cylinder_mask(torch.tensor(x), (0.25, -0.35, 0.15)).tolist() == want
    # Guard: NaN density outside the cylinder must become 0, not NaN (a multiply would leak).
    sigma = torch.tensor([1.0, 2.0, 3.0, 4.0, np.nan, np.inf, 7.0, np.nan])
    out = clip_density(sigma, torch.tensor(x, dtype=torch.float32), cyl)
    assert out.tolist() == [1.0, 2.0, 3.0, 4.0, 0.0, 0.0, 0.0, 0.0]
    assert clip_density(sigma, torch.tensor(x), None) is sigma
    assert clip_aabb([-1, -1, -1, 1, 1, 1], cyl) == [-0.25, -0.35, -0.25, 0.25, 0.15, 0.25]
    with pytest.raises(ValueError, match="does not overlap"):
        clip_aabb([1, 1, 1, 2, 2, 2], cyl)


def test_no_surface_and_nan_density(capsys):
    field = BallField(0.5)
    with pytest.raises(InputError, match="never reaches the threshold"):
        extract_mesh(
            field.density,
            None,
            [-1, -1, -1, 1, 1, 1],
            resolution=16,
            threshold=1000.0,
            progress=False,
        )

    def nan_outside(x):
        s = field.density(x)
        return torch.where(x[:, 0] > 0.8, torch.nan, s)

    mesh = extract_mesh(
        nan_outside, None, [-1, -1, -1, 1, 1, 1], resolution=24, threshold=50.0, progress=False
    )
    assert "NaN/inf" in capsys.readouterr().out
    assert np.all(np.isfinite(mesh.vertices)) and mesh.is_watertight


def test_export_formats_and_png(tmp_path):
    import imageio.v3 as iio
    import trimesh

    mesh = field_mesh(BallField(0.5), resolution=24, threshold=50.0, progress=False)
    for ext in ("ply", "glb", "obj"):
        p = export_mesh(mesh, tmp_path / f"ball.{ext}")
        back = trimesh.load(p, force="mesh")
        assert len(back.faces) == len(mesh.faces)
        np.testing.assert_array_equal(
            np.asarray(back.visual.vertex_colors)[:, :3].max(0), [255, 64, 255]
        )
    with pytest.raises(InputError, match="unknown mesh format"):
        export_mesh(mesh, tmp_path / "ball.stl")
    img = iio.imread(write_mesh_png(mesh, tmp_path / "ball.png", 160, 120))
    assert img.shape == (120, 160, 3)
    centre, corner = img[60, 80].astype(int), img[2, 2].astype(int)
    assert corner.tolist() == [255, 255, 255] and centre.sum() < 3 * 250  # ball on white


def test_mesh_cli_on_a_run(tmp_path, scene_config, random_stream):
    """`fastenerf mesh RUN`: a (briefly initialised, untrained) vanilla run of a clipped real
    scene; the level is picked inside the field's density range so a surface exists."""

    from fastenerf.cli import main as cli
    from fastenerf.config import TrainConfig
    from fastenerf.data.formats.native import load_scene, save_scene
    from fastenerf.mesh import density_grid
    from fastenerf.run import load_run
    from fastenerf.train import Trainer

    cfg = scene_config(width=16, height=12, cylinder=CylinderConfig(), kind="real")
    save_scene(tmp_path / "scene", cfg, random_stream(width=16, height=12))
    trainer = Trainer(
        load_scene(tmp_path / "scene"),
        TrainConfig(backend="vanilla", steps=0, device="cpu"),
        tmp_path / "run",
    )
    trainer.save_checkpoint(finished=True)
    field, _, _ = load_run(tmp_path / "run", device="cpu")
    vol, _ = density_grid(
        field.density, clip_aabb(cfg.aabb, cfg.cylinder), 20, cylinder=cfg.cylinder, progress=False
    )
    level = float(np.quantile(vol[vol > 0], 0.5))
    out = tmp_path / "m.glb"
    rc = cli(
        [
            "mesh",
            str(tmp_path / "run"),
            "--out",
            str(out),
            "--resolution",
            "20",
            "--threshold",
            f"{level:.6g}",
            "--dirs",
            "2",
            "--png",
            str(tmp_path / "m.png"),
        ]
    )
    assert rc == 0 and out.is_file() and (tmp_path / "m.png").is_file()
    import trimesh

    v = trimesh.load(out, force="mesh").vertices
    h = 0.5 / 19
    assert len(v) and np.sqrt(v[:, 0] ** 2 + v[:, 2] ** 2).max() <= 0.25 + h
    assert cli(["mesh", str(tmp_path / "run"), "--out", str(tmp_path / "m.stl")]) == 2
    assert cli(["mesh", str(tmp_path / "nope"), "--out", str(out)]) == 2


def test_ngp_mesh_leaves_out_the_fog_its_cameras_never_saw():
    from fastenerf.fields.ngp import NGPField

    # A new ngp field in a small box is fog above the mesh threshold (σ = 9 / 0.2 = 45) ...
    box = [-0.1, -0.1, -0.1, 0.1, 0.1, 0.1]
    field = NGPField(box, device="cpu")
    x = torch.zeros(4, 3)
    with torch.no_grad():
        assert (field.density(x) > 10.0).all()
    # ... that no training camera saw: one at z = 5 looking further along +z (OpenCV axes)
    c2w = np.eye(4)
    c2w[2, 3] = 5.0
    K = np.array([[50.0, 0, 32], [0, 50.0, 32], [0, 0, 1]])
    field.observe_cameras(K, c2w[None], 64, 64)
    with pytest.raises(InputError, match="never reaches the threshold"):
        field_mesh(field, resolution=16, threshold=10.0, progress=False)
