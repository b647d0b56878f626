"""The `ngp` backend: hash grid + SH + tiny MLP, occupancy-grid marching (DESIGN §4).

Encoding, network, sampler and renderer stay separate as in instant-ngp:
    x --hash_grid_encode--> density MLP --> (σ, geometry features)
    d --sh_encode---------> colour MLP([geometry features, SH]) --> rgb
    rays --march_rays (occupancy grid)--> packed samples --composite--> pixels
Training can compact the marched samples first (`early_stop_eps`): σ alone, without
gradients, picks the samples still visible (kernels/prune.py); only those run the full field.
Every heavy op is a Warp kernel from `fastenerf.kernels`; the MLPs are plain PyTorch
(bf16 autocast on CUDA, set by the trainer). Only what the scene needs is built: the
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
from ..kernels.occupancy import OccupancyGrid
from ..kernels.prune import prune_samples, prune_samples_fixed
from ..kernels.ray_points import ray_points
from ..kernels.raymarch import march_rays
from ..kernels.raymarch_fixed import FixedSamples, empty_fixed_samples, march_rays_fixed
from ..kernels.sh import sh_encode
from .base import Field, RenderOutput, check_points, park_non_finite, view_cone_angle
from .capacity import SampleCapacity
from .compaction import CompactionSwitch

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


def _mlp(n_in: int, hidden: int, n_out: int, n_hidden_layers: int) -> nn.Sequential:
    # No biases, like tiny-cuda-nn's fully fused MLPs: the hash features carry the offsets.
    layers: list[nn.Module] = []
    d = n_in
    for _ in range(n_hidden_layers):
        layers += [nn.Linear(d, hidden, bias=False), nn.ReLU(inplace=True)]
        d = hidden
    layers.append(nn.Linear(d, n_out, bias=False))
    return nn.Sequential(*layers)


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
    # the training step `update` last saw (the early cone applies before `early_steps`)
    train_step: int = 0
    # fixed-capacity training marches (None: exactly sized, the host reads the count)
    sample_capacity: SampleCapacity | None = None
    # the same for the compacted samples (MarcherOptions.early_stop_eps), None: exact or off
    pruned_capacity: SampleCapacity | None = None
    # (R,) uniform [0, 1) march offsets drawn outside a captured step (None: drawn per march)
    train_jitter: torch.Tensor | None = None
    _fixed_out = None
    _fixed_key = None
    _pruned_out = None
    _pruned_key = None
    _capacity_cone = None
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
        # the box as kernel arguments: read on the host once, not from the device every march
        self._aabb_host = [float(v) for v in np.asarray(aabb, dtype=np.float32)]
        self.grid_cfg = opt.encoding
        gen = torch.Generator().manual_seed(seed)
        self.table = nn.Parameter(init_table(self.grid_cfg, "cpu", generator=gen))
        self.density_net = _mlp(self.grid_cfg.n_output_dims, net.hidden, 1 + net.geo_features, 1)
        self.color_net = _mlp(net.geo_features + 16, net.hidden, 3, 2)
        cyl = None if cylinder is None else (cylinder.radius, cylinder.y_min, cylinder.y_max)
        # The grid's threshold is an optical thickness over one minimal step: the marcher's.
        self.grid = OccupancyGrid(
            list(aabb),
            opt.occupancy.grid_resolution,
            1,
            cylinder=cyl,
            step_size=opt.marcher.dt_min,
            device=device,
        )
        self.compaction = None  # compaction_auto's switch (None: fixed by the options)
        if opt.marcher.compaction_auto and self._compaction_set():
            self.compaction = CompactionSwitch(opt.marcher.compact_below)
        self.to(device)

    # -- state ---------------------------------------------------------------------------
    def _apply(self, fn, recurse=True):
        super()._apply(fn, recurse)
        # The box is kernel geometry: it keeps float32 through .double()/.half().
        self.aabb = self.aabb.float()
        # The occupancy grid is plain tensors (no gradient): it follows the module's device.
        self.grid.to(self.aabb.device)
        return self

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

    def _geometry(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """σ (N,) float32 and geometry features (N, geo_features) at world points x (N, 3)."""
        xn, w, cfg = self._normalise(_cast(x, torch.float32)), None, self.grid_cfg
        table = _cast(self.table, torch.float32)
        if self.level_weights is not None:
            # expand, not repeat_interleave: nothing a captured step could wait on
            w = self.level_weights[:, None].expand(-1, cfg.n_features).reshape(-1)
        if w is not None and self.level_weights_mode == "gradient":
            # coarse-to-fine on the pose gradient only (fields/level_weights.py), in the
            # encoding's backward: one forward, the x-gradient weighted
            feats = hash_grid_encode(xn, table, cfg, x_grad_weights=w.float())
        else:
            feats = hash_grid_encode(xn, table, cfg)
            feats = feats if w is None else feats * w
        h = self.density_net(_cast(feats, self.density_net[0].weight.dtype))
        net = self.options.network
        # one split, not an index and a slice: its backward is one concatenation of the two
        # gradients, theirs two zero-filled copies and a sum
        logit, geo = h.split([1, h.shape[1] - 1], dim=1)
        logit = _cast(logit.squeeze(1), torch.float32) + net.density_bias
        sigma = trunc_exp(logit, net.max_log_density)
        if self.cylinder is not None:
            sigma = clip_density(sigma, x, self.cylinder)
        return sigma, geo

    def density(self, x: torch.Tensor) -> torch.Tensor:
        check_points("x", x, "NGPField.density")
        return self._geometry(x)[0]

    def _radiance(self, geo: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        sh = sh_encode(as_float32(d))
        rgb = self.color_net(torch.cat([geo, _cast(sh, geo.dtype)], -1))
        return torch.sigmoid(_cast(rgb, torch.float32))

    def color(self, x: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        check_points("x", x, "NGPField.color")
        check_points("d", d, "NGPField.color")
        return self._radiance(self._geometry(x)[1], d)

    def render(self, rays_o, rays_d, *, near: float, background, train: bool) -> RenderOutput:
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
            marched = self._march(rays_o, rays_d, near, train)
        samples = marched
        if train and self._prunes():
            with torch.no_grad(), record_function("prune"):
                samples = self._prune(rays_o, rays_d, marched)
        packed_info, t_starts, t_ends, ray_idx = samples[:4]
        with record_function("field"):
            # per-ray backward: the rays are learnt under pose refinement (kernels/ray_points)
            x, d = ray_points(rays_o, rays_d, 0.5 * (t_starts + t_ends), ray_idx, packed_info)
            sigma, geo = self._geometry(x)
            rgb = self._radiance(geo, d)
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
            res["distortion"] = distortion_loss(
                out["weights"], t_starts, t_ends, packed_info
            ).mean()
        return res

    def _march(self, rays_o, rays_d, near: float, train: bool) -> tuple:
        """Training or inference samples: (packed_info, t_starts, t_ends, ray_idx), or a
        FixedSamples when training marches into fixed-capacity buffers."""
        opt = self.options.marcher
        cone = self._train_cone() if train else opt.cone_angle
        if not train and (view := view_cone_angle()) is not None:
            cone = max(cone, view)
        jitter = None
        if train:
            jitter = self.train_jitter
            if jitter is None or len(jitter) != len(rays_o):
                jitter = torch.rand(len(rays_o), device=rays_o.device)
        march = dict(
            near=near,
            cone_angle=cone,
            dt_min=opt.dt_min,
            max_samples=opt.max_samples,
            jitter=jitter,
        )
        if train and self.sample_capacity is not None:
            return self._march_fixed(rays_o, rays_d, cone, march)
        return march_rays(rays_o, rays_d, self._aabb_host, self.grid, **march)

    def _train_cone(self) -> float:
        opt = self.options.marcher
        if opt.early_cone_angle is not None and self.train_step < opt.early_steps:
            return opt.early_cone_angle
        return opt.cone_angle

    def graph_key(self) -> tuple | None:
        """Capturable while training marches into fixed buffers: (capacities, cone, level
        weights' use). Pose refinement's coarse-to-fine weights change in place
        (`coarse_to_fine`): a graph reads each step's; whether they apply, and how, it bakes in."""
        if self.sample_capacity is None:
            return None
        pruned = self.pruned_capacity  # compacting or not is in the key even before sizing
        cap = (self._prunes(), pruned and pruned.capacity)
        weights = self.level_weights is not None and self.level_weights_mode
        return (self.sample_capacity.capacity, cap, self._train_cone(), weights)

    def use_fixed_capacity(self, on: bool) -> None:
        """March (and compact) training batches into fixed-capacity buffers (no host sync;
        `capacity.py`) or into exactly sized ones (the host reads the counts)."""
        self.sample_capacity = SampleCapacity() if on else None
        self.pruned_capacity = self._new_pruned_capacity()
        self._capacity_cone = None

    def _march_fixed(self, rays_o, rays_d, cone: float, march: dict):
        cap = self.sample_capacity
        if cap.capacity is None or cone != self._capacity_cone:
            # first batch, or the cone changed (the want jumps): size it once, exactly
            exact = march_rays(rays_o, rays_d, self._aabb_host, self.grid, **march)
            cap.reset(len(exact[1]))
            self._capacity_cone = cone
            if self.pruned_capacity is not None:
                self.pruned_capacity.reset()  # its want jumps too: sized at this batch
        key = (len(rays_o), cap.capacity)
        if self._fixed_out is None or self._fixed_key != key:
            self._fixed_out = empty_fixed_samples(len(rays_o), cap.capacity, rays_o.device)
            self._fixed_key = key
        fixed = march_rays_fixed(
            rays_o,
            rays_d,
            self._aabb_host,
            self.grid,
            capacity=cap.capacity,
            out=self._fixed_out,
            **march,
        )
        cap.observe(fixed.n_wanted)
        return fixed

    def _new_pruned_capacity(self) -> SampleCapacity | None:
        """The compacted samples' buffer: with fixed capacity, while compacting."""
        return SampleCapacity() if self.sample_capacity is not None and self._prunes() else None

    def _compaction_set(self) -> bool:
        opt = self.options.marcher
        return opt.early_stop_eps > 0 or opt.alpha_threshold > 0

    def _prunes(self) -> bool:
        """Whether training compacts its marched samples now (`MarcherOptions.early_stop_eps`;
        with `compaction_auto`, while the switch says it pays)."""
        return self._compaction_set() and (self.compaction is None or self.compaction.on)

    def _prune(self, rays_o, rays_d, marched):
        """The marched samples a training step trains on: those still visible by the density
        alone (kernels/prune.py), exactly sized or a FixedSamples as `marched` is."""
        opt = self.options.marcher
        packed_info, t_starts, t_ends, ray_idx = marched[:4]
        x, _ = ray_points(rays_o, rays_d, 0.5 * (t_starts + t_ends), ray_idx, packed_info)
        sigma = self._geometry(x)[0]  # every slot, a fixed buffer's padding too: never read
        args = (sigma, packed_info, t_starts, t_ends, opt.early_stop_eps, opt.alpha_threshold)
        if not isinstance(marched, FixedSamples):
            return prune_samples(*args)
        cap = self.pruned_capacity
        if cap.capacity is None:  # first batch: size it once, exactly
            cap.reset(len(prune_samples(*args)[1]))
        key = (len(rays_o), cap.capacity)
        if self._pruned_out is None or self._pruned_key != key:
            self._pruned_out = empty_fixed_samples(len(rays_o), cap.capacity, rays_o.device)
            self._pruned_key = key
        pruned = prune_samples_fixed(*args, capacity=cap.capacity, out=self._pruned_out)
        cap.observe(pruned.n_wanted)
        return pruned

    # -- occupancy -----------------------------------------------------------------------
    def update(self, step: int) -> None:
        """Refresh the occupancy grid every `update_every` steps (instant-ngp's schedule)."""
        self.train_step = step
        opt = self.options.occupancy
        if step % opt.update_every:
            return
        for cap in (self.sample_capacity, self.pruned_capacity):
            if cap is not None:
                cap.refresh()
        if self.compaction is not None and self.compaction.refresh():
            self.pruned_capacity = self._new_pruned_capacity()  # sized anew at the next batch
        with torch.no_grad():
            self.grid.update(
                step,
                lambda x: self._geometry(x)[0],  # the grid's own points: finite, not read back
                decay=opt.grid_decay,
                threshold=opt.density_threshold,
                warmup_steps=opt.warmup_steps,
            )

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
