"""Self-calibration: the training poses and contrast thresholds learnt with the field (#20).

`SelfCalibration` owns the parts that are switched on (`pose_refine.PoseRefiner`,
`threshold.ThresholdEstimator`), their own Adam (one group each, own learning rates) and
the coarse-to-fine schedule of the field's encoding. The trainer asks it, per step, for
the rays and targets of a batch (`apply`), steps it after the field's optimiser (`step`)
and logs its `stats`; `report` goes into RUN/config.json. Guards: the optimiser step is
skipped when a gradient is not finite (a NaN would stay in Adam's moments for good), the
threshold parameters are projected into their bounds after each step, and pose corrections
are gauge-fixed (`pose_refine`) unless one is shared by every pose (`refine_shared`: a camera
mis-mounted; no gauge, refine_gauge is ignored).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from .coarse_to_fine import set_encoding_window
from .config import TrainConfig
from .data.loop_ratio import scene_loop_ratio
from .errors import InputError
from .fields.base import Field
from .optim import lr_as_floats, lr_as_tensors, set_group_lr
from .pose_refine import PoseRefiner, RowAdam
from .sampling import RayBatch, RaySampler
from .threshold import ThresholdEstimator

ADAM_BETAS = (0.9, 0.999)
ADAM_EPS = 1e-12  # pose gradients can be small; 1e-8 would damp their steps


def used_rows(sampler: RaySampler) -> torch.Tensor:
    """(G,) bool: the grid rows some window starts or ends on (a loop never uses its last)."""
    ws = sampler.windows
    used = torch.zeros(ws.n_views + 1, dtype=torch.bool)
    used[torch.from_numpy(np.unique(ws.pose_index(np.arange(ws.n_views + 1))))] = True
    return used


def check_knots(knots: int, rows: int) -> None:
    """One-line InputError unless refine_knots fits the grid: at most one per grid pose."""
    if knots > rows - 1:
        why = f"{knots} knots for a grid of {rows} poses: at most {rows - 1} (0: one per pose)"
        raise InputError(f"refine_knots: {why}")


def pose_lr(cfg: TrainConfig, progress: float) -> float:
    """The pose corrections' lr at training `progress` in [0, 1]: 0 before refine_start, then
    an exponential decay from refine_lr to refine_lr_final over the rest of the budget, ramped
    up linearly over its first refine_warmup (a row's first visits would otherwise take
    full-size Adam steps in whatever direction the young field's gradient points). The
    per-pose phase after refine_shared_until starts its own ramp and decay there."""
    if progress < cfg.refine_start:
        return 0.0
    start = cfg.refine_start
    if 0 < cfg.refine_shared_until <= progress:
        start = max(start, cfg.refine_shared_until)
    r = (progress - start) / (1.0 - start)
    ramp = 1.0 if cfg.refine_warmup <= 0 else min(1.0, r / cfg.refine_warmup)
    return ramp * cfg.refine_lr * (cfg.refine_lr_final / cfg.refine_lr) ** r


def row_gate(cfg: TrainConfig, prior_turn_deg: float | None) -> float:
    """The row Adam's significance gate: refine_gate, or 0 (off) where the motion prior turned
    the given poses by more than refine_gate_prior_deg on average (prior_turn_deg: its report's
    mean_turn_deg, None without the prior). The gate is for poses that are already right."""
    limit = cfg.refine_gate_prior_deg
    if limit is not None and prior_turn_deg is not None and prior_turn_deg > limit:
        return 0.0
    return cfg.refine_gate


def pose_gauge(cfg: TrainConfig) -> str:
    """The refiner's gauge: none for a shared row (it has none); "auto" is none for turns
    only, since with the centres held at the given ones a turn shared by every camera about
    its own centre is no rigid motion of the scene, and the mean gauge would keep the mean of
    the pose errors for good (measured: benchmarks/RESULTS.md); mean when centres move too."""
    if cfg.refine_shared:
        return "none"
    if cfg.refine_gauge == "auto":
        return "mean" if cfg.refine_translation else "none"
    return cfg.refine_gauge


class SelfCalibration:
    """The learnt calibration of one training run (see the module docstring).

    cfg: the resolved TrainConfig; sampler: the run's RaySampler (built with_poses /
    with_parts as cfg asks); thresholds: scene.json's (C_pos, C_neg); field: the field whose
    encoding the coarse-to-fine schedule weights; true_c2w: optional (G, 4, 4) exact grid
    poses (a pose-error study's unperturbed rig), for the error stats; ratio: a measured
    threshold ratio, or None; prior_turn_deg: the motion prior's mean turn of the given poses
    (degrees), or None without the prior, for the gate (`row_gate`).
    """

    def __init__(
        self,
        cfg: TrainConfig,
        sampler: RaySampler,
        thresholds: tuple[float, float],
        field: Field,
        true_c2w: torch.Tensor | None = None,
        ratio: float | None = None,
        prior_turn_deg: float | None = None,
    ):
        self.cfg, self.field = cfg, field
        self.gate = row_gate(cfg, prior_turn_deg) if cfg.refine_optimizer == "row-adam" else 0.0
        self.decay = cfg.refine_defaults()[1] if cfg.refine_poses else 0.0
        self.poses: PoseRefiner | None = None
        self.thresholds: ThresholdEstimator | None = None
        groups = []
        self.pose_optimizer: RowAdam | None = None  # refine_optimizer "row-adam"
        self._seen: torch.Tensor | None = None  # (G,) bool rows the last batch saw
        if cfg.refine_poses:
            check_knots(cfg.refine_knots, len(sampler.grid_c2w))
            self.poses = PoseRefiner(
                sampler.grid_c2w,
                used_rows(sampler),
                pose_gauge(cfg),
                true_c2w,
                translation=cfg.refine_translation,
                shared=cfg.refine_shared,
                knots=cfg.refine_knots,
            )
            betas = (cfg.refine_beta1, ADAM_BETAS[1])
            group = {"params": [self.poses.delta], "lr": cfg.refine_lr, "name": "poses"}
            group["betas"] = betas
            if cfg.refine_optimizer == "row-adam":
                gate = {"gate": self.gate, "gate_beta": cfg.refine_gate_beta}
                self.pose_optimizer = RowAdam([group], cfg.refine_lr, betas, ADAM_EPS, **gate)
            else:
                groups.append(group)
        if cfg.estimate_threshold:
            self.thresholds = ThresholdEstimator(
                *thresholds,
                sampler.n_pix,
                per_pixel=cfg.threshold_per_pixel,
                free_scale=cfg.threshold_free_scale,
                pixel_weight=cfg.threshold_pixel_weight,
                ratio=ratio,
                device=sampler.device,
            )
            params = [p for p in self.thresholds.parameters() if p.requires_grad]
            if params:  # a measured ratio, no per-pixel factors: nothing to learn
                groups.append({"params": params, "lr": cfg.threshold_lr, "name": "thresholds"})
        if not self.wanted(cfg):
            raise ValueError("SelfCalibration: neither refine_poses nor estimate_threshold is on")
        # torch's Adam takes no empty list: a placeholder group when row-adam has the poses.
        # Fused where the field's Adam is (the device-paced step): it skips on `found_inf`.
        fused = torch.device(sampler.device).type == "cuda" or cfg.step_mode in ("device", "graph")
        self.optimizer = torch.optim.Adam(
            groups or [{"params": [], "name": "none"}],
            betas=ADAM_BETAS,
            eps=ADAM_EPS,
            fused=fused if groups else None,
        )
        self._placeholder = not groups  # the optimiser holds no parameter
        self.skipped_steps = 0  # steps whose gradients were not finite
        self.c2f: float | None = None  # fraction of the coarse-to-fine schedule done
        self._sharing = False  # the poses share one correction now (refine_shared_until)
        self.pose_lr_now = 0.0  # this step's pose lr, on the host (the device may hold a copy)

    @property
    def static(self) -> bool:
        """Nothing learnt: thresholds with a measured ratio only."""
        return self.poses is None and not any(p.requires_grad for p in self.parameters())

    @property
    def capturable(self) -> bool:
        """Whether a CUDA graph can replay the step: every learning rate a device tensor
        (`lr_as_tensors`), the pose rows stepped by the row Adam (which reads its lr and
        decay on the device; plain Adam's decay is a host-side rate), and a fused Adam for the
        thresholds (it skips on the device's non-finite flag)."""
        if self.poses is not None and self.pose_optimizer is None:
            return False
        return self._placeholder or bool(self.optimizer.defaults.get("fused"))

    def graph_key(self) -> tuple:
        """What a captured step bakes in of the calibration: whether the poses step (their lr
        is 0 before refine_start; the row Adam is then not launched at all) and whether they
        share one correction (refine_shared_until)."""
        return (self.poses is not None and self.pose_lr_now > 0, self._sharing)

    def lr_as_tensors(self, device: torch.device) -> None:
        """Learning rates as device tensors a captured step reads (`before_step` fills them)."""
        if not self._placeholder:
            lr_as_tensors(self.optimizer, device)
        if self.pose_optimizer is not None:
            self.pose_optimizer.lr_as_tensors(device)

    def lr_as_floats(self) -> None:
        """Undo `lr_as_tensors` (also after loading a state saved with tensor lrs)."""
        lr_as_floats(self.optimizer)
        if self.pose_optimizer is not None:
            lr_as_floats(self.pose_optimizer)

    @classmethod
    def wanted(cls, cfg: TrainConfig) -> bool:
        return bool(cfg.refine_poses or cfg.estimate_threshold)

    # -- per step ----------------------------------------------------------------------------

    def before_step(self, progress: float, field_lr_scale: float) -> None:
        """Learning rates and the encoding window for training `progress` in [0, 1].

        field_lr_scale: the field's lr now over its initial lr (warm-up and decay), which the
        threshold lr follows; the pose lr decays on its own from refine_lr to refine_lr_final.
        """
        c = self.cfg
        self.pose_lr_now = pose_lr(c, progress)
        was = self._sharing
        self._sharing = self.poses is not None and progress < c.refine_shared_until
        if was and not self._sharing:
            self._forget_pose_moments()
        for g in self.param_groups():
            lr = self.pose_lr_now if g["name"] == "poses" else c.threshold_lr * field_lr_scale
            set_group_lr(g, lr)
        if self.poses is not None:
            self.c2f = set_encoding_window(
                self.field, progress, c.refine_c2f_start, c.refine_c2f_end, c.refine_c2f_mode
            )

    @torch.no_grad()
    def _forget_pose_moments(self) -> None:
        """Zero the pose optimiser's moments and step counts in place (a captured step keeps
        its buffers) where the shared phase ends: they hold the summed gradient of every row,
        hundreds of times one row's, which would shrink each pose's own steps for as long as
        the second moment takes to forget it (~1/(1 − β2) visits)."""
        opt = self.pose_optimizer or self.optimizer
        for v in opt.state.get(self.poses.delta, {}).values():
            if torch.is_tensor(v):
                v.zero_()

    def param_groups(self) -> list[dict]:
        """Every optimiser group (poses, thresholds) of both optimisers."""
        extra = [] if self.pose_optimizer is None else self.pose_optimizer.param_groups
        return [g for g in (*self.optimizer.param_groups, *extra) if g["params"]]

    def apply(
        self, batch: RayBatch
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """rays_o, rays_d (2B, 3), target (B,) and a regulariser (scalar or None) of a batch,
        differentiable w.r.t. the learnt calibration."""
        rays_o, rays_d, target, reg = batch.rays_o, batch.rays_d, batch.target, None
        if self.poses is not None:
            if batch.pose_idx is None:
                raise ValueError("SelfCalibration: the sampler was built without with_poses")
            # the batch's own rays: what the fused path returns on uncorrected rows (δ = 0)
            rays_o, rays_d, self._seen = self.poses.rays_and_rows(
                batch.dirs, batch.pose_idx, batch.rays_d
            )
        if self.thresholds is not None:
            if batch.parts is None:
                raise ValueError("SelfCalibration: the sampler was built without with_parts")
            target = self.thresholds.target(batch.parts, batch.pix)
            reg = self.thresholds.regulariser(batch.pix)
        return rays_o, rays_d, target, reg

    def zero_grad(self) -> None:
        self.optimizer.zero_grad(set_to_none=True)
        if self.pose_optimizer is not None:
            self.pose_optimizer.zero_grad(set_to_none=True)

    def parameters(self) -> list[torch.nn.Parameter]:
        """The learnt calibration's parameters (a device-paced step's guard checks them)."""
        return [p for g in self.param_groups() for p in g["params"]]

    def step(self, found_inf: torch.Tensor | None = None) -> bool:
        """One optimiser step unless a gradient is not finite; returns whether it stepped.

        found_inf: the device-paced step's 0-dim flag (`device_step.FiniteGuard`, which then
        also checked these gradients): the skip is decided on the device and this returns
        True. Without it the host checks (a skip is counted in `skipped_steps`).
        """
        if found_inf is not None and self.optimizer.defaults.get("fused") is False:
            found_inf = None  # an unfused Adam with thresholds cannot skip on the device
        if found_inf is None:
            grads = [p.grad for p in self.parameters() if p.grad is not None]
            if grads and not bool(torch.stack([torch.isfinite(g).all() for g in grads]).all()):
                self.skipped_steps += 1
                self.zero_grad()
                return False
        elif self.optimizer.defaults.get("fused"):  # None: the placeholder, nothing to skip
            self.optimizer.found_inf, self.optimizer.grad_scale = found_inf, None
        if self._sharing and self.poses.delta.grad is not None:
            self._seen = self.poses.share_gradient()  # before either optimiser steps them
        if not self._placeholder:  # whose unfused step a CUDA graph could not capture
            self.optimizer.step()
        if self._row_adam_steps():  # the row Adam decays the rows it steps, in its launch
            self.pose_optimizer.step(self._seen, found_inf=found_inf, decay=self.decay)
        elif self.decay > 0:  # plain Adam, the pose lr still 0, or no pose gradient
            self._decay_poses(found_inf)
        if self.thresholds is not None:
            self.thresholds.project()
        return True

    def _row_adam_steps(self) -> bool:
        """Whether the row Adam steps the poses now (lr > 0 and a gradient); it then also
        applies refine_decay (`RowAdam.step`'s decay, the same ops as `_decay_poses`)."""
        opt = self.pose_optimizer
        return opt is not None and self.pose_lr_now > 0 and self.poses.delta.grad is not None

    @torch.no_grad()
    def _decay_poses(self, found_inf: torch.Tensor | None) -> None:
        """Shrink the corrections of the rows this batch saw by lr x refine_decay (decoupled
        from Adam: its normalised step would scale a prior's pull up to the lr), after the
        optimiser's step; skipped with it (found_inf). Where the row Adam steps the poses it
        does this itself (`RowAdam.step(decay=...)`); this is for the other cases."""
        lr = self.pose_lr_now
        if lr * self.decay == 0:
            return  # a factor of exactly 1: nothing changes
        seen = self._seen
        if found_inf is not None:
            seen = seen & found_inf.to(seen.device).eq(0)
        rate = min(1.0, lr * self.decay)
        self.poses.delta.mul_(1.0 - rate * seen[:, None].to(self.poses.delta.dtype))

    # -- reporting ---------------------------------------------------------------------------

    def stats(self, on_device: bool = False) -> dict[str, Any]:
        """Step stats (metrics.jsonl, the viewer): the pose and threshold estimates.
        on_device: the estimates as 0-dim device tensors, read nowhere here: a device-paced
        step's pending stats, copied to the host at its flush (a read here would wait for
        every queued step, off the training clock)."""
        out: dict[str, Any] = {}
        if self.poses is not None:
            out.update(self.poses.stats(on_device))
            out["c2f"] = 1.0 if self.c2f is None else self.c2f
        if self.thresholds is not None:
            out.update(self.thresholds.stats(on_device))
        if self.skipped_steps:
            out["calibration_skipped_steps"] = self.skipped_steps
        return out

    def report(self) -> dict[str, Any]:
        """What config.json records: the options' results (estimates, corrections' sizes)."""
        out: dict[str, Any] = {"stats": self.stats()}
        if self.thresholds is not None:
            est = self.thresholds
            pos, neg = est.thresholds().tolist()
            out["thresholds"] = {
                "start": {"pos": est.start[0], "neg": est.start[1]},
                "estimate": {"pos": pos, "neg": neg, "ratio": pos / neg},
                "learnt": _learnt(self.cfg, est),
                "measured_ratio": est.measured_ratio,
                "per_pixel": est.pixel is not None,
            }
        if self.poses is not None:
            out["poses"] = {
                "rows": 1 if self.poses.shared else int(self.poses.used.sum()),
                "shared": self.poses.shared,
                "knots": self.cfg.refine_knots,
                "gate": self.gate,
                "gauge": self.poses.gauge,
                "corrections": "world-frame [rotation vector (rad), shift (world units)]",
            }
        return _finite(out)

    def corrections(self) -> np.ndarray | None:
        """(G, 6) float64 gauge-fixed pose corrections, or None without pose refinement."""
        if self.poses is None:
            return None
        with torch.no_grad():
            return self.poses.corrections().double().cpu().numpy()

    # -- checkpoints -------------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        return {
            "poses": None if self.poses is None else self.poses.state_dict(),
            "thresholds": None if self.thresholds is None else self.thresholds.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "pose_optimizer": None
            if self.pose_optimizer is None
            else self.pose_optimizer.state_dict(),
            "skipped_steps": self.skipped_steps,
            "sharing": self._sharing,  # a resume must still see the switch and forget
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if self.poses is not None:
            self.poses.load_state_dict(state["poses"])
        if self.thresholds is not None:
            self.thresholds.load_state_dict(state["thresholds"])
        self.optimizer.load_state_dict(state["optimizer"])
        if self.pose_optimizer is not None:
            self.pose_optimizer.load_state_dict(state["pose_optimizer"])
        self.skipped_steps = int(state.get("skipped_steps", 0))
        self._sharing = bool(state.get("sharing", False))


def measured_ratio(scene, cfg: TrainConfig) -> float | None:
    """The ratio C₊/C₋ counted over the scene's closed loop where `threshold_ratio` asks for
    it (loop; auto where the camera returns to its start pose), else None (learnt)."""
    if not cfg.estimate_threshold or cfg.threshold_ratio == "learn":
        return None
    try:
        loop = scene_loop_ratio(scene)
    except InputError:
        if cfg.threshold_ratio == "loop":
            raise
        return None
    return loop.ratio


def _learnt(cfg: TrainConfig, est: ThresholdEstimator) -> str:
    """What of the thresholds was learnt with the field (config.json's record)."""
    parts = [] if est.measured_ratio is not None else ["ratio"]
    parts += ["scale"] * cfg.threshold_free_scale + ["per-pixel factors"] * (est.pixel is not None)
    return " and ".join(parts) or "nothing (the ratio measured from the loop)"


def _finite(obj: Any) -> Any:
    """JSON-safe: non-finite floats become None (config.json must stay valid JSON)."""
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj
