"""The `ngp` backend: hash grid + SH + tiny MLP, occupancy-grid marching (DESIGN §4).

Encoding, network, sampler and renderer stay separate as in instant-ngp:
    x --hash_grid_encode--> density MLP --> (σ, geometry features)
    d --sh_encode---------> colour MLP([geometry features, SH]) --> rgb
    rays --march_rays (occupancy grid)--> packed samples --composite--> pixels
The sampler, with its occupancy grid, is `OccupancySampler` (occupancy_sampler.py). Training
can compact the marched samples first (`early_stop_eps`): σ alone, without gradients, picks
the samples still visible (kernels/prune.py); only those run the full field.
Every heavy op is a Warp kernel from `fastenerf.kernels`; the MLPs are plain PyTorch
(bf16 autocast on CUDA, set by the trainer; the colour MLP's widths padded for cuBLAS:
`fields/mlp.py`). Only what the scene needs is built: the
cylinder clip exists only when the scene sets one (in the density and in the grid).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch
from torch import nn
from torch.profiler import record_function

from ..backends import NGPOptions, parse_options
from ..clip import clip_aabb, clip_density
from ..config import CylinderConfig, SceneConfig
from ..errors import InputError
from ..kernels.common import as_float32
from ..kernels.composite import composite, distortion_loss
from ..kernels.hashgrid import hash_grid_encode, init_table
from ..kernels.ray_points import ray_points
from ..kernels.raymarch_fixed import FixedSamples
from ..kernels.sh import sh_encode
from .base import Field, RenderOutput, check_points, park_non_finite
from .mlp import ColorMLP, density_logit
from .mlp import mlp as _mlp
from .occupancy_sampler import OccupancySampler

# Optical depth across the box of a new field's fog (density_bias None): e^-9 ≈ 1e-4 of the
# background shows through. On `blocks` (mean box side 1.22; CPU, 116×87, 2048 rays/step, 300
# steps): depth ≈ 1.2 (bias 0) 17.5 dB, ≈ 3.3 (bias 1) 17.9 dB, ≈ 9 (bias 2) 21.4 dB, ≈ 24.5
# (bias 3) 21.1 dB with twice the samples per ray.
INIT_OPTICAL_DEPTH = 9.0


def _fog_bias(aabb) -> float:
    """density_bias giving a fog of optical depth INIT_OPTICAL_DEPTH across the box's mean side."""
    box = np.asarray(aabb, dtype=np.float64)
    return math.log(INIT_OPTICAL_DEPTH / float(np.mean(box[3:] - box[:3])))


class _TruncExp(torch.autograd.Function):
    """exp with a clamped argument, so σ and its gradient stay finite for huge logits.

    Forward clamps at `hi` (σ bounded); torch-ngp's trunc_exp clamps only the gradient, so its σ
    still overflows to inf. Backward passes the gradient at the clamp (e^hi · g) straight through
    instead of the true 0 above it: a logit that overshot can still be pushed back down.
    """

    @staticmethod
    def forward(ctx, x, hi: float):
        y = torch.exp(x.clamp(max=hi))
        ctx.save_for_backward(y)  # the derivative: exp(min(x, hi)) is y itself
        return y

    @staticmethod
    def backward(ctx, g):
        (y,) = ctx.saved_tensors
        return g * y, None


def trunc_exp(x: torch.Tensor, hi: float = 15.0) -> torch.Tensor:
    """exp(min(x, hi)), same shape and dtype as x; gradient g · exp(min(x, hi)), finite for any
    finite or infinite x (NaN stays NaN)."""
    return _TruncExp.apply(x, hi)


