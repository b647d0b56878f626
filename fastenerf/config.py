"""Configuration dataclasses: the scene's (`scene_config`, re-exported here) and training's.

`TrainConfig` holds every training option, by component (field, sampler, optimiser, the
studies' perturbations, self-calibration); `train_preset` fills it for a preset and backend.
Scene-side units and what `SceneConfig` switches on: `fastenerf.scene_config`.
"""

from __future__ import annotations

import dataclasses
import re
from dataclasses import dataclass, field
from typing import Any, Literal

from . import backends
from .backends import BACKEND_NAMES, parse_options
from .cpu_preset import NGP_CPU_RAYS, ngp_cpu_options
from .errors import InputError
from .perturb_config import PerturbConfig
from .scene_config import (  # noqa: F401  (re-exported: fastenerf.config is where they are read)
    EVENTNERF_REAL_THRESHOLD,
    EVENTNERF_REAL_Y_MIN,
    CylinderConfig,
    IntrinsicsConfig,
    SceneConfig,
    TrajectoryConfig,
    eventnerf_real_cylinder,
)
from .schema import check as _check
from .schema import check_ranges, from_dict

MAX_RAYS_PER_STEP = 1 << 20
"""Pixels per step above this are refused: 2^20 already needs tens of GiB on a GPU (ngp)."""
NGP_GPU_RAYS = 4096
"""ngp's pixels per step on a GPU: half as many per step train as well per second as 8192
did, in more and shorter steps (benchmarks/RESULTS.md: every built-in scene, mesh scene)."""

DEVICE_PATTERN = re.compile(r"^(auto|cpu|cuda(:\d+)?)$")


