"""The field backends by name, and their options: the one registry everything reads.

`BACKENDS` maps a name to what the rest of the code needs to know without building a field:
its options dataclass (what `TrainConfig.backend_options` is parsed into) and its optimiser
defaults. The field classes themselves live in `fastenerf.fields.<name>` (imported lazily, so
this module and `--help` load neither torch nor Warp).

Options come in sections, as instant-ngp's config (encoding / network / sampler):
    ngp      encoding (kernels' HashGridConfig), network, marcher, occupancy, compositing
    vanilla  one flat section (VanillaOptions)
`parse_options` takes a JSON object nested by section (`{"marcher": {"cone_angle": 0}}`) or
flat (`{"cone_angle": 0}`, what older run folders hold): a flat key goes to its section.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Literal

from .errors import InputError
from .kernels.gridconfig import HashGridConfig
from .schema import from_dict


@dataclass
class NetworkOptions:
    """The ngp field's two tiny MLPs (no biases, as tiny-cuda-nn's fully fused ones)."""

    hidden: int = field(default=64, metadata={"min": 1, "max": 1024})
    """Neurons per hidden layer of the density MLP (1 hidden layer) and colour MLP (2)."""
    geo_features: int = field(default=15, metadata={"min": 1, "max": 256})
    """Geometry features the density MLP hands to the colour MLP besides σ."""
    density_bias: float | None = field(default=None, metadata={"min": -50.0, "max": 50.0})
    """σ = exp(MLP logit + density_bias), so a new field is a uniform fog of σ ≈ e^bias
    (1/world units). None: the fog's optical depth across the box is 9 (INIT_OPTICAL_DEPTH),
    whatever the scene's scale; under event supervision a transparent start stalls colour."""
    max_log_density: float = field(default=15.0, metadata={"min": 1.0, "max": 80.0})
    """The truncated exp's clamp: σ ≤ e^max_log_density (15: ≈ 3.3e6, DESIGN §5), computed
    in float32 whatever the MLP's autocast dtype."""
    fused_relu: bool = False
    """Each hidden layer's ReLU in its GEMM's epilogue (cuBLASLt through
    `torch._addmm_activation`; fields/mlp.py): the same function without the separate
    activation kernel's pass over every sample. New CUDA runs set it (`GPU_NETWORK`); on the
    CPU torch's `_addmm_activation` is an addmm and then a clamp, nothing saved. False: a
    GEMM, then a ReLU kernel, each module called as nn.Sequential would."""
    bf16_features: bool = False
    """Where the MLPs run under bf16 autocast (the GPU), the hash grid and the SH encoding
    write their features and read their gradient in bf16 (kernels/hashgrid.py, sh.py): the
    values the MLPs would cast them to anyway (both round to nearest even), without the
    casts' passes over every sample's features. The hash grid's stay float32 where
    coarse-to-fine weights the features' values. New CUDA runs set it (`GPU_NETWORK`)."""


