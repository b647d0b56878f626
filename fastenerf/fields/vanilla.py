"""The reference backbone (DESIGN §9): NeRF MLP with positional encoding, hierarchical sampling.

Separate coarse and fine networks as the reference: 8 layers x 256 with the input re-injected
after layer 4, positional encoding [x, sin(2^k x), cos(2^k x)] (no π) with 12 frequencies for
positions and 4 for directions, colour through a sigmoid. Density goes through softplus(raw − 1)
(as mip-NeRF) by default, a stated deviation from the reference's relu: with relu a network
whose initial raw density is negative everywhere (common for small nets) renders nothing and
never receives a gradient, and the event loss gives black pixels almost none anyway
(d/dc log(c**2.2 + eps) → 0 as c → 0). `density_activation="relu"` restores the reference.
Rays are clipped to the scene box (rays that miss it get zero weight), 64 stratified coarse
samples, 128 fine samples drawn from the coarse weights (`sample_pdf`), the fine net evaluated
at all 192 (sizes are `backend_options`).
Everything here is plain PyTorch.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import torch
from torch import nn

from ..backends import VanillaOptions, parse_options
from ..clip import clip_density
from ..config import CylinderConfig
from ..errors import InputError
from .base import Field, RenderOutput, check_points, park_non_finite
from .level_weights import weight_gradient_only


class PositionalEncoding(nn.Module):
    """x (N, D) -> [x, sin(2^k x), cos(2^k x)] for k < n_freqs, (N, D (1 + 2 n_freqs)).

    band_weights: None, or (n_freqs,) weights of the bands (coarse-to-fine pose refinement),
    applied as `band_weights_mode` says (fields/level_weights.py).
    """

    band_weights: torch.Tensor | None = None
    band_weights_mode: str = "field"  # or "gradient" (fields/level_weights.py)

    def __init__(self, n_freqs: int):
        super().__init__()
        self.register_buffer(
            "freqs", 2.0 ** torch.arange(n_freqs, dtype=torch.float32), persistent=False
        )

    def out_dim(self, d: int) -> int:
        return d * (1 + 2 * len(self.freqs))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        xb = (x[..., None, :] * self.freqs[:, None]).flatten(-2)
        s, c = torch.sin(xb), torch.cos(xb)
        if self.band_weights is None or (
            self.band_weights_mode == "gradient" and not x.requires_grad
        ):
            return torch.cat([x, s, c], -1)
        w = self.band_weights.to(xb.dtype).repeat_interleave(x.shape[-1])
        if self.band_weights_mode == "gradient":
            # the encoding has no parameters: its value with x's gradient weighted
            return torch.cat([x, *(weight_gradient_only(f.detach(), f, w) for f in (s, c))], -1)
        return torch.cat([x, s * w, c * w], -1)


class NeRFMLP(nn.Module):
    """(encoded x, encoded d) -> (raw density (N,), colour (N, 3) in [0, 1])."""

    def __init__(self, in_pos: int, in_dir: int, depth: int = 8, width: int = 256, skip: int = 4):
        super().__init__()
        self.skip = skip
        layers = []
        for i in range(depth):
            d_in = in_pos if i == 0 else width + (in_pos if i == skip + 1 else 0)
            layers.append(nn.Linear(d_in, width))
        self.layers = nn.ModuleList(layers)
        self.sigma = nn.Linear(width, 1)
        self.feature = nn.Linear(width, width)
        self.view = nn.Linear(width + in_dir, width // 2)
        self.rgb = nn.Linear(width // 2, 3)

    def forward(self, xe: torch.Tensor, de: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        h = xe
        for i, layer in enumerate(self.layers):
            if i == self.skip + 1:
                h = torch.cat([xe, h], -1)
            h = torch.relu(layer(h))
        sigma = self.sigma(h).squeeze(-1)
        h = torch.relu(self.view(torch.cat([self.feature(h), de], -1)))
        return sigma, torch.sigmoid(self.rgb(h))


def ray_aabb(
    rays_o: torch.Tensor,
    rays_d: torch.Tensor,
    aabb: torch.Tensor,
    near: float = 0.0,
    far: float | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Entry and exit distances (R,) of rays (R, 3) in the box aabb (6,), clamped to [near, far].

    The contract of `kernels.raymarch.ray_aabb` (its PyTorch twin): a ray starting inside has
    t_near = near; a ray that misses, or only touches the box (zero length), has
    t_near = t_far = inf. Axis-parallel rays (d = 0 on an axis) give ±inf slab bounds, never
    NaN: the division is done on a direction nudged away from zero.
    """
    d = torch.where(rays_d.abs() < 1e-12, torch.full_like(rays_d, 1e-12), rays_d)
    inv = 1.0 / d
    t_lo = (aabb[:3] - rays_o) * inv
    t_hi = (aabb[3:] - rays_o) * inv
    t_near = torch.minimum(t_lo, t_hi).amax(-1).clamp_min(near)
    t_far = torch.maximum(t_lo, t_hi).amin(-1)
    if far is not None:
        t_far = t_far.clamp_max(far)
    miss = ~(t_far > t_near)
    inf = torch.full_like(t_near, float("inf"))
    return torch.where(miss, inf, t_near), torch.where(miss, inf, t_far)


