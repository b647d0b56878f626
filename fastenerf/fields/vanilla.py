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

from typing import Any

import torch
from torch import nn

from ..clip import clip_density
from .base import Field, RenderOutput, check_points


class PositionalEncoding(nn.Module):
    """x (N, D) -> [x, sin(2^k x), cos(2^k x)] for k < n_freqs, (N, D (1 + 2 n_freqs)).

    band_weights: None, or (n_freqs,) weights of the bands (coarse-to-fine pose refinement).
    """

    band_weights: torch.Tensor | None = None

    def __init__(self, n_freqs: int):
        super().__init__()
        self.register_buffer(
            "freqs", 2.0 ** torch.arange(n_freqs, dtype=torch.float32), persistent=False
        )

    def out_dim(self, d: int) -> int:
        return d * (1 + 2 * len(self.freqs))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        xb = (x[..., None, :] * self.freqs[:, None]).flatten(-2)
        if self.band_weights is None:
            return torch.cat([x, torch.sin(xb), torch.cos(xb)], -1)
        w = self.band_weights.to(xb.dtype).repeat_interleave(x.shape[-1])
        return torch.cat([x, torch.sin(xb) * w, torch.cos(xb) * w], -1)


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
    rays_o: torch.Tensor, rays_d: torch.Tensor, aabb: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Entry and exit distances (R,) of rays with the box aabb (6,); exit < entry on a miss.

    Axis-parallel rays (d = 0 on an axis) give ±inf slab bounds, never NaN: the division is
    done on a direction nudged away from zero.
    """
    d = torch.where(rays_d.abs() < 1e-12, torch.full_like(rays_d, 1e-12), rays_d)
    inv = 1.0 / d
    t_lo = (aabb[:3] - rays_o) * inv
    t_hi = (aabb[3:] - rays_o) * inv
    t_near = torch.minimum(t_lo, t_hi).amax(-1)
    t_far = torch.maximum(t_lo, t_hi).amin(-1)
    return t_near, t_far


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


def composite(
    sigma: torch.Tensor, rgb: torch.Tensor, t: torch.Tensor, delta: torch.Tensor
) -> tuple[torch.Tensor, ...]:
    """Front-to-back compositing of (R, S) samples: weights, rgb (R, 3), depth, opacity (R,).

    alpha = 1 - exp(-σδ) computed as -expm1 so that σδ -> 0 keeps precision and σ -> ∞ gives
    alpha -> 1 with finite gradients.
    """
    alpha = -torch.expm1(-sigma * delta)
    trans = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1.0 - alpha + 1e-10], -1), -1)[
        :, :-1
    ]
    weights = alpha * trans
    color = (weights[..., None] * rgb).sum(1)
    depth = (weights * t).sum(1)
    opacity = weights.sum(1)
    return weights, color, depth, opacity


class VanillaField(Field):
    """NeRF (coarse + fine MLPs) over the box `aabb`, optionally clipped to a cylinder.

    aabb: [xmin, ymin, zmin, xmax, ymax, zmax] world units; positions are mapped to [-1, 1]
    by the box's centre and largest half-extent before encoding (identity for the reference's
    [-1, 1]^3 box). cylinder: (radius, y_min, y_max) density clip (supplement A.2) or None.
    """

    backend = "vanilla"

    def __init__(
        self,
        aabb: list[float],
        cylinder: list[float] | None = None,
        depth: int = 8,
        width: int = 256,
        skip: int = 4,
        pos_freqs: int = 12,
        dir_freqs: int = 4,
        n_coarse: int = 64,
        n_fine: int = 128,
        density_activation: str = "softplus",
    ):
        super().__init__()
        if density_activation not in ("relu", "softplus"):
            raise ValueError("density_activation must be relu or softplus")
        self._config = dict(
            aabb=[float(a) for a in aabb],
            cylinder=None if cylinder is None else [float(c) for c in cylinder],
            depth=depth,
            width=width,
            skip=skip,
            pos_freqs=pos_freqs,
            dir_freqs=dir_freqs,
            n_coarse=n_coarse,
            n_fine=n_fine,
            density_activation=density_activation,
        )
        self.register_buffer("aabb", torch.tensor(aabb, dtype=torch.float32))
        a = self.aabb
        self.register_buffer("center", (a[:3] + a[3:]) / 2, persistent=False)
        self.register_buffer("half_extent", ((a[3:] - a[:3]) / 2).max(), persistent=False)
        self.cylinder = None if cylinder is None else tuple(float(c) for c in cylinder)
        self.n_coarse, self.n_fine = n_coarse, n_fine
        self.density_activation = density_activation
        self.pos_enc = PositionalEncoding(pos_freqs)
        self.dir_enc = PositionalEncoding(dir_freqs)
        in_pos, in_dir = self.pos_enc.out_dim(3), self.dir_enc.out_dim(3)
        self.coarse = NeRFMLP(in_pos, in_dir, depth, width, skip)
        self.fine = NeRFMLP(in_pos, in_dir, depth, width, skip) if n_fine > 0 else None

    def config_dict(self) -> dict[str, Any]:
        return dict(self._config)

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
    ) -> RenderOutput:
        """Volume-render rays (R, 3) each; adds `rgb_coarse` (R, 3) for the coarse-level loss."""
        check_points("rays_o", rays_o, "VanillaField.render")
        check_points("rays_d", rays_d, "VanillaField.render")
        n_rays = rays_o.shape[0]
        t_near, t_far = ray_aabb(rays_o, rays_d, self.aabb)
        t_near = t_near.clamp_min(near)
        hit = t_far > t_near
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
            return (*composite(sigma, rgb, t, delta), delta)

        w_c, rgb_c, depth_c, opa_c, delta_c = run(t_c, self.coarse)
        out: RenderOutput = {}
        if self.fine is not None:
            with torch.no_grad():
                mids = 0.5 * (t_c[:, 1:] + t_c[:, :-1])
                bins = torch.cat([t_near[:, None], mids, t_far[:, None]], -1)
                t_f = sample_pdf(bins, w_c, self.n_fine, deterministic=not train)
                t_all, _ = torch.sort(torch.cat([t_c, t_f], -1), -1)
            w, rgb, depth, opa, delta = run(t_all, self.fine)
            t_s = t_all
            out["rgb_coarse"] = self._bg(rgb_c, opa_c, background)
        else:
            w, rgb, depth, opa, delta, t_s = w_c, rgb_c, depth_c, opa_c, delta_c, t_c
        out["rgb"] = self._bg(rgb, opa, background)
        out["depth"] = depth
        out["opacity"] = opa
        if train:
            from ..losses import distortion_loss

            s = span.clamp_min(1e-6)
            out["distortion"] = distortion_loss(
                w, (t_s + 0.5 * delta - t_near[:, None]) / s, delta / s
            )
        out["n_samples"] = n_rays * (n_c + (self.n_fine + n_c if self.fine is not None else 0))
        return out

    @staticmethod
    def _bg(rgb: torch.Tensor, opacity: torch.Tensor, background: torch.Tensor | None):
        if background is None:
            return rgb
        return rgb + (1.0 - opacity[:, None]) * background.to(rgb.dtype)


def build(scene, cfg) -> VanillaField:
    """The vanilla field for a SceneConfig and TrainConfig (backend_options override sizes)."""
    opts = dict(cfg.backend_options or {})
    cyl = scene.cylinder
    cylinder = None if cyl is None else [cyl.radius, cyl.y_min, cyl.y_max]
    try:
        return VanillaField(list(scene.aabb), cylinder, **opts)
    except TypeError as e:
        from ..errors import InputError

        raise InputError(f"backend_options for vanilla: {e}") from None


def from_config(config: dict) -> VanillaField:
    """Rebuild a field from its `config_dict()` (checkpoints)."""
    return VanillaField(**config)