@dataclass
class MarcherOptions:
    """Ray marching through the occupancy grid (DESIGN §4)."""

    cone_angle: float = field(default=1.0 / 256, metadata={"min": 0.0, "max": 1.0})
    """Step growth with distance: dt = clamp(t · cone_angle, dt_min, dt_max); 0 gives
    constant steps (slower, sharper), 1/256 instant-ngp's (faster). Default: chosen by the
    training budget (0 for a run with a step or time budget, 1/256 for an open-ended one)."""
    dt_min: float | None = field(default=None, metadata={"gt": 0.0, "max": 10.0})
    """Smallest marching step, world units. None: √3 · box size / diagonal_steps."""
    diagonal_steps: int = field(default=1024, metadata={"min": 1, "max": 1_000_000})
    """With dt_min unset, the smallest step is √3 · the box's longest side / this (instant-ngp's
    1024): the same step on every scene relative to its box; fewer, fewer samples per ray."""
    max_samples: int = field(default=1024, metadata={"min": 1, "max": 65536})
    """Most samples along one ray."""
    single_pass: bool = False
    """March each ray once, keeping its samples in scratch rows while counting them, then
    copy them into place (kernels/march_scratch.py, `SINGLE_PASS`); False: march twice (count,
    then write). The same samples either way."""
    early_cone_angle: float | None = field(default=1.0 / 64, metadata={"min": 0.0, "max": 1.0})
    """Cone angle of the first `early_steps` training steps, while the fog of a new field is
    carved (fewer samples per ray then); None: cone_angle from the start. The default was
    chosen on every built-in scene and a mesh scene (benchmarks/RESULTS.md, issue #17)."""
    early_steps: int = field(default=256, metadata={"min": 0, "max": 10_000_000})
    """Training steps that march with early_cone_angle (the occupancy grid's warm-up)."""
    early_stop_eps: float = field(default=0.0, metadata={"min": 0.0, "max": 1.0})
    """Compacted training samples (instant-ngp; nerfacc's early stop): the density network
    first runs alone, without gradients, on every marched sample, and only the samples whose
    transmittance before them is at least this (a fraction of the light, 1e-4 is where
    compositing stops anyway) go through the full field, forward and backward. 0: off (with
    alpha_threshold 0: every marched sample is trained on, no density pre-pass)."""
    alpha_threshold: float = field(default=0.0, metadata={"min": 0.0, "max": 1.0})
    """With compaction, also drop training samples whose opacity alpha = 1 - exp(-σ·dt) is
    below this (nearly transparent ones; nerfacc's alpha_thre). 0: keep them all."""
    carve_hidden: bool = False
    """With compaction: the training march skips occupied cells that no training ray saw
    (every sample marched there since the last clearing behind T < early_stop_eps: the
    inside of a solid), cleared and re-tested every `carve_refresh` grid updates
    (kernels/hidden_cells.py). Evaluation, the viewer and the mesh march the full grid.
    Without compaction nothing is built; while `compaction_auto` has compaction off nothing is
    counted, so the carved cells stay until the next clearing."""
    carve_min_hits: int = field(default=16, metadata={"min": 1, "max": 1_000_000})
    """Marched samples a cell needs since the last clearing before it can be carved."""
    carve_refresh: int = field(default=8, metadata={"min": 1, "max": 1_000_000})
    """Grid updates between clearings of the carved cells."""
    compaction_auto: bool = False
    """With compaction: compact only while it pays, i.e. while compositing uses less than
    `compact_below` of the marched samples (measured on the training renders, read every
    `update_every` steps; fields/compaction.py). False: compact every step."""
    compact_below: float = field(default=0.7, metadata={"min": 0.0, "max": 1.0})
    """The share of marched samples under which `compaction_auto` compacts (the density
    pre-pass costs about 0.3 of a sample's full pass; ±0.05 hysteresis)."""
    capacity_headroom: float = field(default=1.1, metadata={"min": 1.0, "max": 4.0})
    """A captured training step marches into buffers of fixed capacity (fields/capacity.py):
    this times the most samples a batch wanted since the last occupancy update, rounded up
    to 32,768 slots. The field runs over every slot of the buffer, padding too."""
    capacity_shrink_below: float = field(default=0.85, metadata={"gt": 0.0, "max": 1.0})
    """The capacity shrinks (to what the want needs) once the want falls below this share
    of it, by two 32,768-slot quanta at least (so a want at a quantum's edge does not shrink
    and regrow it); it grows as soon as the want passes capacity / capacity_headroom."""
    capacity_shrink_patience: int = field(default=1, metadata={"min": 1, "max": 64})
    """Occupancy updates in a row whose want must allow a shrink before the capacity shrinks
    (to the largest of them). Each change of capacity recaptures the training step's CUDA
    graph; a want whose per-update maximum varies more than a quantum flips it back and forth
    at 1."""

    def __post_init__(self):
        if self.capacity_shrink_below * self.capacity_headroom >= 1.0:
            raise InputError(
                f"capacity_shrink_below ({self.capacity_shrink_below}) must be "
                f"below 1 / capacity_headroom ({1.0 / self.capacity_headroom:.3f}), or the "
                "capacity would shrink and grow back at every occupancy update"
            )


@dataclass
class OccupancyOptions:
    """The occupancy grid that lets the marcher skip empty space (instant-ngp's schedule)."""

    grid_resolution: int = field(default=128, metadata={"min": 8, "max": 512, "multiple_of": 2})
    """Cells per axis of the grid over the box."""
    density_threshold: float = field(default=0.01, metadata={"min": 0.0, "max": 1e6})
    """A cell is occupied while its optical thickness over one dt_min step exceeds this."""
    grid_decay: float = field(default=0.95, metadata={"min": 0.0, "max": 1.0})
    """Factor each cell's density decays by at every grid update."""
    update_every: int = field(default=16, metadata={"min": 1, "max": 1_000_000})
    """Steps between grid updates."""
    update_offset: int = field(default=0, metadata={"min": 0, "max": 1_000_000})
    """Steps past a multiple of update_every at which the grid updates (taken modulo
    update_every; the grid also updates at step 0, where it starts empty). The sampler draws
    its batches 16 steps at a time from step 0, so with 0 both host-heavy jobs fall on one
    step; an offset spreads them over two, so less of the device's queue drains while the
    host works (issue #17; not a default until measured on every scene)."""
    warmup_steps: int = field(default=256, metadata={"min": 0, "max": 10_000_000})
    """Steps during which every cell is refreshed (later: a sample of cells per update)."""