def sample_pdf(
    bins: torch.Tensor, weights: torch.Tensor, n: int, deterministic: bool
) -> torch.Tensor:
    """Inverse-transform samples (R, n) from piecewise-constant pdfs.

    bins: (R, M + 1) bin edges; weights: (R, M) non-negative (need not sum to 1).
    """
    w = weights + 1e-5  # a ray with all-zero weights samples uniformly instead of 0/0
    pdf = w / w.sum(-1, keepdim=True)
    cdf = torch.cat([torch.zeros_like(pdf[:, :1]), torch.cumsum(pdf, -1)], -1)
    if deterministic:
        u = torch.linspace(0.0, 1.0, n, device=bins.device).expand(bins.shape[0], n)
    else:
        u = torch.rand(bins.shape[0], n, device=bins.device)
    u = u.contiguous()
    idx = torch.searchsorted(cdf, u, right=True)
    below = (idx - 1).clamp(0, cdf.shape[-1] - 1)
    above = idx.clamp(0, cdf.shape[-1] - 1)
    cdf_b, cdf_a = cdf.gather(1, below), cdf.gather(1, above)
    bin_b, bin_a = bins.gather(1, below), bins.gather(1, above)
    denom = torch.where(cdf_a - cdf_b < 1e-5, torch.ones_like(cdf_a), cdf_a - cdf_b)
    return bin_b + (u - cdf_b) / denom * (bin_a - bin_b)


def composite_dense(
    sigma: torch.Tensor,
    rgb: torch.Tensor,
    t: torch.Tensor,
    delta: torch.Tensor,
    background: torch.Tensor | None = None,
) -> dict[str, torch.Tensor]:
    """Front-to-back compositing of (R, S) samples on a dense grid (every ray S samples).

    The contract of `kernels.composite.composite` (which takes packed samples): returns a dict
    of rgb (R, 3) composited over `background` (3,) (None: black), depth (R,) = sum of w · t
    (un-normalised), opacity (R,) = sum of weights, weights (R, S). sigma (R, S) 1/world
    units, rgb (R, S, 3), t and delta (R, S) world units.
    alpha = 1 - exp(-σδ) computed as -expm1 so that σδ -> 0 keeps precision and σ -> ∞ gives
    alpha -> 1 with finite gradients.
    """
    alpha = -torch.expm1(-sigma * delta)
    trans = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1.0 - alpha + 1e-10], -1), -1)[
        :, :-1
    ]
    weights = alpha * trans
    color = (weights[..., None] * rgb).sum(1)
    opacity = weights.sum(1)
    if background is not None:
        color = color + (1.0 - opacity[:, None]) * background.to(color.dtype)
    return {"rgb": color, "depth": (weights * t).sum(1), "opacity": opacity, "weights": weights}


def distortion_loss_dense(
    weights: torch.Tensor, t_mid: torch.Tensor, delta: torch.Tensor
) -> torch.Tensor:
    """Per-ray mip-NeRF 360 distortion loss (R,) of dense samples, in O(S) per ray.

    The dense twin of `kernels.composite.distortion_loss` (packed samples, interval ends);
    both return the per-ray loss (take `.mean()` for the regulariser).
    weights, t_mid, delta: (R, S) compositing weights, interval midpoints and widths along each
    ray, sorted by t_mid, in the units the caller chooses (vanilla passes normalised ray
    distance, so the value does not depend on scale).
        sum_ij w_i w_j |m_i - m_j| + 1/3 sum_i w_i^2 delta_i
    The double sum is 2 sum_i w_i (m_i W_{<i} - (w m)_{<i}) with exclusive prefix sums.
    """
    dt = torch.promote_types(weights.dtype, torch.float32)  # bf16 under autocast -> float32
    w, m, delta = weights.to(dt), t_mid.to(dt), delta.to(dt)
    wm = w * m
    w_before = torch.cumsum(w, -1) - w
    wm_before = torch.cumsum(wm, -1) - wm
    bi = 2.0 * (w * (m * w_before - wm_before)).sum(-1)
    uni = (w**2 * delta).sum(-1) / 3.0
    return bi + uni


