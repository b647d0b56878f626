"""Field backends through `make_field`: ranges and shapes, misses, gradients, checkpoint round
trip, the cylinder clip (issue #7), numerical guards (DESIGN §5), and the ngp occupancy grid.

Real Warp launches at small sizes (8 hash levels, T = 2^12, 32^3 occupancy grid).
"""

from __future__ import annotations

import io
import json
import math

import numpy as np
import pytest
import torch

from fastenerf.backends import BACKEND_NAMES as BACKENDS
from fastenerf.backends import parse_options
from fastenerf.clip import cylinder_mask
from fastenerf.config import CylinderConfig, TrainConfig
from fastenerf.fields import field_from_config, make_field
from fastenerf.fields import ngp as ngp_mod
from fastenerf.fields import occupancy_sampler as sampler_mod
from fastenerf.fields.capacity import SampleCapacity
from fastenerf.fields.ngp import trunc_exp
from fastenerf.kernels.hashgrid import grid_indices

SMALL = {
    "ngp": dict(
        n_levels=8,
        log2_table_size=12,
        base_resolution=8,
        max_resolution=128,
        hidden=32,
        grid_resolution=32,
        dt_min=0.02,  # ~100 steps across the box instead of ~600: CPU time
        max_samples=256,
    ),
    "vanilla": dict(depth=2, width=32, n_coarse=16, n_fine=16, pos_freqs=4, dir_freqs=2),
}
CYL = CylinderConfig(radius=0.25, y_min=-0.35, y_max=0.15)
BG = torch.tensor([0.2, 0.5, 0.8])


@pytest.fixture
def make(scene_config):
    """make(backend, cylinder=None, **options) -> a small field of `backend` for a 32x24 scene."""

    def _make(backend: str, cylinder: CylinderConfig | None = None, **options):
        scene = scene_config(32, 24, cylinder=cylinder)
        cfg = TrainConfig(backend=backend, backend_options={**SMALL[backend], **options})
        torch.manual_seed(0)  # vanilla's nn.Linear init draws from the global generator
        return make_field(backend, scene, cfg)

    return _make


def hit_rays(n: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """n rays from around (0, 0, -3) towards random points of the [-0.5, 0.5]^3 core."""
    g = torch.Generator().manual_seed(seed)
    o = torch.tensor([0.0, 0.0, -3.0]) + 0.4 * (torch.rand(n, 3, generator=g) - 0.5)
    target = torch.rand(n, 3, generator=g) - 0.5
    return o, torch.nn.functional.normalize(target - o, dim=-1)


def miss_rays() -> tuple[torch.Tensor, torch.Tensor]:
    """Rays that never meet the [-1, 1]^3 box: above it, pointing away, grazing beside it."""
    o = torch.tensor([[0.0, 2.5, -3.0], [3.0, 0.0, 0.0], [1.5, -1.5, -3.0]])
    d = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    return o, d


def saturate_density(field) -> None:
    """Make the raw density network output enormous everywhere (σ at its largest)."""
    with torch.no_grad():
        if field.backend == "ngp":
            field.table.fill_(1.0)
            field.density_net[0].weight.fill_(1.0)
            field.density_net[2].weight[0].fill_(1e30)  # logit ~ 5e32, finite in float32
        else:
            for net in (field.coarse, field.fine):
                net.sigma.bias.fill_(1e30)


def params(field) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in field.named_parameters()}


# ---------------------------------------------------------------------------- both backends


@pytest.mark.parametrize("backend", BACKENDS)
def test_density_and_color_ranges(make, backend):
    f = make(backend)
    x = 2.4 * (torch.rand(500, 3, generator=torch.Generator().manual_seed(1)) - 0.5)
    d = torch.nn.functional.normalize(torch.randn(500, 3), dim=-1)
    sigma = f.density(x)
    rgb = f.color(x, d)
    assert sigma.shape == (500,) and sigma.dtype == torch.float32
    assert torch.isfinite(sigma).all() and (sigma >= 0).all()
    assert rgb.shape == (500, 3) and rgb.dtype == torch.float32
    assert ((rgb >= 0) & (rgb <= 1)).all()


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("train", [False, True])
def test_render_shapes_and_misses(make, backend, train):
    f = make(backend)
    ho, hd = hit_rays(12)
    mo, md = miss_rays()
    inside_o, inside_d = torch.zeros(1, 3), torch.tensor([[0.0, 1.0, 0.0]])  # starts inside
    o = torch.cat([ho, mo, inside_o])
    d = torch.cat([hd, md, inside_d])
    out = f.render(o, d, near=1e-4, background=BG, train=train)
    R = len(o)
    assert out["rgb"].shape == (R, 3) and out["depth"].shape == (R,)
    assert out["opacity"].shape == (R,)
    for k in ("rgb", "depth", "opacity"):
        assert torch.isfinite(out[k]).all(), k
    assert ((out["opacity"] >= 0) & (out["opacity"] <= 1 + 1e-6)).all()
    assert (out["opacity"][:12] > 0).all() and out["opacity"][-1] > 0
    miss = slice(12, 15)
    assert torch.equal(out["opacity"][miss], torch.zeros(3))
    assert torch.equal(out["rgb"][miss], BG.expand(3, 3))
    if train:
        assert out["distortion"].ndim == 0 and torch.isfinite(out["distortion"])
    # no background: a miss is black
    out = f.render(mo, md, near=1e-4, background=None, train=train)
    assert torch.equal(out["rgb"], torch.zeros(3, 3))


@pytest.mark.parametrize("backend", BACKENDS)
def test_gradients_reach_every_parameter(make, backend):
    f = make(backend)
    o, d = hit_rays(24)
    out = f.render(o, d, near=1e-4, background=BG, train=True)
    loss = (out["rgb"] - 0.3).square().mean() + out["depth"].mean() + out["distortion"]
    if "rgb_coarse" in out:
        loss = loss + (out["rgb_coarse"] - 0.3).square().mean()
    loss.backward()
    for name, p in f.named_parameters():
        assert p.grad is not None, name
        assert torch.isfinite(p.grad).all(), name
        assert p.grad.abs().sum() > 0, name