@dataclass
class CompositingOptions:
    """Compositing the marched samples, and the distortion loss over them
    (kernels/composite.py)."""

    distortion_layout: Literal["auto", "ray", "block"] = "auto"
    """How the distortion loss's kernels run: "ray", one thread per ray; "block", 32 threads
    per ray with tile scans over chunks of samples (kernels/distortion_block.py); "auto",
    `DISTORTION_CUDA_AUTO` on CUDA and "ray" on the CPU. The same loss and gradient up to
    float32 rounding."""


@dataclass
class NGPOptions:
    """Accuracy/speed knobs of the ngp backend, by component."""

    encoding: HashGridConfig = field(default_factory=HashGridConfig)
    """Multiresolution hash grid over the box."""
    network: NetworkOptions = field(default_factory=NetworkOptions)
    """Density and colour MLPs."""
    marcher: MarcherOptions = field(default_factory=MarcherOptions)
    """Ray marching."""
    occupancy: OccupancyOptions = field(default_factory=OccupancyOptions)
    """Empty-space skipping."""
    compositing: CompositingOptions = field(default_factory=CompositingOptions)
    """Compositing and the distortion loss."""


@dataclass
class VanillaOptions:
    """The reference NeRF's sizes (DESIGN §9): coarse and fine MLPs, hierarchical sampling."""

    depth: int = field(default=8, metadata={"min": 1, "max": 32})
    """Layers of each MLP."""
    width: int = field(default=256, metadata={"min": 2, "max": 4096})
    """Neurons per layer."""
    skip: int = field(default=4, metadata={"min": 0, "max": 32})
    """The encoded position is fed again after layer skip + 1."""
    pos_freqs: int = field(default=12, metadata={"min": 0, "max": 24})
    """Positional-encoding frequencies of positions (sin/cos(2^k x), k < pos_freqs)."""
    dir_freqs: int = field(default=4, metadata={"min": 0, "max": 24})
    """Positional-encoding frequencies of view directions."""
    n_coarse: int = field(default=64, metadata={"min": 1, "max": 4096})
    """Stratified samples per ray for the coarse network."""
    n_fine: int = field(default=128, metadata={"min": 0, "max": 4096})
    """Samples per ray drawn from the coarse weights for the fine network (0: no fine net)."""
    density_activation: Literal["softplus", "relu"] = "softplus"
    """softplus(raw - 1) (mip-NeRF's; trains from any start) or relu (the reference's)."""


@dataclass(frozen=True)
class Backend:
    """What the registry knows of one backend."""

    name: str
    options: type
    lr: float  # learning rate when a preset leaves it open
    adam_betas: tuple[float, float]
    adam_eps: float
    summary: str


# The reference's constant 5e-4 for the NeRF MLP (§9), instant-ngp's 1e-2 (and its Adam
# betas / eps) for hash grids (§4).
BACKENDS: dict[str, Backend] = {
    "ngp": Backend(
        "ngp", NGPOptions, 1e-2, (0.9, 0.99), 1e-15, "hash grid + tiny MLP, Warp kernels"
    ),
    "vanilla": Backend(
        "vanilla", VanillaOptions, 5e-4, (0.9, 0.999), 1e-8, "reference NeRF MLP, PyTorch"
    ),
}
BACKEND_NAMES: tuple[str, ...] = tuple(BACKENDS)


def backend(name: str) -> Backend:
    """The registry entry of `name`, or a one-line InputError listing the backends."""
    if name not in BACKENDS:
        raise InputError(f"unknown backend {name!r} (choose from {', '.join(BACKEND_NAMES)})")
    return BACKENDS[name]


def option_names(cls: type) -> dict[str, str | None]:
    """{option name: its section (None for a top-level field)} of an options dataclass."""
    names: dict[str, str | None] = {}
    for f in dataclasses.fields(cls):
        if _is_section(f):
            names.update({g.name: f.name for g in dataclasses.fields(f.default_factory)})
        else:
            names[f.name] = None
    return names


def _is_section(f: dataclasses.Field) -> bool:
    return f.default_factory is not dataclasses.MISSING and dataclasses.is_dataclass(
        f.default_factory
    )