@dataclass
class TrainConfig:
    """How to train one field on one scene (saved resolved in RUN/config.json).

    `None` means "the default for this scene and device", filled by `resolved()` (each field's
    docstring says what that default is). Windows are measured in views (grid steps of the
    stream's pose grid); times are µs; the budget is whichever of steps / minutes ends first.
    Every field is a flag of `fastenerf train` (`win_max` -> `--win-max`), its help this text.
    """

    backend: str = field(default="ngp", metadata={"choices": BACKEND_NAMES})
    """Field backend."""
    preset: Literal["eventnerf", "fast", "custom"] = "fast"
    """Where the unset knobs come from: eventnerf (the reference's settings) or fast (ours)."""
    log_eps: float | None = field(default=None, metadata={"gt": 0.0, "max": 10.0})
    """eps of the log transform L(c) = log(c**gamma + eps), the guard against log(0).
    Default: 0.1 synthetic, 1e-5 real (the reference's); presets other than eventnerf use the
    simulator's eps when scene.json records one."""
    gamma: float = field(default=2.2, metadata={"gt": 0.0, "max": 10.0})
    """Display-to-linear exponent of the log transform: linear intensity is c**gamma."""
    win_min: int = field(default=1, metadata={"min": 1, "max": 1_000_000})
    """Shortest event window, views: the length is drawn as w ~ U{win_min..win_max}."""
    win_max: int | None = field(default=None, metadata={"min": 1, "max": 1_000_000})
    """Longest event window, views. Default: 50 synthetic / 100 real views of a 1000-view
    loop (the reference's), scaled by n_views / 1000; ngp's fast preset: 0.2 of a synthetic
    loop (FAST_WINDOW_FRACTION; a GPU run with --refine-poses starts on the reference's and
    lengthens them once the poses settle: refine_settle_px)."""
    win_redraw: Literal["step", "load"] = "step"
    """When window lengths are drawn: every step (ours), or once per end view at load (ref.)."""
    neg_ratio: float | None = field(default=None, metadata={"min": 0.0, "max": 1.0})
    """Fraction of each batch drawn at uniform pixels (negative sampling; the rest among pixels
    with events in their window). Default: 0.1 synthetic, 0.05 real."""
    rays_per_step: int | None = field(default=None, metadata={"min": 1, "max": MAX_RAYS_PER_STEP})
    """Pixels per step, each rendered at the window's start and end. Default: by preset and
    device and backend (ngp on CUDA 4096, vanilla on CUDA 8192; on a CPU 512, the CPU
    preset's for ngp; 1024 for eventnerf)."""
    samples_per_step: int | None = field(default=None, metadata={"min": 1024, "max": 1 << 30})
    """ngp: adapt the pixels per step so that a step trains on about this many samples
    (DESIGN §4: ~256 k on a GPU; instant-ngp's rule, `batch_size`), in multiples of 1,024
    pixels up to rays_per_step, decided where the sampler draws a block of steps. None:
    rays_per_step throughout."""
    windows_per_step: int = field(default=1, metadata={"min": 1, "max": 65536})
    """Windows per step; the pixels are split evenly over them (fast preset: 16)."""
    lr: float | None = field(default=None, metadata={"gt": 0.0, "max": 1.0})
    """Initial learning rate. Default: by backend (ngp 1e-2, vanilla 5e-4)."""
    lr_final: float | None = field(default=None, metadata={"gt": 0.0, "max": 1.0})
    """Learning rate at the end of the budget (exponential decay; unset: constant; fast: lr/10)."""
    lr_decay_start: float = field(default=0.0, metadata={"min": 0.0, "max": 0.99})
    """Budget fraction spent at `lr` before the decay to lr_final starts (instant-ngp decays
    late; fast preset 0.7); 0: from the first step."""
    lr_warmup_steps: int = field(default=0, metadata={"min": 0, "max": 1_000_000_000})
    """Steps of linear learning-rate warm-up from 0."""
    adam_betas: list[float] | None = None
    """Adam's two betas, each in [0, 1). Default: by backend (ngp 0.9 0.99, vanilla 0.9 0.999)."""
    adam_eps: float | None = field(default=None, metadata={"gt": 0.0, "max": 1.0})
    """Adam's eps. Default: by backend (ngp 1e-15, vanilla 1e-8)."""
    steps: int | None = field(default=None, metadata={"min": 0, "max": 1_000_000_000})
    """Step budget: the run's TOTAL number of steps (with --resume too: steps already done
    count towards it)."""
    minutes: float | None = field(default=None, metadata={"min": 0, "max": 10_000_000})
    """Training-time budget in minutes, evaluation and checkpoints excluded (with --resume:
    the run's total). Default when neither budget is given: 1 minute."""
    distortion_weight: float | None = field(default=None, metadata={"min": 0.0, "max": 1e6})
    """Weight of the mip-NeRF 360 distortion loss. Default: 1e-4 synthetic, 0 real."""
    checkpoint_every_s: float = field(default=30.0, metadata={"min": 0.0, "max": 1e9})
    """Wall seconds between checkpoints (0: only at the end and on Ctrl-C); written in the
    background, so a kill loses at most this much."""
    checkpoint_every_steps: int = field(default=0, metadata={"min": 0, "max": 1_000_000_000})
    """And/or a checkpoint every this many steps (0: by time only)."""
    eval_every_s: float = field(default=30.0, metadata={"min": 0.0, "max": 1e9})
    """Seconds of training between quick evaluations on test views (0: never)."""
    eval_views: int = field(default=3, metadata={"min": 1, "max": 100_000})
    """Test views of a quick evaluation."""
    eval_scale: float = field(default=0.25, metadata={"gt": 0.0, "max": 4.0})
    """Image scale of a quick evaluation."""
    log_every: int = field(default=10, metadata={"min": 1, "max": 1_000_000_000})
    """Write a metrics.jsonl line every this many steps."""
    seed: int = field(default=0, metadata={"min": 0, "max": 2**32 - 1})
    """Random seed (weights, window lengths, rays)."""
    amp: bool = True
    """bf16 autocast of the MLPs (CUDA only)."""
    device: str = "auto"
    """auto (CUDA if there is one, else CPU), cpu, cuda or cuda:N."""
    step_mode: Literal["auto", "plain", "device", "graph"] = "auto"
    """plain: the host reads each step's loss before updating (debugging); device: the finite
    check, skip and stats stay on the device, read every few steps (fused Adam); graph: device,
    replayed from a CUDA graph (ngp; device where a step cannot be captured); auto: graph on
    CUDA, plain on the CPU."""
    graph_copies: int = field(default=1, metadata={"min": 1, "max": 2})
    """graph: capture the step this many times and replay the copies in turn (each its own
    memory), so a replay never waits behind the previous replay of the same graph (issue
    #17; `benchmarks.graph_relaunch` measures whether that wait exists)."""
    graph_keys: int = field(default=4, metadata={"min": 1, "max": 8})
    """graph: keep the captured steps of this many keys (sample-buffer capacities, cone,
    compaction), the least recently used put down first, each in its own memory; a capacity
    that turns back to a kept size replays its graph instead of warming up and capturing
    again (what a recapture costs, and how often a capacity at a quantum's edge turns back:
    benchmarks/RESULTS.md, the forty-second session). Kept only while a quarter of the
    device's memory is free (`graph_step.KEEP_FREE_SHARE`). 1: a new key drops the old
    graph."""
    chunk: int = field(default=16384, metadata={"min": 1, "max": 1 << 22})
    """Rays per render call outside training (evaluation, rendering)."""
    backend_options: dict[str, Any] = field(default_factory=dict)
    """The backend's options (fastenerf.backends: NGPOptions / VanillaOptions), as JSON nested
    by section or flat."""
    perturb: PerturbConfig = field(default_factory=lambda: PerturbConfig())
    """The robustness studies' perturbations of the training data (pose error, noise events)."""
    # Self-calibration (issue #20; fastenerf/self_calibration.py): both off by default.
    smooth_poses: int = field(default=0, metadata={"min": 0, "max": 1 << 20})
    """Fit the training poses to a smooth path first (fastenerf/pose_smoothing.py): odd number
    of grid poses per local fit; removes pose-to-pose jitter, not a shared error."""
    smooth_order: int = field(default=2, metadata={"min": 1, "max": 2})
    """Degree of that fit (1: exact for turns at a constant rate, e.g. a turntable's)."""
    refine_poses: bool = False
    """Learn a correction of every training pose (window grid) with the field (own Adam)."""
    refine_translation: bool = False
    """Also learn the centres' shifts (off: from an orbit a small shift and turn look alike)."""
    refine_lr: float = 3e-3
    """Pose-correction lr at the start (rad, world units per step); decays to refine_lr_final."""
    refine_lr_final: float = 1e-6
    """Pose-correction learning rate at the end of the budget."""
    refine_c2f_start: float = 0.1
    """Coarse-to-fine (BARF): budget fraction where the encoding's finer levels (ngp hash
    levels, vanilla frequency bands) start to fade in; before it only the coarsest."""
    refine_c2f_end: float = 0.5
    """Budget fraction where every level is on (<= refine_c2f_start: no schedule)."""
    refine_c2f_mode: Literal["field", "gradient"] = "gradient"
    """What the coarse-to-fine weights act on: field (BARF: the field sees only the levels on)
    or gradient (the field sees every level; only the pose gradient is level-weighted)."""
    refine_start: float = 0.02
    """Budget fraction before which the poses are not updated (the field first carves its fog;
    later, it has learnt the wrong poses' blur); then the pose lr decays to refine_lr_final."""
    refine_warmup: float = 0.1
    """Fraction of the pose schedule over which the pose lr ramps up from 0 (0: no ramp)."""
    refine_windows_per_step: int | None = field(default=None, metadata={"min": 1, "max": 65536})
    """While refining poses, at least this many windows per step (each row needs visits).
    Default: 16 with smooth_poses, else 64 (`refine_defaults`)."""
    refine_win_max: int | None = field(default=None, metadata={"min": 1, "max": 1_000_000})
    """While refining poses, the corrections learn only from windows up to this many views
    (longer ones still render through the corrected poses, without a pose gradient); None:
    from every window. For long field windows with the pose gradient of short ones, where the
    poses are believed close: at 2° the long windows' field absorbs the pose error."""
    refine_settle_px: float | None = field(default=None, metadata={"min": 1e-6, "max": 1e3})
    """While refining poses, the field's windows lengthen to settle_win_max once the poses
    settle: when the corrections' turns moved less than this many pixels (RMS over the poses,
    at the focal length) over the last 5 % of the budget. Until then the field trains on
    win_max (default: the reference's), and the corrections learn from windows up to
    refine_win_max (default: win_max) throughout. None: off (`pose_settle`), except on a
    GPU run of ngp's fast preset on a synthetic scene with win_max unset: SETTLE_PX (0.3)."""
    refine_settle_smooth: int = field(default=0, metadata={"min": 0, "max": 1 << 20})
    """Once the poses settle (refine_settle_px), fit the corrected turns to a smooth path once
    (`pose_smoothing`'s fit, order 1, over this many grid poses; odd, >= 5) and set the
    corrections to reach it: what each pose's own estimate adds of noise (`pose_jitter_deg`)
    goes, an error smooth along the path stays. Needs a correction per pose. 0: off."""
    refine_freeze: bool = False
    """Stop learning the poses once they settle (refine_settle_px): the corrections stay as
    they are and the rays leave the autograd graph, so the rest of the run no longer pays for
    the pose gradient (the hash grid's position gradient, the rays' backward)."""
    refine_restart: bool = False
    """Once the poses settle (refine_settle_px), start the field afresh on them (a new field,
    occupancy grid and optimiser; the learning rate, occupancy and cone schedules over the
    budget left, `field_restart`): the first field has learnt the wrong poses' blur. Only
    where the given poses were off (refine_restart_deg). The poses are frozen from a restart
    on (a new field's gradient would move them); one GPU only."""
    refine_resume: float = field(default=0.0, metadata={"min": 0.0, "max": 1.0})
    """With refine_restart: the fraction of the new field's budget (what was left at the
    restart) after which the poses learn again, against the new field, whose gradient no
    longer carries the first field's blur; their lr goes on along its decay, their optimiser's
    moments cleared. 0: the poses stay frozen to the end. Below 1."""
    refine_restart_deg: float = field(default=0.1, metadata={"min": 0.0, "max": 180.0})
    """refine_restart only where the given poses were off by more than this mean turn
    (degrees): the motion prior's (smooth_poses; an exact path's is ~1e-14) or, without it,
    the corrections' at the settle. Below it the restart is declined: a field trained on poses
    that close has little blur to shed, and a restart would cost the budget before it."""
    refine_reset_deg: float = field(default=0.0, metadata={"min": 0.0, "max": 180.0})
    """While refining poses, every 1 % of the budget a pose row whose correction turns
    further than this (degrees) is put back to no correction, its optimiser state cleared
    (`pose_guard`: a row that ran away, its view's events pulling it further). Needs a
    correction per pose (no knots, no sharing). 0: off."""
    refine_diffuse_until: float = field(default=0.0, metadata={"min": 0.0, "max": 1.0})
    """While refining poses, the colour ignores the view direction (the ngp colour MLP's
    inputs past SH degree 0 masked) until this budget fraction, or until the poses settle
    (refine_settle_px) where that comes first: views of a point that disagree through a
    pose's error cannot be explained by view-dependent colour, only by the poses. 0: off."""
    settle_win_max: int | None = field(default=None, metadata={"min": 1, "max": 1_000_000})
    """The field's longest window once the poses settle (refine_settle_px), views. Default:
    the fast preset's long windows, FAST_WINDOW_FRACTION of the loop (at least win_max)."""
    refine_optimizer: Literal["adam", "row-adam"] = "row-adam"
    """adam: one Adam over every pose row; row-adam: lazy, a row steps when a batch sees it."""
    refine_beta1: float = field(default=0.9, metadata={"min": 0.0, "max": 0.9999})
    """The pose Adam's β1 (on noise-only visits m/√v shrinks as √((1 − β1)/(1 + β1)))."""
    refine_gauge: Literal["auto", "mean", "first", "none"] = "auto"
    """Gauge fix: mean (zero-mean corrections), first (first pose fixed), none (free drift);
    auto: none for turns only (the given centres fix the frame), mean with refine_translation."""
    refine_shared: bool = False
    """One correction c2w_i · R shared by every pose (a mis-mounted camera); no gauge fix."""
    refine_shared_until: float = field(default=0.0, metadata={"min": 0.0, "max": 1.0})
    """Budget fraction until which every pose takes one shared correction (the rows' summed
    gradient), each its own after (0: per pose throughout); needs the gauge none."""
    refine_knots: int = field(default=0, metadata={"min": 0, "max": 1 << 20})
    """Learn the corrections at this many knots spread along the pose grid, each grid pose's
    interpolated between its two (0: one per grid pose): for an error smooth along the path."""
    refine_knot_rows: bool = False
    """With refine_knots: each grid pose also learns its own correction, added to the knots'
    (the knots pool the gradient of an error smooth along the path, the rows take the rest)."""
    refine_decay: float | None = field(default=None, metadata={"min": 0.0, "max": 1e4})
    """Decoupled decay towards the given poses: a row a batch sees shrinks by pose lr x this.
    Default: 0 with smooth_poses, else 30 (`refine_defaults`)."""
    refine_gate: float = field(default=1.5, metadata={"min": 0.0, "max": 100.0})
    """Significance gate on the row-adam's pose steps (0: off; adam has none): a component steps
    in full once its mean gradient stands 2 x gate standard errors from zero, none below gate."""
    refine_gate_beta: float = field(default=0.99, metadata={"min": 0.0, "max": 0.9999})
    """The gate's averaging of a row's gradients (β; ~1/(1 − β) visits)."""
    refine_gate_prior_deg: float | None = field(default=None, metadata={"min": 0.0, "max": 180})
    """Gate off where the motion prior turned the given poses by more than this mean (deg):
    they are known to be off, so no step is held back as noise (None: the gate always holds)."""
    estimate_threshold: bool = False
    """Estimate the thresholds' ratio C_pos/C_neg (product kept: the scale is not observable)."""
    threshold_ratio: Literal["auto", "loop", "learn"] = "auto"
    """estimate_threshold's ratio: loop (counted over the closed loop, data/loop_ratio.py),
    learn (with the field), auto (loop where the camera returns to its start pose)."""
    threshold_lr: float = 1e-3
    """Threshold learning rate (log units per step), following the field's lr schedule."""
    threshold_per_pixel: bool = False
    """Also learn per-pixel factors on the thresholds (mismatch), regularised towards 1."""
    threshold_pixel_weight: float = 1.0
    """Weight of the per-pixel factors' regulariser (mean squared log factor)."""
    threshold_free_scale: bool = False
    """Learn the common scale too (ill-posed: nothing holds it; for experiments)."""

    def validate(self, where: str = "train config") -> TrainConfig:
        """Check every value's type-free range; raise a one-line InputError naming the key."""
        check_ranges(self, where)
        ok, dev = DEVICE_PATTERN.match(str(self.device)) is not None, self.device
        _check(ok, where, "device", f"must be auto, cpu, cuda or cuda:N, got {dev!r}")
        ok, lo = self.win_max is None or self.win_max >= self.win_min, self.win_min
        _check(ok, where, "win_max", f"must be >= win_min ({lo}), got {self.win_max}")
        rays, wins = self.rays_per_step, self.windows_per_step
        ok = rays is None or rays >= wins
        _check(ok, where, "rays_per_step", f"must be at least windows_per_step ({wins})")
        ok = self.samples_per_step is None or self.backend == "ngp"
        _check(ok, where, "samples_per_step", "needs the ngp backend (it counts the samples)")
        self._validate_self_calibration(where)
        ok = (b := self.adam_betas) is None or (len(b) == 2 and all(0 <= x < 1 for x in b))
        _check(ok, where, "adam_betas", f"must be two numbers in [0, 1), got {b}")
        parse_options(self.backend, self.backend_options, f"{where} backend_options")
        return self

    def _validate_self_calibration(self, where: str) -> None:
        for key in ("refine_lr", "refine_lr_final", "threshold_lr"):
            v = getattr(self, key)
            _check(0 < v <= 1, where, key, f"must be in (0, 1], got {v}")
        for key in ("refine_c2f_start", "refine_c2f_end", "refine_start", "refine_warmup"):
            v = getattr(self, key)
            _check(0 <= v <= 1, where, key, f"must be a budget fraction in [0, 1], got {v}")
        w, n = self.threshold_pixel_weight, self.smooth_poses
        ok = n == 0 or (n >= 5 and n % 2 == 1)
        _check(ok, where, "smooth_poses", f"must be 0 (off) or odd and >= 5, got {n}")
        for key, allowed in (
            ("refine_gauge", ("auto", "mean", "first", "none")),
            ("refine_c2f_mode", ("field", "gradient")),
            ("refine_optimizer", ("adam", "row-adam")),
        ):
            v = getattr(self, key)
            _check(v in allowed, where, key, f"must be one of {allowed}, got {v!r}")
        v = self.refine_start
        _check(v < 1, where, "refine_start", f"must be below 1 (poses never learnt), got {v}")
        g = "mean" if self.refine_gauge == "auto" and self.refine_translation else self.refine_gauge
        ok = g in ("auto", "none") and self.refine_poses and not self.refine_shared
        why = "needs refine_poses, refine_gauge none and no refine_shared"
        _check(self.refine_shared_until == 0 or ok, where, "refine_shared_until", why)
        ok = self.refine_poses or not self.refine_shared
        _check(ok, where, "refine_shared", "needs refine_poses (it shapes the pose correction)")
        ok = self.refine_poses or self.refine_settle_px is None
        _check(ok, where, "refine_settle_px", "needs refine_poses (it watches the corrections)")
        ok = self.refine_poses or not self.refine_freeze
        _check(ok, where, "refine_freeze", "needs refine_poses (it stops the pose learning)")
        ok = self.refine_poses or not self.refine_restart
        _check(ok, where, "refine_restart", "needs refine_poses (it restarts when they settle)")
        v = self.refine_resume
        _check(v < 1, where, "refine_resume", f"must be below 1 (the poses never resume), got {v}")
        ok = self.refine_restart or v == 0
        _check(ok, where, "refine_resume", "needs refine_restart (the poses resume after it)")
        per_pose = self.refine_knots == 0 and not self.refine_shared
        per_pose = per_pose and self.refine_shared_until == 0
        ok = self.refine_reset_deg == 0 or (self.refine_poses and per_pose)
        why = "needs refine_poses with a correction per pose (no knots, no sharing)"
        _check(ok, where, "refine_reset_deg", why)
        n = self.refine_settle_smooth
        ok = n == 0 or (n >= 5 and n % 2 == 1)
        _check(ok, where, "refine_settle_smooth", f"must be 0 (off) or odd and >= 5, got {n}")
        ok = n == 0 or (self.refine_poses and per_pose)
        _check(ok, where, "refine_settle_smooth", why)
        ok = self.refine_poses or self.refine_diffuse_until == 0
        _check(ok, where, "refine_diffuse_until", "needs refine_poses (it ends when they settle)")
        ok = self.refine_diffuse_until == 0 or self.backend == "ngp"
        why = "needs the ngp backend (it masks its colour MLP's SH inputs)"
        _check(ok, where, "refine_diffuse_until", why)
        ok = self.settle_win_max is None or self.refine_settle_px is not None
        _check(ok, where, "settle_win_max", "needs refine_settle_px (when the windows lengthen)")
        k, shared = self.refine_knots, self.refine_shared or self.refine_shared_until > 0
        ok = k == 0 or (k >= 2 and not shared)
        _check(ok, where, "refine_knots", f"must be 0 or >= 2 and without refine_shared, got {k}")
        ok = not self.refine_knot_rows or k >= 2
        _check(ok, where, "refine_knot_rows", "needs refine_knots (it adds rows to the knots)")
        _check(0 <= w <= 1e6, where, "threshold_pixel_weight", f"must be in [0, 1e6], got {w}")

    def refine_defaults(self) -> tuple[int, float]:
        """(refine_windows_per_step, refine_decay), a None filled: 16 and 0 after smooth_poses
        (what the prior leaves is slow along the path, and the decay held it back), else 64 and
        30 (without the prior, 16 windows leave half of a 1° error; benchmarks/RESULTS.md)."""
        prior, w, d = self.smooth_poses > 0, self.refine_windows_per_step, self.refine_decay
        w = (16 if prior else 64) if w is None else w
        return w, (0.0 if prior else 30.0) if d is None else d

    def resolved(self, scene: SceneConfig, device: str = "cpu") -> TrainConfig:
        """A copy with every `None` replaced by its scene / device / backend default."""
        real = scene.kind == "real"
        c = dataclasses.replace(
            self,
            backend_options=dict(self.backend_options),
            perturb=dataclasses.replace(self.perturb),
        )
        if c.log_eps is None:
            if c.preset != "eventnerf" and scene.sim_log_eps:
                # A simulated scene records the eps its events were made with: the matched log
                # is the exact model (0.1 against a 1e-3 simulator under-predicts dark edges).
                c.log_eps = float(scene.sim_log_eps)
            else:
                c.log_eps = 1e-5 if real else 0.1
        cpu_ngp = c.backend == "ngp" and not str(device).startswith("cuda")
        c._resolve_windows(scene.n_views, real, cpu_ngp)
        why = "needs refine_settle_px here (it says when the poses settled), e.g. 0.3"
        ok = not c.refine_restart or c.refine_settle_px is not None
        _check(ok, "train config", "refine_restart", why)
        ok = not c.refine_freeze or c.refine_settle_px is not None
        _check(ok, "train config", "refine_freeze", why)
        ok = not c.refine_settle_smooth or c.refine_settle_px is not None
        _check(ok, "train config", "refine_settle_smooth", why)
        if c.neg_ratio is None:
            c.neg_ratio = 0.05 if real else 0.1
        if c.distortion_weight is None:
            c.distortion_weight = 0.0 if real else 1e-4
        if cpu_ngp:  # the CPU preset fills the options left unset (fastenerf.cpu_preset)
            c.backend_options = ngp_cpu_options(c.backend_options)
        if c.rays_per_step is None:
            # a 2-core CPU needs small batches; vanilla keeps the 8192 it was measured with
            gpu = NGP_GPU_RAYS if c.backend == "ngp" else 8192
            c.rays_per_step = gpu if str(device).startswith("cuda") else 512
            c.rays_per_step = NGP_CPU_RAYS if cpu_ngp else c.rays_per_step
            c.rays_per_step = max(c.rays_per_step, c.windows_per_step)
        c.refine_windows_per_step, c.refine_decay = c.refine_defaults()
        if c.refine_poses:
            more = min(c.refine_windows_per_step, c.rays_per_step)
            c.windows_per_step = max(c.windows_per_step, more)
        b = backends.backend(c.backend)
        if c.lr is None:
            c.lr = b.lr
        if c.adam_betas is None:
            c.adam_betas = list(b.adam_betas)
        if c.adam_eps is None:
            c.adam_eps = b.adam_eps
        if c.steps is None and c.minutes is None:
            c.minutes = 1.0
        c.device = str(device)
        return c.validate()

    def _resolve_windows(self, n_views: int, real: bool, cpu_ngp: bool) -> None:
        """win_max and, where the windows lengthen once the poses settle, settle_win_max and
        refine_win_max: the `None`s replaced in place (`resolved`'s copy)."""
        if self.win_max is None:
            longer = self.backend == "ngp" and self.preset == "fast" and not real
            if longer and self.refine_poses and not cpu_ngp and self.refine_settle_px is None:
                self.refine_settle_px = SETTLE_PX  # a GPU run that refines poses: see SETTLE_PX
            settle = self.refine_poses and self.refine_settle_px is not None
            # A run whose windows lengthen once the poses settle starts on the reference's.
            longer = longer and (cpu_ngp or not self.refine_poses) and not settle
            fraction = FAST_WINDOW_FRACTION if longer else None
            self.win_max = reference_win_max(n_views, real, self.win_min, fraction)
        if self.refine_poses and self.refine_settle_px is not None:
            if self.settle_win_max is None:
                fraction = FAST_WINDOW_FRACTION
                self.settle_win_max = reference_win_max(n_views, real, self.win_min, fraction)
            self.settle_win_max = max(self.settle_win_max, self.win_max)
            if self.refine_win_max is None:
                self.refine_win_max = self.win_max

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any], where: str = "train config") -> TrainConfig:
        return from_dict(cls, d, where).validate(where)