@pytest.mark.parametrize("backend", BACKENDS)
def test_checkpoint_round_trip_renders_identically(make, backend):
    f = make(backend)
    with torch.no_grad():  # move away from the seed-0 init that from_config would rebuild
        for p in f.parameters():
            p.add_(0.05 * torch.randn_like(p))
    for step in range(0, 33, 16):
        f.update(step)  # ngp: a non-trivial occupancy grid that must travel with the weights
    f.eval()
    o, d = hit_rays(16, seed=3)
    ref = f.render(o, d, near=1e-4, background=BG, train=False)

    config = json.loads(json.dumps(f.config_dict()))  # what config.json / checkpoints hold
    g = field_from_config(backend, config).eval()
    before = g.render(o, d, near=1e-4, background=BG, train=False)
    assert not torch.equal(before["rgb"], ref["rgb"])  # the round trip below has work to do

    buf = io.BytesIO()
    torch.save(f.state_dict(), buf)
    buf.seek(0)
    g.load_state_dict(torch.load(buf, weights_only=True))  # as the trainer loads checkpoints
    out = g.render(o, d, near=1e-4, background=BG, train=False)
    for k in ("rgb", "depth", "opacity"):
        assert torch.equal(out[k], ref[k]), k

    # nested in another module (a wrapper, torch.compile): the whole state still travels
    h = torch.nn.ModuleDict({"field": field_from_config(backend, config)}).eval()
    h.load_state_dict(torch.nn.ModuleDict({"field": f}).state_dict())
    out = h["field"].render(o, d, near=1e-4, background=BG, train=False)
    assert torch.equal(out["rgb"], ref["rgb"])


# ---------------------------------------------------------------------------- cylinder clip


@pytest.mark.parametrize("backend", BACKENDS)
def test_cylinder_zeroes_density_outside_even_when_saturated(make, backend):
    f = make(backend, cylinder=CYL)
    saturate_density(f)
    x = 2 * torch.rand(4000, 3, generator=torch.Generator().manual_seed(2)) - 1
    x = torch.cat([x, torch.tensor([[0.0, 0.0, 0.0], [0.26, 0.0, 0.0], [0.0, 0.16, 0.0]])])
    inside = cylinder_mask(x, CYL)
    assert 0 < int(inside.sum()) < len(x)
    sigma = f.density(x)
    assert torch.isfinite(sigma).all()
    assert torch.equal(sigma[~inside], torch.zeros(int((~inside).sum())))
    assert (sigma[inside] > 1e6).all()  # the clip leaves the inside alone
    # the saturated field renders opaque through the cylinder and nothing beside it, and its
    # gradients stay finite (alpha saturates, DESIGN §5)
    o = torch.tensor([[0.0, -0.1, -3.0], [0.5, -0.1, -3.0], [0.0, 0.5, -3.0]])
    d = torch.tensor([[0.0, 0.0, 1.0]]).expand(3, 3)
    f.train()
    out = f.render(o, d, near=1e-4, background=BG, train=True)
    assert out["opacity"][0] > 0.99
    assert torch.equal(out["opacity"][1:], torch.zeros(2))
    (out["rgb"].sum() + out["depth"].sum() + out["distortion"]).backward()
    for name, p in f.named_parameters():
        assert p.grad is None or torch.isfinite(p.grad).all(), name


@pytest.mark.parametrize("backend", BACKENDS)
def test_no_cylinder_builds_no_clip(make, backend, monkeypatch):
    f = make(backend)
    assert f.cylinder is None
    assert f.built()["cylinder"] is False
    assert make(backend, cylinder=CYL).built()["cylinder"] is True
    if backend == "ngp":
        assert f.grid.cylinder is None  # nor in the grid or the marcher

        def boom(*a, **k):
            raise AssertionError("clip code ran without a cylinder")

        monkeypatch.setattr(ngp_mod, "clip_density", boom)
        saturate_density(f)
        assert (f.density(torch.tensor([[0.9, 0.9, 0.9]])) > 1e6).all()
        f.update(0)
        o, d = hit_rays(4)
        assert f.render(o, d, near=1e-4, background=BG, train=True)["n_samples"] > 0


def _cell_boxes(grid) -> tuple[np.ndarray, np.ndarray]:
    """Min and max corners (R^3, 3) of the cells of cascade 0, in flat-id order."""
    R = grid.resolution
    a = np.array(grid.aabb_list, np.float64)
    size = (a[3:] - a[:3]) / R
    ijk = np.stack(np.meshgrid(*[np.arange(R)] * 3, indexing="ij"), -1).reshape(-1, 3)
    lo = a[:3] + ijk * size
    return lo, lo + size


def test_ngp_grid_never_occupies_cells_outside_cylinder(make):
    f = make("ngp", cylinder=CYL, warmup_steps=32)
    saturate_density(f)
    for step in range(0, 97, 16):  # warm-up and sparse updates
        f.update(step)
    lo, hi = _cell_boxes(f.grid)
    dx = np.maximum(np.maximum(lo[:, 0], -hi[:, 0]), 0)
    dz = np.maximum(np.maximum(lo[:, 2], -hi[:, 2]), 0)
    meets = (dx**2 + dz**2 <= CYL.radius**2) & (hi[:, 1] >= CYL.y_min) & (lo[:, 1] <= CYL.y_max)
    occ = f.grid.binary[0].reshape(-1).numpy()
    assert occ.any()
    assert not (occ & ~meets).any()


# ---------------------------------------------------------------------------- stability


def test_trunc_exp_keeps_density_and_gradient_finite():
    logits = torch.tensor([-1e4, -5.0, 0.0, 10.0, 15.0, 20.0, 1e3, 1e4, math.inf])
    assert torch.isinf(torch.exp(logits[-3:])).all()  # what the guard prevents
    x = logits.clone().requires_grad_(True)
    y = trunc_exp(x)
    y.sum().backward()
    assert torch.isfinite(y).all() and torch.isfinite(x.grad).all()
    below = logits <= 15
    assert torch.allclose(y[below], torch.exp(logits[below]), rtol=1e-6, atol=0)
    # clipped at e^15 as float32 rounds it (torch's exp is within 1 ulp, CPU-dependent)
    assert torch.allclose(y[~below], torch.full_like(y[~below], math.exp(15.0)), rtol=1e-6, atol=0)
    assert (x.grad[~below] > 0).all()  # an overshooting logit can still be pushed down
    # bf16 logits stay finite as well (e^15 is far below bf16's max)
    yb = trunc_exp(logits.to(torch.bfloat16))
    assert yb.dtype == torch.bfloat16 and torch.isfinite(yb).all()