class VanillaField(Field):
    """NeRF (coarse + fine MLPs) over the box `aabb`, optionally clipped to a cylinder.

    aabb: [xmin, ymin, zmin, xmax, ymax, zmax] world units; positions are mapped to [-1, 1]
    by the box's centre and largest half-extent before encoding (identity for the reference's
    [-1, 1]^3 box). options: sizes (VanillaOptions); cylinder: density clip (supplement A.2).
    """

    backend = "vanilla"

    def __init__(
        self,
        aabb: list[float],
        options: VanillaOptions | None = None,
        cylinder: CylinderConfig | None = None,
    ):
        super().__init__()
        opt = options or VanillaOptions()
        self.options = opt
        self.register_buffer("aabb", torch.tensor(aabb, dtype=torch.float32))
        a = self.aabb
        self.register_buffer("center", (a[:3] + a[3:]) / 2, persistent=False)
        self.register_buffer("half_extent", ((a[3:] - a[:3]) / 2).max(), persistent=False)
        self.cylinder = cylinder
        self.n_coarse, self.n_fine = opt.n_coarse, opt.n_fine
        self.density_activation = opt.density_activation
        self.pos_enc = PositionalEncoding(opt.pos_freqs)
        self.dir_enc = PositionalEncoding(opt.dir_freqs)
        in_pos, in_dir = self.pos_enc.out_dim(3), self.dir_enc.out_dim(3)
        sizes = (opt.depth, opt.width, opt.skip)
        self.coarse = NeRFMLP(in_pos, in_dir, *sizes)
        self.fine = NeRFMLP(in_pos, in_dir, *sizes) if opt.n_fine > 0 else None

    def config_dict(self) -> dict[str, Any]:
        return {
            "aabb": [float(v) for v in self.aabb.cpu()],
            "options": dataclasses.asdict(self.options),
            "cylinder": None if self.cylinder is None else dataclasses.asdict(self.cylinder),
        }

    def built(self) -> dict[str, Any]:
        """Which optional parts this field runs (for RUN/config.json)."""
        return {
            "cylinder": self.cylinder is not None,
            "occupancy_grid": False,
            "fine_network": self.fine is not None,
        }

    # -- Field interface ---------------------------------------------------------------------

    def _net(
        self, x: torch.Tensor, d: torch.Tensor, net: NeRFMLP
    ) -> tuple[torch.Tensor, torch.Tensor]:
        raw, rgb = net(self.pos_enc((x - self.center) / self.half_extent), self.dir_enc(d))
        sigma = (
            torch.relu(raw)
            if self.density_activation == "relu"
            else nn.functional.softplus(raw - 1.0)
        )
        if self.cylinder is not None:
            sigma = clip_density(sigma, x, self.cylinder)
        return sigma, rgb

    def density(self, x: torch.Tensor) -> torch.Tensor:
        """σ (N,) from the fine network (the one that renders), 1/world units."""
        net = self.fine if self.fine is not None else self.coarse
        d = torch.zeros_like(x)
        d[:, 2] = 1.0
        return self._net(x, d, net)[0].float()

    def color(self, x: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        net = self.fine if self.fine is not None else self.coarse
        return self._net(x, d, net)[1].float()

    def render(
        self,
        rays_o: torch.Tensor,
        rays_d: torch.Tensor,
        *,
        near: float,
        background: torch.Tensor | None,
        train: bool,
        grad_rays: torch.Tensor | None = None,
    ) -> RenderOutput:
        """Volume-render rays (R, 3) each; adds `rgb_coarse` (R, 3) for the coarse-level loss.
        grad_rays is not used: every ray's gradient is computed (autograd's own)."""
        check_points("rays_o", rays_o, "VanillaField.render", finite=not train)
        check_points("rays_d", rays_d, "VanillaField.render", finite=not train)
        bad = None
        if train:  # checked on the device, not read: a bad ray is parked, its pixel made NaN
            rays_o, rays_d, bad = park_non_finite(rays_o, rays_d)
        n_rays = rays_o.shape[0]
        t_near, t_far = ray_aabb(rays_o, rays_d, self.aabb, near)
        hit = torch.isfinite(t_near)
        # A miss gets a dummy unit interval and zero weight (hit mask), so nothing is NaN.
        t_near = torch.where(hit, t_near, torch.zeros_like(t_near))
        t_far = torch.where(hit, t_far, torch.ones_like(t_far))
        span = (t_far - t_near)[:, None]
        n_c = self.n_coarse
        u = torch.arange(n_c, device=rays_o.device, dtype=torch.float32)[None]
        u = u + (torch.rand(n_rays, n_c, device=rays_o.device) if train else 0.5)
        t_c = t_near[:, None] + span * (u / n_c)
        mask = hit[:, None].float()

        def run(t: torch.Tensor, net: NeRFMLP):
            delta = torch.diff(t, dim=-1, append=t_far[:, None])
            x = rays_o[:, None] + rays_d[:, None] * t[..., None]
            d = rays_d[:, None].expand_as(x)
            sigma, rgb = self._net(x.reshape(-1, 3), d.reshape(-1, 3), net)
            sigma = sigma.float().reshape(t.shape) * mask
            rgb = rgb.float().reshape(*t.shape, 3)
            return composite_dense(sigma, rgb, t, delta, background), delta

        coarse, delta_c = run(t_c, self.coarse)
        out: RenderOutput = {}
        if self.fine is not None:
            with torch.no_grad():
                mids = 0.5 * (t_c[:, 1:] + t_c[:, :-1])
                bins = torch.cat([t_near[:, None], mids, t_far[:, None]], -1)
                t_f = sample_pdf(bins, coarse["weights"], self.n_fine, deterministic=not train)
                t_s, _ = torch.sort(torch.cat([t_c, t_f], -1), -1)
            fine, delta = run(t_s, self.fine)
            out["rgb_coarse"] = coarse["rgb"]
        else:
            fine, delta, t_s = coarse, delta_c, t_c
        out["rgb"] = fine["rgb"]
        out["depth"] = fine["depth"]
        out["opacity"] = fine["opacity"]
        if train:
            s = span.clamp_min(1e-6)
            out["distortion"] = distortion_loss_dense(
                fine["weights"], (t_s + 0.5 * delta - t_near[:, None]) / s, delta / s
            ).mean()
        out["n_samples"] = n_rays * (n_c + (self.n_fine + n_c if self.fine is not None else 0))
        if bad is not None:  # the step's loss is then NaN, and the step is skipped
            for k in ("rgb", "rgb_coarse"):
                if k in out:
                    out[k] = torch.where(bad, float("nan"), out[k])
        return out


def build(scene, cfg) -> VanillaField:
    """The vanilla field for a SceneConfig and TrainConfig (backend_options: VanillaOptions)."""
    opts = parse_options("vanilla", getattr(cfg, "backend_options", None))
    return VanillaField(list(scene.aabb), opts, scene.cylinder)


def canonical_config(config: dict) -> dict:
    """The `config_dict()` of the field `from_config(config)` builds, without building it.

    Also reads runs saved before the options had a dataclass: options as top-level keys and
    the cylinder as a [radius, y_min, y_max] list.
    """
    where = "checkpoint field_config"
    if not isinstance(config, dict) or "aabb" not in config:
        raise InputError(f"{where}: not a vanilla field config (needs aabb)")
    config = dict(config)
    aabb, cyl = config.pop("aabb"), config.pop("cylinder", None)
    options = config.pop("options", config)  # old form: the options are the remaining keys
    if isinstance(cyl, (list, tuple)):
        cyl = CylinderConfig(*cyl)
    elif isinstance(cyl, dict):
        cyl = CylinderConfig(**cyl)
    return {
        "aabb": [float(v) for v in torch.tensor(aabb, dtype=torch.float32)],
        "options": dataclasses.asdict(parse_options("vanilla", options, f"{where} options")),
        "cylinder": None if cyl is None else dataclasses.asdict(cyl),
    }


def from_config(config: dict, device=None) -> VanillaField:
    """Rebuild a field from its `config_dict()` (checkpoints, also older flat ones); load the
    weights after."""
    c = canonical_config(config)
    cyl = None if c["cylinder"] is None else CylinderConfig(**c["cylinder"])
    field = VanillaField(c["aabb"], parse_options("vanilla", c["options"]), cyl)
    return field if device is None else field.to(device)