def _cast(t: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """t in `dtype`: t itself where it already is (a no-op `.to` still dispatches an op)."""
    return t if t.dtype == dtype else t.to(dtype)


def _n_used(samples) -> int | torch.Tensor:
    """Slots holding samples: a Python int for exactly sized ones, a 0-dim device count for a
    FixedSamples (never read here)."""
    return samples.n_used[0] if isinstance(samples, FixedSamples) else int(len(samples[1]))


class _OnSampler:
    """A field attribute that is its sampler's: the trainer, graph capture and tests reach the
    sampler's state through the field."""

    def __set_name__(self, owner, name: str) -> None:
        self.name = name

    def __get__(self, field, owner=None):
        return self if field is None else getattr(field.sampler, self.name)

    def __set__(self, field, value) -> None:
        setattr(field.sampler, self.name, value)


class NGPField(Field):
    """Hash-grid radiance field over `aabb` with an occupancy grid for empty-space skipping.

    aabb: [xmin, ymin, zmin, xmax, ymax, zmax] world units; cylinder: optional density clip.
    Everything handed to a Warp kernel is float32 whatever the module's dtype (`.double()`) or
    autocast; the MLPs run in their parameters' dtype (or the autocast one); σ and colours come
    out float32.
    """

    backend = "ngp"
    # None, or (n_levels,) weights of the hash levels (coarse-to-fine pose refinement)
    level_weights: torch.Tensor | None = None
    # the sampler's (fields/occupancy_sampler.py), documented there
    grid = _OnSampler()
    compaction = _OnSampler()
    train_step = _OnSampler()
    sample_capacity = _OnSampler()
    pruned_capacity = _OnSampler()
    train_jitter = _OnSampler()
    _box_key = None
    _box = None
    level_weights_mode: str = "field"  # or "gradient" (fields/level_weights.py)

    def __init__(
        self,
        aabb,
        options: NGPOptions | None = None,
        cylinder: CylinderConfig | None = None,
        seed: int = 0,
        device: str | torch.device | None = None,
    ):
        super().__init__()
        # The grid is built (its kernels launched) where the field will run: a CUDA machine
        # need not have Warp's CPU compiler. None: CUDA when there is one.
        device = torch.device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
        opt = options or NGPOptions()
        net = opt.network
        if net.density_bias is None:
            net = dataclasses.replace(net, density_bias=_fog_bias(aabb))
            opt = dataclasses.replace(opt, network=net)
        self.options = opt
        self.cylinder = cylinder
        self.register_buffer("aabb", torch.tensor(aabb, dtype=torch.float32))
        self.grid_cfg = opt.encoding
        gen = torch.Generator().manual_seed(seed)
        self.table = nn.Parameter(init_table(self.grid_cfg, "cpu", generator=gen))
        n_in = self.grid_cfg.n_output_dims
        relu = {"fused_relu": net.fused_relu}
        self.density_net = _mlp(n_in, net.hidden, 1 + net.geo_features, 1, **relu)
        self.color_net = ColorMLP(net.geo_features, net.hidden, **relu)
        self.sampler = OccupancySampler(aabb, opt, cylinder, device)
        self.to(device)

    # -- state ---------------------------------------------------------------------------
    def _apply(self, fn, recurse=True):
        super()._apply(fn, recurse)
        # The box is kernel geometry: it keeps float32 through .double()/.half().
        self.aabb = self.aabb.float()
        # The occupancy grid is plain tensors (no gradient): it follows the module's device.
        self.grid.to(self.aabb.device)
        if self.sampler.hidden is not None:
            self.sampler.hidden.to(self.aabb.device)
        return self

    def pad_legacy(self, t: torch.Tensor) -> torch.Tensor:
        """A tensor saved for the colour MLP's unpadded layout (weights or their optimiser
        state, checkpoints from before the thirty-first session) in the padded one
        (`ColorMLP.pad_legacy`); any other tensor as it is."""
        return self.color_net.pad_legacy(t)

    def grid_state_aabb(self) -> list[float]:
        return [float(v) for v in self.aabb.cpu()]

    # The grid travels as the module's extra state (key `<prefix>_extra_state`), so a field nested
    # in another module, or wrapped by torch.compile, saves and loads it too.
    def get_extra_state(self) -> dict:
        return {"grid": self.grid.state_dict()}

    def set_extra_state(self, state: dict) -> None:
        self.grid.load_state_dict(state["grid"])

    def config_dict(self) -> dict:
        return {
            "aabb": self.grid_state_aabb(),
            "options": dataclasses.asdict(self.options),
            "cylinder": None if self.cylinder is None else dataclasses.asdict(self.cylinder),
        }

    def built(self) -> dict:
        """Which optional parts this field runs (for RUN/config.json)."""
        return {
            "cylinder": self.cylinder is not None,
            "occupancy_grid": True,
            "fine_network": False,
        }

    # -- field ---------------------------------------------------------------------------
    def _box_corner_and_size(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(lo (3,), hi - lo (3,)) of `aabb`, made once per box, not three ops every call: the
        buffer's address and version (bumped by a load into it) say when to make them anew."""
        key = (self.aabb.data_ptr(), self.aabb._version)
        if self._box_key != key:
            lo, hi = self.aabb[:3], self.aabb[3:]
            self._box, self._box_key = (lo, hi - lo), key
        return self._box

    def _normalise(self, x: torch.Tensor) -> torch.Tensor:
        lo, size = self._box_corner_and_size()
        # a non-finite point becomes the box's centre: the kernels index memory with it
        u = torch.nan_to_num((x - lo) / size, nan=0.5, posinf=1.0, neginf=0.0)
        return u.clamp(0.0, 1.0).contiguous()

    def _geometry(
        self, x: torch.Tensor, x_grad_mask: torch.Tensor | None = None, from_rows=None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """σ (N,) float32 and h (N, 1 + geo_features), the density MLP's output in its dtype (σ's
        logit first, then the geometry features the colour MLP reads), at world points x (N, 3);
        x_grad_mask: optional (N,) bool, the points whose gradient w.r.t. x is read (the
        others get none: `hash_grid_encode`); from_rows: optional (`_encode`'s features of a
        superset of x's points, each point's row in them), gathered instead of encoded."""
        return self._density_head(x, self._encode(x, x_grad_mask, from_rows))

    def _level_weights(self) -> tuple[torch.Tensor | None, bool]:
        """Coarse-to-fine's weights of the encoding's columns (L*F,) or None, and whether they
        weight the features' values (else only the pose gradient, in the backward)."""
        if self.level_weights is None:
            return None, False
        # expand, not repeat_interleave: nothing a captured step could wait on
        w = self.level_weights[:, None].expand(-1, self.grid_cfg.n_features).reshape(-1)
        return w, self.level_weights_mode != "gradient"

    def _encode(self, x, x_grad_mask=None, from_rows=None) -> torch.Tensor:
        """The hash grid's features (N, L*F) at world points x (N, 3), unweighted, in
        `_features_dtype` (float32 where coarse-to-fine weights their values)."""
        xn, cfg = self._normalise(_cast(x, torch.float32)), self.grid_cfg
        w, on_values = self._level_weights()
        return hash_grid_encode(
            xn,
            _cast(self.table, torch.float32),
            cfg,
            x_grad_weights=w.float() if w is not None and not on_values else None,
            x_grad_mask=x_grad_mask,
            out_dtype=torch.float32 if on_values else self._features_dtype(xn),
            from_rows=from_rows,
        )

    def _density_head(self, x: torch.Tensor, feats: torch.Tensor):
        """`_geometry`'s (σ, h) from the points x (N, 3) and their `_encode` features."""
        w, on_values = self._level_weights()
        feats = feats * w if on_values else feats
        if feats.dtype == torch.float32:
            feats = _cast(feats, self.density_net[0].weight.dtype)
        logit, h = density_logit(self.density_net(feats))
        net = self.options.network
        logit = logit + net.density_bias
        sigma = trunc_exp(logit, net.max_log_density)
        if self.cylinder is not None:
            sigma = clip_density(sigma, x, self.cylinder)
        return sigma, h

    def _features_dtype(self, x: torch.Tensor) -> torch.dtype:
        """What the hash grid and the SH encoding write their features in: bf16 with
        `bf16_features` while autocast runs the MLPs in bf16 on x's device, else float32."""
        kind = x.device.type
        on = self.options.network.bf16_features and torch.is_autocast_enabled(kind)
        return (
            torch.bfloat16
            if on and torch.get_autocast_dtype(kind) == torch.bfloat16
            else torch.float32
        )

    def _sigma(self, x: torch.Tensor) -> torch.Tensor:
        """σ (N,) float32 at world points x (N, 3), unchecked: for the sampler's own points
        (a grid's cells, a march's samples), finite, and never read back on the host."""
        return self._geometry(x)[0]

    def density(self, x: torch.Tensor) -> torch.Tensor:
        check_points("x", x, "NGPField.density")
        return self._sigma(x)

    def _radiance(self, h: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        """Colours (N, 3) float32 in (0, 1) from `_geometry`'s h (N, 1 + geo_features) and unit
        view directions d (N, 3)."""
        rgb = self.color_net(h, sh_encode(as_float32(d), out_dtype=self._features_dtype(d)))
        return torch.sigmoid(_cast(rgb, torch.float32))

    def color(self, x: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        check_points("x", x, "NGPField.color")
        check_points("d", d, "NGPField.color")
        return self._radiance(self._geometry(x)[1], d)

    def render(
        self, rays_o, rays_d, *, near: float, background, train: bool, grad_rays=None
    ) -> RenderOutput:
        check_points("rays_o", rays_o, "NGPField.render", finite=not train)
        check_points("rays_d", rays_d, "NGPField.render", finite=not train)
        if rays_o.shape != rays_d.shape:
            raise InputError(
                f"NGPField.render: rays_o {tuple(rays_o.shape)} and rays_d "
                f"{tuple(rays_d.shape)} differ in shape"
            )
        rays_o, rays_d, bad = as_float32(rays_o), as_float32(rays_d), None
        if train:  # checked on the device, not read: see check_points
            rays_o, rays_d, bad = park_non_finite(rays_o, rays_d)
        with torch.no_grad(), record_function("march"):
            marched = self.sampler.march(rays_o, rays_d, near, train)
        samples, from_rows = marched, None
        if train and self.sampler.prunes():
            with torch.no_grad(), record_function("prune"):
                samples, from_rows = self._prune(rays_o, rays_d, marched)
        packed_info, t_starts, t_ends, ray_idx = samples[:4]
        with record_function("field"):
            # per-ray backward: the rays are learnt under pose refinement (kernels/ray_points)
            x, d = ray_points(rays_o, rays_d, 0.5 * (t_starts + t_ends), ray_idx, packed_info)
            keep = None  # the samples whose position gradient is read (the encoding's mask)
            if grad_rays is not None and x.requires_grad:
                keep = grad_rays.index_select(0, ray_idx)
            sigma, h = self._geometry(x, keep, from_rows)
            rgb = self._radiance(h, d)
        with record_function("composite"):
            out = composite(sigma, rgb, t_starts, t_ends, packed_info, ray_idx, background)
        if train and self.compaction is not None:
            self.compaction.observe(out["weights"], _n_used(marched))
        if bad is not None:  # a non-finite ray's pixel is NaN, so the step is skipped
            out["rgb"] = torch.where(bad, float("nan"), out["rgb"])
        res: RenderOutput = {
            "rgb": out["rgb"],
            "depth": out["depth"],
            "opacity": out["opacity"],
            "n_samples": _n_used(samples),
        }
        if samples is not marched:
            res["n_marched"] = _n_used(marched)
        if isinstance(samples, FixedSamples):  # rays either buffer had no room for are out
            overflow = samples.overflow
            res["valid"] = ~(overflow if samples is marched else overflow | marched.overflow)
        if train:
            layout = self.options.compositing.distortion_layout
            res["distortion"] = distortion_loss(
                out["weights"], t_starts, t_ends, packed_info, layout=layout
            ).mean()
        return res

    def _prune(self, rays_o, rays_d, marched):
        """The marched samples a training step trains on (the sampler's prune), and what their
        encoding is gathered from: (the marched samples' features, the kept slots' rows),
        the prune's density pass having encoded every marched sample already."""
        seen = []

        def density(x):
            seen.append(self._encode(x))
            return self._density_head(x, seen[-1])[0]

        samples, src = self.sampler.prune(rays_o, rays_d, marched, density, with_src=True)
        return samples, (seen[-1], src)

    def graph_key(self) -> tuple | None:
        """Capturable while training marches into fixed buffers: (capacities, cone, level
        weights' use). Pose refinement's coarse-to-fine weights change in place
        (`coarse_to_fine`): a graph reads each step's; whether they apply, and how, it bakes in."""
        key = self.sampler.graph_key()
        if key is None:
            return None
        weights = self.level_weights is not None and self.level_weights_mode
        return (*key, weights)

    def graph_state(self) -> dict:
        """The sampler's buffers a captured step holds (`OccupancySampler.graph_state`)."""
        return self.sampler.graph_state()

    def set_graph_state(self, state: dict) -> None:
        """Put back a `graph_state()` (a kept graph replays again)."""
        self.sampler.set_graph_state(state)

    def use_fixed_capacity(self, on: bool) -> None:
        """March (and compact) training batches into fixed-capacity buffers (no host sync;
        `capacity.py`) or into exactly sized ones (the host reads the counts)."""
        self.sampler.use_fixed_capacity(on)

    # -- occupancy -----------------------------------------------------------------------
    def update(self, step: int) -> None:
        """Refresh the occupancy grid every `update_every` steps (instant-ngp's schedule)."""
        self.sampler.update(step, self._sigma)

    def observe_cameras(
        self, K: np.ndarray, c2ws: np.ndarray, width: int, height: int, near: float = 0.0
    ) -> None:
        """Cells no training camera sees stay empty for good (DESIGN §4).

        K: (3, 3) pinhole intrinsics in pixels; c2ws: (M, 4, 4) OpenCV camera-to-world;
        width, height: image size in pixels; near: world units.
        """
        dev = self.aabb.device
        self.grid.mark_unseen(
            torch.as_tensor(K, dtype=torch.float32, device=dev),
            torch.as_tensor(c2ws, dtype=torch.float32, device=dev),
            width,
            height,
            near,
        )


def build(scene: SceneConfig, cfg) -> NGPField:
    """A new ngp field for `scene`, knobs from `cfg.backend_options` (see `NGPOptions`).

    Where the scene sets a clip cylinder, the field's box is the box shrunk to the cylinder's
    bounding box: the hash grid's and the occupancy grid's resolution go where the object is.
    """
    opts = parse_options("ngp", getattr(cfg, "backend_options", None))
    device = getattr(cfg, "device", None)
    device = None if device in (None, "auto") else device
    aabb = clip_aabb(scene.aabb, scene.cylinder)
    return NGPField(aabb, opts, scene.cylinder, seed=getattr(cfg, "seed", 0), device=device)


def canonical_config(config: dict) -> dict:
    """The `config_dict()` of the field `from_config(config)` builds, without building it.

    Turns the flat options of runs saved before the options had sections into today's form, so
    a resume can compare a checkpoint's field config with a new field's.
    """
    where = "checkpoint field_config"
    if not isinstance(config, dict) or "aabb" not in config or "options" not in config:
        raise InputError(f"{where}: not an ngp field config (needs aabb and options)")
    options = dict(config["options"])
    if "network" not in options and "density_bias" not in options:
        options["density_bias"] = 0.0  # runs saved before density_bias were trained without
    opts = parse_options("ngp", options, f"{where} options")
    if opts.network.density_bias is None:
        opts = dataclasses.replace(
            opts, network=dataclasses.replace(opts.network, density_bias=_fog_bias(config["aabb"]))
        )
    cyl = config.get("cylinder")
    cyl = dataclasses.asdict(CylinderConfig(**cyl)) if cyl else None
    aabb = [float(v) for v in np.asarray(config["aabb"], dtype=np.float32)]
    return {"aabb": aabb, "options": dataclasses.asdict(opts), "cylinder": cyl}


def from_config(config: dict, device: str | torch.device | None = None) -> NGPField:
    """Rebuild a field from its `config_dict()` (checkpoints); load the weights after.

    Also reads the flat `options` of runs saved before the options had sections.
    """
    c = canonical_config(config)
    return NGPField(
        c["aabb"],
        parse_options("ngp", c["options"]),
        CylinderConfig(**c["cylinder"]) if c["cylinder"] else None,
        device=device,
    )