# Longest event window of ngp's fast preset on synthetic scenes, as a fraction of the loop (the
# reference's 0.05 elsewhere): a run of seconds to minutes learns faster from windows that span
# more of the loop (every built-in scene and a mesh scene, on a 2-core CPU and on an H100:
# benchmarks/RESULTS.md, the twenty-second and twenty-third sessions). A GPU run that refines
# poses gets them only once its poses settle (SETTLE_PX): at 2° a field on long windows from the
# start absorbs the pose error and the poses stop higher, even with the pose gradient from
# short windows only (refine_win_max; the twenty-fourth session).
FAST_WINDOW_FRACTION = 0.2

# A GPU run of ngp's fast preset that refines poses on a synthetic scene, with win_max unset,
# starts on the reference's windows and lengthens them to FAST_WINDOW_FRACTION once the pose
# corrections move less than this many pixels per 5 % of the budget (`pose_settle`): the long
# windows' gain at 0° on every built-in scene and the mesh scene, with the short windows' pose
# accuracy at 2° (benchmarks/RESULTS.md, the twenty-fifth session). An explicit win_max keeps
# its windows throughout; the CPU, where long windows did not hurt at 2°, keeps them long.
SETTLE_PX = 0.3


def reference_win_max(
    n_views: int, real: bool, win_min: int = 1, fraction: float | None = None
) -> int:
    """Longest event window, views: the reference's 50 (synthetic) / 100 (real) views of a
    1000-view loop, as the same fraction of a loop of `n_views` (or `fraction` of it)."""
    fraction = (0.1 if real else 0.05) if fraction is None else fraction
    return max(win_min, 2, round(fraction * n_views))