def test_ngp_density_finite_for_huge_logits(make):
    f = make("ngp")
    saturate_density(f)
    sigma = f.density(torch.rand(64, 3) - 0.5)
    assert torch.allclose(sigma, torch.full((64,), math.exp(15.0)), rtol=1e-6, atol=0)


@pytest.mark.parametrize(
    "backend, options",
    [(b, {}) for b in BACKENDS] + [("ngp", {"fused_relu": True})],
)
def test_bf16_autocast_render_is_finite_and_float32(make, backend, options):
    f = make(backend, **options)
    # the density MLP's output layer: a module call with fused hidden layers as without
    layer = f.density_net[-1] if backend == "ngp" else f.fine.layers[0]
    seen = []
    layer.register_forward_hook(lambda m, i, o: seen.append(o.dtype))
    o, d = hit_rays(16)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = f.render(o, d, near=1e-4, background=BG, train=True)
    assert torch.bfloat16 in seen  # the MLP really ran in bf16 ...
    for k in ("rgb", "depth", "opacity"):  # ... and float32 came out of the kernels
        assert out[k].dtype == torch.float32 and torch.isfinite(out[k]).all(), k
    loss = out["rgb"].square().mean() + out["distortion"]
    if "rgb_coarse" in out:
        loss = loss + out["rgb_coarse"].square().mean()
    loss.backward()
    for name, p in f.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
        assert p.grad.dtype == p.dtype, name


# A NaN in one coordinate is not a miss for the marcher: it emits finite-t samples at NaN
# positions, whose NaN σ and gradients would reach the weights. Outside training the field
# refuses them; in training the ray is parked and its pixel made NaN (the step is skipped).
@pytest.mark.parametrize(
    "backend",
    ["ngp", "vanilla"],
)
@pytest.mark.parametrize("bad", ["rays_o", "rays_d"])
@pytest.mark.parametrize("value", [math.nan, math.inf])
def test_non_finite_rays_rejected_at_the_boundary(make, backend, bad, value):
    f = make(backend)
    o, d = hit_rays(8)
    rays = {"rays_o": o.clone(), "rays_d": d.clone()}
    rays[bad][5, 1] = value
    before = params(f)
    with pytest.raises(ValueError, match=bad):
        f.render(rays["rays_o"], rays["rays_d"], near=1e-4, background=BG, train=False)
    for k, v in f.named_parameters():
        assert torch.equal(v, before[k]), k
    # A training render does not read its rays on the host (a device sync per step): the bad
    # ray's pixel comes out NaN instead (so the step's loss is NaN and the guard skips it),
    # and every other pixel is what it is without the bad ray.
    out = f.render(rays["rays_o"], rays["rays_d"], near=1e-4, background=BG, train=True)
    assert torch.isnan(out["rgb"][5]).all()
    keep = torch.arange(8) != 5
    assert torch.isfinite(out["rgb"][keep]).all()
    loss = out["rgb"][keep].sum()
    loss.backward()
    for k, p in f.named_parameters():
        assert p.grad is None or torch.isfinite(p.grad).all(), k


def test_ngp_non_finite_points_rejected(make):
    f = make("ngp")
    x = torch.zeros(4, 3)
    x[2, 0] = math.nan
    with pytest.raises(ValueError, match=r"density: x has NaN or inf in 1 of 4 rows"):
        f.density(x)
    with pytest.raises(ValueError, match=r"color: d "):
        f.color(torch.zeros(4, 3), x)


# ---------------------------------------------------------------------------- ngp occupancy


def test_ngp_update_only_every_update_every_steps(make, monkeypatch):
    f = make("ngp", update_every=5)
    calls = []
    real = f.grid.update
    monkeypatch.setattr(
        f.grid, "update", lambda step, *a, **k: (calls.append(step), real(step, *a, **k))
    )
    for step in range(23):
        f.update(step)
    assert calls == [0, 5, 10, 15, 20]
    assert f.grid.threshold.item() >= 0  # real updates ran (the initial threshold is -0.5)