# Options that were removed, each with the value that meant "off": a saved config that has
# it off still loads (the key is dropped); one that turned it on is an error.
RETIRED = {"relu_mask": False}  # slower on every scene (RESULTS.md, the forty-second session)


def _retired(key: str, value: Any, where: str) -> bool:
    """Whether `key` is a retired option given its old default (drop it); an error where it
    was turned on."""
    if key not in RETIRED:
        return False
    if value != RETIRED[key]:
        raise InputError(f"{where}: '{key}' was removed (it is off now); leave it out")
    return True


def nest_options(cls: type, d: dict, where: str) -> dict:
    """`d` with every flat key moved into its section; one line for an unknown key. A
    retired key at its old default is dropped (`RETIRED`)."""
    if not isinstance(d, dict):
        raise InputError(f"{where}: must be a JSON object")
    sections = {f.name for f in dataclasses.fields(cls) if _is_section(f)}
    names = option_names(cls)
    out: dict[str, Any] = {}
    for key, value in d.items():
        if key in sections:
            if not isinstance(value, dict):
                raise InputError(f"{where}: '{key}' must be an object (a section of options)")
            for k, v in value.items():
                if _retired(k, v, where):
                    continue
                if names.get(k) != key:
                    valid = ", ".join(k2 for k2, s in names.items() if s == key)
                    raise InputError(f"{where}: unknown key '{key}.{k}' (valid: {valid})")
                _put(out, key, k, v, where)
        elif key in names:
            _put(out, names[key], key, value, where)
        elif _retired(key, value, where):
            continue
        else:
            valid = ", ".join([*sorted(sections), *names])
            raise InputError(f"{where}: unknown key '{key}' (valid: {valid})")
    return out


def _put(out: dict, section: str | None, key: str, value: Any, where: str) -> None:
    node = out if section is None else out.setdefault(section, {})
    if key in node:
        raise InputError(f"{where}: '{key}' is given twice (flat and in section '{section}')")
    node[key] = value


def parse_options(name: str, d: dict | None, where: str = "backend_options") -> Any:
    """The options dataclass of backend `name` from a JSON object (nested or flat).

    Types and ranges are checked; every problem is one InputError line naming the key.
    """
    cls = backend(name).options
    return from_dict(cls, nest_options(cls, dict(d or {}), where), where)


def get_option(name: str, d: dict | None, key: str) -> Any:
    """The value `d` gives option `key` of backend `name` (flat or in its section), or None."""
    d = d or {}
    if key in d:
        return d[key]
    section = option_names(backend(name).options).get(key)
    return (d.get(section) or {}).get(key) if section else None


def set_option(name: str, d: dict | None, key: str, value: Any) -> dict:
    """A copy of options `d` with option `key` set: in its section if `d` has that section
    written out, else flat."""
    out = dict(d or {})
    section = option_names(backend(name).options).get(key)
    if section and isinstance(out.get(section), dict) and key not in out:
        out[section] = {**out[section], key: value}
    else:
        out[key] = value
    return out


# Compaction where it pays, on CUDA (measured on every built-in scene and a mesh scene of ours,
# benchmarks/RESULTS.md); the CPU preset's runs are not measured with it and keep it off.
COMPACTION_KEYS = ("early_stop_eps", "alpha_threshold", "compaction_auto")
GPU_COMPACTION = {"early_stop_eps": 1e-4, "compaction_auto": True}
# The ReLU in the GEMM's epilogue and the encodings' features in bf16 on CUDA (each measured
# on every built-in scene and the mesh scene, benchmarks/RESULTS.md); the CPU has neither
# the epilogue nor bf16 autocast.
GPU_NETWORK = {"fused_relu": True, "bf16_features": True}


def ngp_run_defaults(opts: dict | None, cone: float, device: str) -> dict:
    """ngp's options with the defaults a new run writes into its config (so a resume runs
    alike): `cone` unless cone_angle is set; on CUDA (`device` cuda[:N], or auto with a GPU)
    compaction_auto unless an option of compaction is set, and `GPU_NETWORK`'s options
    unless set."""
    out = dict(opts or {})
    if get_option("ngp", out, "cone_angle") is None:
        out = set_option("ngp", out, "cone_angle", cone)
    cuda = device.startswith("cuda")
    if device == "auto":
        import torch

        cuda = torch.cuda.is_available()
    if cuda and all(get_option("ngp", out, k) is None for k in COMPACTION_KEYS):
        for k, v in GPU_COMPACTION.items():
            out = set_option("ngp", out, k, v)
    for k, v in GPU_NETWORK.items() if cuda else ():
        if get_option("ngp", out, k) is None:
            out = set_option("ngp", out, k, v)
    return out