# Presets: values a preset fixes; the rest stay at the dataclass defaults (None = scene default).
TRAIN_PRESETS: dict[str, dict[str, Any]] = {
    # The reference implementation (DESIGN §9): 1024 pixels x 2 poses from ONE window per step,
    # window length drawn once per end view at load time, constant lr, AMP, 5e5 iterations.
    "eventnerf": {
        "win_redraw": "load",
        "rays_per_step": 1024,
        "windows_per_step": 1,
        "lr_final": None,
        "steps": 500_000,
        "amp": True,
    },
    # Our choices for speed:
    # - rays_per_step by device and backend (ngp: NGP_GPU_RAYS on CUDA, 256 on a CPU): more,
    #   smaller steps learn faster per second; the per-step cost is what limits a CPU.
    # - 16 windows per step: one window sees a narrow arc of views, so a step with many windows
    #   gives a far less noisy gradient for the same number of rays.
    # - window length re-drawn every step: every end view meets every length over training
    #   instead of one fixed length per view (supplement G found random lengths essential).
    # - lr held for 70 % of the budget, then exponential decay to lr/10: the high lr learns,
    #   the late decay removes the noise floor (benchmarks/RESULTS.md: every built-in scene).
    "fast": {
        "win_redraw": "step",
        "windows_per_step": 16,
        "lr_final_ratio": 0.1,
        "lr_decay_start": 0.7,
        "amp": True,
    },
}