@pytest.mark.parametrize("option", [{"fused_relu": True}])
def test_ngp_fused_relu_renders_and_trains_as_the_plain_field(make, option):
    """fused_relu (each hidden ReLU in its GEMM) is how the MLPs run, not what they are: the same
    parameters render the same colours and depths with the same gradients (within what the
    plain field differs from itself by), and the options are in the field's saved config."""
    plain, fused, again = (make("ngp", **o) for o in ({}, option, {}))
    for k, v in option.items():
        assert fused.config_dict()["options"]["network"][k] is v
        assert getattr(fused.color_net, k) is v and getattr(fused.density_net, k) is v
    fused.load_state_dict(plain.state_dict())
    assert fused.config_dict()["options"]["network"]["fused_relu"] is True
    assert fused.density_net.fused_relu and fused.color_net.fused_relu
    assert not plain.density_net.fused_relu and not plain.color_net.fused_relu
    assert not make("ngp").density_net.fused_relu  # the default (CUDA runs set it)
    o, d = hit_rays(48)
    outs, grads = [], []
    for f in (plain, fused, again):
        out = f.render(o, d, near=1e-4, background=BG, train=True)
        loss = out["rgb"].square().sum() + out["depth"].sum()
        grads.append(torch.autograd.grad(loss, list(f.parameters()), allow_unused=True))
        outs.append(out)
    torch.testing.assert_close(outs[0]["rgb"], outs[1]["rgb"], rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(outs[0]["depth"], outs[1]["depth"], rtol=1e-5, atol=1e-5)
    # the training render's backward sums by atomics: the plain field against itself sets
    # the tolerance
    for a, b, c in zip(*grads, strict=True):
        assert (a is None) == (b is None) == (c is None)
        if a is not None:
            noise = (c - a).abs().max().item()
            assert (b - a).abs().max().item() <= 3 * noise + 1e-6
    assert any(g is not None and g.abs().sum() > 0 for g in grads[1])


def test_ngp_update_offset_moves_the_updates_but_keeps_step_0(make, monkeypatch):
    """update_offset: the grid starts empty, so step 0 updates; then offset past each
    multiple of update_every (modulo it: 7 with 5 is 2)."""
    for offset in (2, 7):
        f = make("ngp", update_every=5, update_offset=offset)
        calls = []
        real = f.grid.update
        monkeypatch.setattr(
            f.grid,
            "update",
            lambda step, *a, calls=calls, real=real, **k: (calls.append(step), real(step, *a, **k)),
        )
        for step in range(23):
            f.update(step)
        assert calls == [0, 2, 7, 12, 17, 22]


def ball_field(make, radius: float = 0.4, **options):
    """An ngp field whose density is e^15 in a ball of ~`radius` at the origin, ~e^-20 outside.

    Level 0 of the hash grid is dense: its feature 0 is +1 at lattice vertices inside the ball
    and -1 outside; the MLP computes 20 · (relu(f) − relu(−f)) = 20 f as the density logit.
    """
    f = make("ngp", **options)
    cfg = f.grid_cfg
    N = cfg.resolutions[0]
    assert not cfg.hashed[0]
    ijk = torch.stack(torch.meshgrid(*[torch.arange(N + 1)] * 3, indexing="ij"), -1).reshape(-1, 3)
    lo, hi = f.aabb[:3], f.aabb[3:]
    world = lo + ijk / N * (hi - lo)
    rows = grid_indices(ijk.int(), 0, cfg)
    with torch.no_grad():
        for p in f.parameters():
            p.zero_()
        f.table[rows, 0] = torch.where(world.norm(dim=-1) < radius, 1.0, -1.0)
        f.density_net[0].weight[0, 0] = 1.0
        f.density_net[0].weight[1, 0] = -1.0
        f.density_net[2].weight[0, 0] = 20.0
        f.density_net[2].weight[0, 1] = -20.0
    return f


def test_ngp_occupancy_empties_space_around_a_ball(make):
    f = ball_field(make, warmup_steps=48)
    assert f.density(torch.zeros(1, 3)) > 1e6
    assert f.density(torch.tensor([[0.8, 0.8, 0.8]])) < 1e-6
    # through the ball, and through empty space beside it
    o = torch.tensor([[0.0, 0.0, -3.0], [0.7, 0.7, -3.0]])
    d = torch.tensor([[0.0, 0.0, 1.0]]).expand(2, 3)
    f.eval()

    before = [
        f.render(o[i : i + 1], d[i : i + 1], near=1e-4, background=None, train=False)
        for i in range(2)
    ]
    for step in range(0, 97, 16):  # warm-up (all cells) then sparse updates
        f.update(step)
    after = [
        f.render(o[i : i + 1], d[i : i + 1], near=1e-4, background=None, train=False)
        for i in range(2)
    ]
    assert before[1]["n_samples"] > 50 and after[1]["n_samples"] == 0
    assert 0 < after[0]["n_samples"] < before[0]["n_samples"]
    assert after[0]["opacity"] > 0.99  # skipping lost nothing that matters
    assert abs(float(after[0]["depth"].detach()) - float(before[0]["depth"].detach())) < 0.02
    # every cell well away from the ball is empty; the centre is occupied
    lo, hi = _cell_boxes(f.grid)
    centre = torch.from_numpy(0.5 * (lo + hi)).float()
    occ = f.grid.binary[0].reshape(-1)
    far = centre.norm(dim=-1) > 0.75
    assert not occ[far].any()
    assert f.grid.occupied(torch.zeros(1, 3)).all()


def test_ngp_observe_cameras_one_camera_leaves_space_behind_it_empty(make):
    f = make("ngp")
    K = np.array([[16.0, 0, 16], [0, 16.0, 12], [0, 0, 1]])
    c2w = np.eye(4)[None]  # at the origin, looking down +z
    f.observe_cameras(K, c2w, 32, 24, near=0.0)
    saturate_density(f)  # dense everywhere: only the visibility mask keeps cells empty
    f.update(0)
    lo, hi = _cell_boxes(f.grid)
    centre = torch.from_numpy(0.5 * (lo + hi)).float()
    occ = f.grid.binary[0].reshape(-1)
    valid = f.grid.valid[0]
    behind = centre[:, 2] < -0.1
    in_view = (centre[:, 2] > 0.2) & (centre[:, :2].abs().max(-1).values < 0.5 * centre[:, 2])
    assert not valid[behind].any() and not occ[behind].any()
    assert occ[in_view].all()
    # a ray behind the camera marches nothing
    out = f.render(
        torch.tensor([[0.0, 0.0, -0.2]]),
        torch.tensor([[0.0, 0.0, -1.0]]),
        near=1e-4,
        background=None,
        train=False,
    )
    assert out["n_samples"] == 0


# ---------------------------------------------------------------------------- ngp devices, dtypes


def test_ngp_grid_follows_module_device_and_survives_dtype_casts(make):
    f = ball_field(make)
    f.update(0)
    f.eval()
    o, d = hit_rays(8)
    ref = f.render(o, d, near=1e-4, background=BG, train=False)
    occ = f.grid.bitfield.clone()

    f.to("cpu")
    assert f.grid.density.device == f.table.device == f.grid.bitfield.device
    f.double()
    assert f.table.dtype == torch.float64 and f.density_net[0].weight.dtype == torch.float64
    assert f.aabb.dtype == torch.float32  # kernel geometry stays float32
    assert f.grid.density.dtype == torch.float32 and f.grid.bitfield.dtype == torch.uint8
    assert torch.equal(f.grid.bitfield, occ)
    f.train()
    out = f.render(o.double(), d.double(), near=1e-4, background=BG, train=True)
    assert out["rgb"].dtype == torch.float32 and torch.isfinite(out["rgb"]).all()
    out["rgb"].sum().backward()
    assert f.table.grad.dtype == torch.float64 and torch.isfinite(f.table.grad).all()

    f.float().eval()
    assert f.table.dtype == torch.float32
    out = f.render(o, d, near=1e-4, background=BG, train=False)
    for k in ("rgb", "depth", "opacity"):
        assert torch.equal(out[k], ref[k]), k


def test_ngp_normalises_points_in_the_box_it_holds_now(make):
    # the box's corner and size are made once and kept: a box written into the buffer (as
    # load_state_dict does) or a move must make them anew
    f = make("ngp")
    x = torch.zeros(1, 3)
    old = f.aabb.clone()
    u = f._normalise(x)
    with torch.no_grad():
        f.aabb.copy_(torch.tensor([-1.0, -1.0, -1.0, 3.0, 3.0, 3.0]))
    assert torch.equal(f._normalise(x), torch.full((1, 3), 0.25))
    with torch.no_grad():
        f.aabb.copy_(old)
    f.double()  # a new buffer
    assert torch.equal(f._normalise(x), u)


def test_new_ngp_field_is_a_fog_of_fixed_optical_depth_at_any_scale():
    # A new field starts as fog of optical depth INIT_OPTICAL_DEPTH across the box whatever
    # its size (transparent starts stall the event loss: RESULTS.md); old runs keep bias 0.
    for scale in (0.1, 1.0, 20.0):
        aabb = [-scale, -scale, -scale, scale, scale, scale]
        f = ngp_mod.NGPField(aabb, device="cpu")
        x = (torch.rand(256, 3) * 2 - 1) * scale
        with torch.no_grad():
            depth = f.density(x) * (2 * scale)
        assert torch.allclose(depth, torch.full_like(depth, ngp_mod.INIT_OPTICAL_DEPTH), rtol=0.05)
        conf = f.config_dict()
        assert conf["options"]["network"]["density_bias"] == pytest.approx(math.log(4.5 / scale))
        assert ngp_mod.from_config(conf, device="cpu").options == f.options
    # a run saved before density_bias existed (flat options without it) was trained without one
    old = {"aabb": aabb, "options": {"hidden": 64}, "cylinder": None}
    assert ngp_mod.from_config(old, device="cpu").options.network.density_bias == 0.0
    opts = parse_options("ngp", {"network": {"density_bias": -1.0}})
    fixed = ngp_mod.NGPField(aabb, opts, device="cpu")
    assert fixed.options.network.density_bias == -1.0


def test_ngp_early_cone_marches_fewer_samples_until_early_steps(make):
    """The default schedule (issue #17): early_cone_angle for the first early_steps training
    steps, then cone_angle; renders outside training always use cone_angle."""
    f = make("ngp", cone_angle=0.0, early_cone_angle=1 / 8, early_steps=2, dt_min=0.005)
    o, d = hit_rays(16)

    def samples(train: bool) -> int:
        return int(f.render(o, d, near=1e-4, background=BG, train=train)["n_samples"])

    early, evaluation = samples(True), samples(False)
    f.train_step = 2  # what `update` sets
    late = samples(True)
    assert early < 0.6 * late, (early, late)
    assert abs(evaluation - late) <= 0.05 * late  # eval marches with cone_angle (jitter aside)
    defaults = parse_options("ngp", {})
    assert defaults.marcher.early_cone_angle == 1 / 64 and defaults.marcher.early_steps == 256


def test_ngp_diagonal_steps_sets_the_step_relative_to_the_box(make):
    """`diagonal_steps` (dt_min unset): half of them, twice the step, half the samples per ray
    through a fog that fills the box; the occupancy threshold's step follows; a dt_min given
    wins over it."""
    o, d = hit_rays(16)

    def field_and_samples(**options):
        # few steps across the [-1, 1]^3 box (SMALL's dt_min unset): CPU time, max_samples
        opts = dict(cone_angle=0.0, early_cone_angle=None, dt_min=None) | options
        f = make("ngp", **opts)
        return f, int(f.render(o, d, near=1e-4, background=BG, train=False)["n_samples"])

    f128, n128 = field_and_samples(diagonal_steps=128)
    f64, n64 = field_and_samples(diagonal_steps=64)
    assert f128.sampler.grid.step_size == pytest.approx(math.sqrt(3) * 2 / 128)
    assert f64.sampler.grid.step_size == pytest.approx(2 * f128.sampler.grid.step_size)
    assert n64 == pytest.approx(n128 / 2, rel=0.05), (n64, n128)
    fixed, _ = field_and_samples(diagonal_steps=64, dt_min=0.005)
    assert fixed.sampler.grid.step_size == 0.005
    assert parse_options("ngp", {}).marcher.diagonal_steps == 1024


def test_view_cone_is_a_floor_for_this_threads_inference_renders_only(make):
    """`view_cone` (the viewer's speed setting): inference renders in this thread march with at
    least that cone (fewer samples), training renders and other threads keep the field's own,
    a smaller cone than the field's changes nothing, and leaving the block restores it."""
    import threading

    from fastenerf.fields.base import view_cone

    f = make("ngp", cone_angle=0.0, early_cone_angle=None, dt_min=0.005)
    o, d = hit_rays(16)

    def samples(train: bool = False) -> int:
        return int(f.render(o, d, near=1e-4, background=BG, train=train)["n_samples"])

    own, trained = samples(), samples(True)
    other = []
    with view_cone(1 / 8):
        fast = samples()
        assert abs(samples(True) - trained) <= 0.05 * trained  # training: the field's own
        t = threading.Thread(target=lambda: other.append(samples()))
        t.start()
        t.join()
    assert fast < 0.6 * own, (fast, own)
    assert other == [own] and samples() == own
    g = make("ngp", cone_angle=1 / 8, early_cone_angle=None, dt_min=0.005)
    with view_cone(1 / 256):  # a floor: a coarser field's own cone stays
        n = int(g.render(o, d, near=1e-4, background=BG, train=False)["n_samples"])
    assert n == int(g.render(o, d, near=1e-4, background=BG, train=False)["n_samples"])


# ------------------------------------------------------------- ngp compacted samples (prune)


def _train_render(f, o, d, seed: int = 3):
    """A training render (jitter seeded) and the gradients of a loss on it, rays' included."""
    o, d = o.clone().requires_grad_(), d.clone().requires_grad_()
    torch.manual_seed(seed)
    out = f.render(o, d, near=1e-4, background=BG, train=True)
    loss = (out["rgb"] - 0.3).square().mean() + out["depth"].mean() + out["distortion"]
    f.zero_grad()
    loss.backward()
    grads = {k: p.grad.clone() for k, p in f.named_parameters()}
    return out, loss.detach(), {**grads, "rays_o": o.grad, "rays_d": d.grad}


def test_ngp_compacted_samples_train_as_all_marched_ones(make, monkeypatch):
    """early_stop_eps 1e-4 (where compositing stops anyway): the full field runs on a fraction
    of the marched samples, yet pixels, loss and gradients (the rays' too, for pose refinement)
    are those of all of them. 0 (the default) runs no density pre-pass at all."""
    o, d = hit_rays(24)
    opaque = dict(density_bias=3.0)  # a thick fog: most marched samples lie behind T < 1e-4
    ref, ref_loss, ref_g = _train_render(make("ngp", **opaque), o, d)
    out, loss, g = _train_render(make("ngp", early_stop_eps=1e-4, **opaque), o, d)
    assert out["n_marched"] == ref["n_samples"] and "n_marched" not in ref
    assert out["n_samples"] < 0.5 * out["n_marched"], (out["n_samples"], out["n_marched"])
    for k in ("rgb", "depth", "opacity"):
        torch.testing.assert_close(out[k], ref[k], rtol=0, atol=1e-6)
    assert float(loss) == pytest.approx(float(ref_loss), rel=1e-6)
    for k, v in g.items():
        assert torch.isfinite(v).all() and v.abs().sum() > 0, k
        torch.testing.assert_close(v, ref_g[k], rtol=1e-4, atol=1e-6 * float(v.abs().max()))
    # off: not one call into the pruning
    monkeypatch.setattr(sampler_mod, "prune_samples", None)
    monkeypatch.setattr(sampler_mod, "prune_samples_fixed", None)
    f = make("ngp", **opaque)
    again, _, _ = _train_render(f, o, d)
    assert torch.equal(again["rgb"], ref["rgb"]) and again["n_samples"] == ref["n_samples"]
    f.use_fixed_capacity(True)
    assert f.pruned_capacity is None and "n_marched" not in _train_render(f, o, d)[0]


@pytest.mark.parametrize(
    "fixed, weights, bf16",
    [(False, None, False), (True, None, True), (True, "field", False), (False, "gradient", True)],
)
def test_ngp_compacted_samples_reuse_the_prunes_encoding(make, monkeypatch, fixed, weights, bf16):
    """The kept samples' features are gathered from the prune's density pass, which encoded
    every marched sample already: the hash grid runs forward once a compacted training
    render, and the render, loss and every gradient are those of encoding the kept samples
    anew, bit for bit (exactly sized buffers and fixed ones, the rays' gradients included;
    coarse-to-fine's weights on the features or on the pose gradient; bf16 features under
    bf16 autocast)."""
    o, d = hit_rays(24)
    calls = []
    encode = ngp_mod.hash_grid_encode

    def counted(*a, **kw):
        calls.append(kw.get("from_rows") is None)
        return encode(*a, **kw)

    monkeypatch.setattr(ngp_mod, "hash_grid_encode", counted)
    runs = []
    for reuse in (True, False):
        f = make("ngp", early_stop_eps=1e-4, density_bias=3.0, bf16_features=bf16)
        f.use_fixed_capacity(fixed)
        if weights is not None:
            f.level_weights = torch.linspace(1.0, 0.0, f.grid_cfg.n_levels)
            f.level_weights_mode = weights
        _train_render(f, o, d)  # sizes the fixed buffers
        if not reuse:  # the kept samples encoded anew
            monkeypatch.setattr(
                ngp_mod,
                "hash_grid_encode",
                lambda *a, **kw: counted(*a, **{**kw, "from_rows": None}),
            )
        calls.clear()
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            runs.append((_train_render(f, o, d), calls.count(True)))
    ((out, loss, g), encoded), ((ref, ref_loss, ref_g), ref_encoded) = runs
    assert (encoded, ref_encoded) == (1, 2)
    assert out["n_samples"] < out["n_marched"]
    for k in ("rgb", "depth", "opacity"):
        assert torch.equal(out[k], ref[k]), k
    assert torch.equal(loss, ref_loss)
    for k, v in g.items():
        assert torch.equal(v, ref_g[k]), k


def _detached_render(f, o, d, keep, grad_rays, seed: int = 3):
    """`_train_render` with the rays outside `keep` detached, as pose refinement detaches a
    long window's; `grad_rays` goes to the field."""
    o, d = o.clone().requires_grad_(), d.clone().requires_grad_()
    ro = torch.where(keep[:, None], o, o.detach())
    rd = torch.where(keep[:, None], d, d.detach())
    torch.manual_seed(seed)
    out = f.render(ro, rd, near=1e-4, background=BG, train=True, grad_rays=grad_rays)
    loss = (out["rgb"] - 0.3).square().mean() + out["depth"].mean() + out["distortion"]
    f.zero_grad()
    loss.backward()
    grads = {k: p.grad.clone() for k, p in f.named_parameters() if p.grad is not None}
    return out, {**grads, "rays_o": o.grad, "rays_d": d.grad}


@pytest.mark.parametrize("backend", BACKENDS)
def test_grad_rays_skips_only_gradients_nobody_reads(make, backend, monkeypatch):
    """grad_rays (the rays pose refinement learns from): pixels and every gradient the caller
    reads are those without it; ngp's encoding skips the other rays' points (its x-gradient
    mask), and the mask is what decides (the wrong one changes the rays' gradients)."""
    o, d = hit_rays(24)
    keep = torch.arange(24) % 3 == 0
    ref, ref_g = _detached_render(make(backend), o, d, keep, None)
    masks = []
    if backend == "ngp":
        encode = ngp_mod.hash_grid_encode

        def spy(*args, x_grad_mask=None, **kw):
            masks.append(x_grad_mask)
            return encode(*args, x_grad_mask=x_grad_mask, **kw)

        monkeypatch.setattr(ngp_mod, "hash_grid_encode", spy)
    out, g = _detached_render(make(backend), o, d, keep, keep)
    torch.testing.assert_close(out["rgb"], ref["rgb"], rtol=0, atol=0)
    for k, v in g.items():
        if k.startswith("rays_"):
            assert v[~keep].abs().max() == 0 and v[keep].abs().min() > 0, k
        torch.testing.assert_close(v, ref_g[k], rtol=1e-5, atol=1e-7 * float(v.abs().max()))
    if backend == "ngp":
        assert len(masks) == 1 and masks[0] is not None
        assert 0 < int(masks[0].sum()) < len(masks[0])  # some points skipped, not all
        _, wrong = _detached_render(make(backend), o, d, keep, ~keep)
        assert not torch.allclose(wrong["rays_o"][keep], g["rays_o"][keep])


def test_ngp_compacted_samples_in_fixed_buffers(make):
    """With fixed capacity the compacted samples get their own buffer, sized exactly on the
    first batch, then following the want at occupancy updates; a ray that either buffer has no
    room for is left out (`valid`), the others render as with exact sizes."""
    f = make("ngp", early_stop_eps=1e-4, density_bias=3.0)
    o, d = hit_rays(24)
    exact, _, _ = _train_render(f, o, d)
    f.use_fixed_capacity(True)
    fixed, _, g = _train_render(f, o, d)  # sizes both buffers from this batch
    assert fixed["valid"].all()
    assert int(fixed["n_samples"]) == exact["n_samples"]
    assert int(fixed["n_marched"]) == exact["n_marched"]
    torch.testing.assert_close(fixed["rgb"], exact["rgb"], rtol=0, atol=1e-6)
    assert all(torch.isfinite(v).all() for v in g.values())
    # the compacted buffer too small: rays are flagged, the rest unchanged, gradients finite
    f.pruned_capacity.capacity = exact["n_samples"] // 2
    small, _, g = _train_render(f, o, d)
    valid = small["valid"]
    assert (
        0 < int(valid.sum()) < len(valid) and int(small["n_samples"]) <= f.pruned_capacity.capacity
    )
    torch.testing.assert_close(small["rgb"][valid], exact["rgb"][valid], rtol=0, atol=1e-6)
    assert all(torch.isfinite(v).all() for v in g.values())
    # the march's buffer too small as well: its overflowed rays are out too
    f.sample_capacity.capacity = exact["n_marched"] // 4
    both, _, _ = _train_render(f, o, d)
    assert int((~both["valid"]).sum()) > int((~valid).sum())
    torch.testing.assert_close(
        both["rgb"][both["valid"]], exact["rgb"][both["valid"]], atol=1e-6, rtol=0
    )
    # occupancy updates grow the compacted buffer to what was wanted
    f.update(16)
    f.update(32)
    assert f.pruned_capacity.capacity >= exact["n_samples"]
    # a new cone (the early steps are over) sizes both buffers again at that batch, exactly
    f.pruned_capacity.capacity = 1
    f.train_step = f.options.marcher.early_steps
    late, _, _ = _train_render(f, o, d)
    assert late["valid"].all() and f.pruned_capacity.capacity >= int(late["n_samples"]) > 0


def test_ngp_compaction_auto_keeps_compacting_only_where_it_pays(make):
    """compaction_auto: the share of marched samples compositing uses, read one occupancy
    update late, turns compaction off on a field that uses nearly all of them (a thin fog) and
    keeps it on where most lie behind T < 1e-4 (a thick one). Off, the step is the plain one
    (no pre-pass, its own graph key); on or off, pixels are those of all marched samples."""
    o, d = hit_rays(24)
    auto = dict(early_stop_eps=1e-4, compaction_auto=True)
    for bias, stays_on in ((3.0, True), (-6.0, False)):
        f, plain = make("ngp", density_bias=bias, **auto), make("ngp", density_bias=bias)
        f.use_fixed_capacity(True)
        first, _, _ = _train_render(f, o, d)  # auto starts compacting (a new field's fog)
        assert "n_marched" in first and f.compaction.on
        key = f.graph_key()
        for step in (16, 32):  # the first update copies the sums, the second reads them
            for g in (f, plain):  # the same grid updates (seeded): the same marched samples
                torch.manual_seed(step)
                g.update(step)
            _train_render(f, o, d)
        ref, _, _ = _train_render(plain, o, d)
        share = f.compaction.share
        assert share is not None and (share < 0.5 if stays_on else share > 0.9), share
        assert f.compaction.on is stays_on and (f.pruned_capacity is not None) is stays_on
        assert (f.graph_key() == key) is stays_on
        out, _, g = _train_render(f, o, d)
        assert ("n_marched" in out) is stays_on
        assert out["valid"].all() and all(torch.isfinite(v).all() for v in g.values())
        torch.testing.assert_close(out["rgb"], ref["rgb"], rtol=0, atol=1e-6)
    # switched back on, its buffer not sized yet: still not the key of the step without it
    off = f.graph_key()
    f.compaction.on, f.pruned_capacity = True, SampleCapacity()
    assert f.graph_key() != off


def test_ngp_capacity_options_size_the_buffers_and_trained_slots_names_them(make):
    """capacity_headroom, capacity_shrink_below and capacity_shrink_patience reach both
    fixed-capacity buffers; trained_slots is the buffer the field trains on (the compacted one
    while compacting), None while buffers are exactly sized; a shrink share that would flap
    is refused."""
    from fastenerf.backends import parse_options
    from fastenerf.errors import InputError

    o, d = hit_rays(24)
    opts = dict(capacity_headroom=2.0, capacity_shrink_below=0.3, capacity_shrink_patience=3)
    for compact in (False, True):
        f = make("ngp", **opts, **({"early_stop_eps": 1e-4} if compact else {}))
        assert f.sampler.trained_slots() is None
        f.use_fixed_capacity(True)
        out, _, _ = _train_render(f, o, d)
        s = f.sampler
        caps = [s.sample_capacity] + ([s.pruned_capacity] if compact else [])
        for cap in caps:
            assert (cap.headroom, cap.shrink_below, cap.shrink_patience) == (2.0, 0.3, 3)
            assert cap.size_for(10**6) == 62 * 2**15  # 2e6 slots, rounded up to the quantum
        assert s.trained_slots() == caps[-1].capacity >= int(out["n_samples"]) > 0
        for i, cap in enumerate(caps):  # tell the two buffers apart
            cap.capacity = (3 + i) * cap.quantum
        assert s.trained_slots() == (4 if compact else 3) * 2**15
    with pytest.raises(InputError, match="capacity_shrink_below") as e:
        parse_options("ngp", {"capacity_headroom": 1.5, "capacity_shrink_below": 0.7})
    assert len(str(e.value).splitlines()) == 1


def test_compaction_switch_hysteresis():
    """Within ±0.05 of `below` the state holds (no graph recaptured per flicker); beyond, it
    switches; the first refresh only starts the copy (no reading yet)."""
    from fastenerf.fields.compaction import CompactionSwitch

    sw = CompactionSwitch(0.7)

    def feed(share: float) -> bool:
        w = torch.zeros(1000)
        w[: round(1000 * share)] = 0.5
        sw.observe(w, 1000)
        return sw.refresh()

    assert not feed(0.9) and sw.on and sw.share is None  # nothing read yet
    assert feed(0.72) and not sw.on and sw.share == pytest.approx(0.9)  # 0.9 read: off
    assert not feed(0.6) and not sw.on  # 0.72 read: inside the band, stays off
    assert feed(0.72) and sw.on  # 0.6 read: on
    assert not feed(0.72) and sw.on  # 0.72 read: inside the band, stays on
    assert sw.switches == 2


def test_new_gpu_runs_compact_where_it_pays_cpu_runs_do_not():
    """The preset writes compaction_auto and GPU_NETWORK into a new CUDA run's options (and
    the cone into every run's), never over an option the user set, flat or by section."""
    from fastenerf.backends import ngp_run_defaults
    from fastenerf.config import train_preset

    gpu = ngp_run_defaults({}, 0.0, "cuda:1")
    assert gpu == {
        "cone_angle": 0.0,
        "early_stop_eps": 1e-4,
        "compaction_auto": True,
        "fused_relu": True,
        "bf16_features": True,
    }
    assert ngp_run_defaults({}, 0.0, "cpu") == {"cone_angle": 0.0}
    mine = {"marcher": {"early_stop_eps": 0.0}, "network": {"fused_relu": False}}
    assert ngp_run_defaults(mine, 0.5, "cuda") == {
        "marcher": {"early_stop_eps": 0.0, "cone_angle": 0.5},
        "network": {"fused_relu": False, "bf16_features": True},
    }
    assert ngp_run_defaults({"alpha_threshold": 0.01}, 0.0, "cuda")["alpha_threshold"] == 0.01
    assert ngp_run_defaults({"fused_relu": False}, 0.0, "cuda")["fused_relu"] is False
    cfg = train_preset("fast", "ngp", device="cuda", minutes=1.0)
    assert cfg.backend_options["compaction_auto"] is True
    assert cfg.backend_options["fused_relu"] is True
    assert cfg.backend_options["bf16_features"] is True
    cpu = train_preset("fast", "ngp", device="cpu").backend_options
    assert not {"compaction_auto", "fused_relu", "bf16_features"} & set(cpu)


def test_ngp_distortion_layout_is_how_the_loss_runs_not_what_it_is(make):
    """compositing.distortion_layout picks the distortion loss's kernels: "block" gives the
    "ray" loss to float32 rounding and its gradients within what "ray" differs from itself
    by (the training render's backward sums by atomics); the choice is in the saved config."""
    fields = [make("ngp", distortion_layout=k) for k in ("ray", "block", "ray")]
    for f in fields[1:]:
        f.load_state_dict(fields[0].state_dict())
    assert fields[1].config_dict()["options"]["compositing"]["distortion_layout"] == "block"
    assert make("ngp").options.compositing.distortion_layout == "auto"  # the default
    o, d = hit_rays(48)
    losses, grads = [], []
    for f in fields:
        loss = f.render(o, d, near=1e-4, background=BG, train=True)["distortion"]
        grads.append(torch.autograd.grad(loss, list(f.parameters()), allow_unused=True))
        losses.append(loss.detach())
    assert losses[0] > 0
    torch.testing.assert_close(losses[1], losses[0], rtol=1e-4, atol=0)
    for a, b, c in zip(*grads, strict=True):
        if a is not None:
            noise = (c - a).abs().max().item()
            assert (b - a).abs().max().item() <= 3 * noise + 1e-4 * a.abs().max().item() + 1e-9
    assert any(g is not None and g.abs().sum() > 0 for g in grads[1])


def test_ngp_bf16_features_are_what_the_mlp_casts_the_float32_ones_to(make):
    """bf16_features under bf16 autocast: the hash grid writes the features the density MLP
    would have cast them to, and reads their bf16 gradient as the float32 path reads it cast
    back, so a render and its gradients are the float32-feature field's bit for bit;
    outside autocast the option changes nothing (float32 features)."""
    plain, fast = make("ngp", bf16_features=False), make("ngp", bf16_features=True)
    fast.load_state_dict(plain.state_dict())
    o, d = hit_rays(48)
    x = torch.rand(64, 3) - 0.5
    assert fast._features_dtype(x) == torch.float32  # no autocast
    outs, grads = [], []
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert fast._features_dtype(x) == torch.bfloat16
        assert plain._features_dtype(x) == torch.float32
        for f in (plain, fast):  # an evaluation render: no jitter, the same samples
            out = f.render(o, d, near=1e-4, background=BG, train=False)
            loss = out["rgb"].square().sum() + out["depth"].sum()
            grads.append(torch.autograd.grad(loss, list(f.parameters()), allow_unused=True))
            outs.append(out)
    for k in ("rgb", "depth", "opacity"):
        assert torch.equal(outs[1][k], outs[0][k]), k
    for a, b in zip(*grads, strict=True):
        assert (a is None and b is None) or torch.equal(a, b)
    names = [n for n, _ in fast.named_parameters()]
    assert dict(zip(names, grads[1], strict=True))["table"].abs().sum() > 0