# ngp's marching cone angle follows the training budget unless backend_options set it: constant
# steps (0) for a run with a budget (after `NGPOptions.marcher.early_cone_angle`'s first steps);
# instant-ngp's 1/256 for an open-ended run (the live viewer), which renders several times faster.
OPEN_ENDED_CONE = 1.0 / 256


def ngp_cone_for_budget(minutes: float | None, steps: int | None) -> float:
    """0 for a run with a time or step budget; OPEN_ENDED_CONE for one with neither."""
    return OPEN_ENDED_CONE if minutes is None and steps is None else 0.0


def train_preset(name: str, backend: str = "ngp", **overrides: Any) -> TrainConfig:
    """The TrainConfig of preset `name` ("eventnerf" | "fast") for `backend`, with overrides.

    Overrides whose value is None are ignored (so CLI flags that were not given keep the preset).
    """
    if name not in TRAIN_PRESETS:
        raise InputError(f"unknown preset {name!r} (choose from {sorted(TRAIN_PRESETS)})")
    lr = backends.backend(backend).lr
    values = dict(TRAIN_PRESETS[name])
    ratio = values.pop("lr_final_ratio", None)
    values.update({k: v for k, v in overrides.items() if v is not None})
    names = {f.name for f in dataclasses.fields(TrainConfig)}
    if unknown := sorted(set(values) - names):
        raise InputError(f"unknown training option(s) {unknown}")
    if isinstance(values.get("perturb"), dict):  # e.g. a benchmark's --set perturb={...}
        values["perturb"] = from_dict(PerturbConfig, values["perturb"], "perturb")
    cfg = TrainConfig(backend=backend, preset=name, **values)
    if cfg.lr is None:
        cfg.lr = lr
    if ratio is not None and overrides.get("lr_final") is None:
        cfg.lr_final = cfg.lr * ratio
    if overrides.get("minutes") is not None and overrides.get("steps") is None:
        cfg.steps = None  # a time budget replaces the preset's step count
    if backend == "ngp":  # written into the run's config: a resume runs alike
        cone = ngp_cone_for_budget(cfg.minutes, cfg.steps)
        opts = backends.ngp_run_defaults(cfg.backend_options, cone, str(cfg.device))
        cfg.backend_options = opts
    return cfg.validate()
