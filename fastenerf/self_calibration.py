"""Self-calibration: the training poses and contrast thresholds learnt with the field (#20).

`SelfCalibration` owns the parts that are switched on (`pose_calibration.PoseCalibration`,
`threshold.ThresholdEstimator`) and their own Adam (one group each, own learning rates;
the poses' row Adam is the pose part's). The trainer asks it, per step, for
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

from .config import TrainConfig
from .data.loop_ratio import scene_loop_ratio
from .errors import InputError
from .fields.base import Field
from .optim import lr_as_floats, lr_as_tensors, set_group_lr
from .pose_calibration import ADAM_BETAS, ADAM_EPS, PoseCalibration
from .pose_refine import PoseRefiner, RowAdam
from .sampling import RayBatch, RaySampler
from .threshold import ThresholdEstimator


class SelfCalibration:
    """The learnt calibration of one training run (see the module docstring).

    cfg: the resolved TrainConfig; sampler: the run's RaySampler (built with_poses /
    with_parts as cfg asks); thresholds: scene.json's (C_pos, C_neg); field: the field whose
    encoding the coarse-to-fine schedule weights; true_c2w: optional (G, 4, 4) exact grid
    poses (a pose-error study's unperturbed rig), for the error stats; ratio: a measured
    threshold ratio, or None; prior_turn_deg: the motion prior's mean turn of the given poses
    (degrees), or None without the prior, for the gate (`pose_calibration.row_gate`).
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
        self.cfg = cfg
        self.pose_cal: PoseCalibration | None = None
        self.thresholds: ThresholdEstimator | None = None
        groups = []
        if cfg.refine_poses:
            self.pose_cal = PoseCalibration(cfg, sampler, field, true_c2w, prior_turn_deg)
            groups += self.pose_cal.adam_groups
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

    @property
    def poses(self) -> PoseRefiner | None:
        """The learnt pose corrections, or None without refine_poses."""
        return None if self.pose_cal is None else self.pose_cal.refiner

    @property
    def pose_optimizer(self) -> RowAdam | None:
        """The poses' row Adam (refine_optimizer "row-adam"), else None."""
        return None if self.pose_cal is None else self.pose_cal.optimizer

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
        is 0 before refine_start; the row Adam is then not launched at all), whether they
        share one correction (refine_shared_until) and whether they are frozen (refine_freeze:
        the rays then carry no gradient)."""
        pc = self.pose_cal
        if pc is None:
            return (False, False, False)
        return (pc.lr > 0, pc.sharing, pc.frozen)

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
        pc = self.pose_cal
        if pc is not None and pc.schedule(progress):
            pc.forget_moments(pc.optimizer or self.optimizer)
        for g in self.param_groups():
            lr = pc.lr if g["name"] == "poses" else self.cfg.threshold_lr * field_lr_scale
            set_group_lr(g, lr)
        if pc is not None:
            pc.window(progress)
            pc.guard(progress, pc.optimizer or self.optimizer)

    def settled(self) -> bool:
        """Whether the poses have settled (`refine_settle_px`; False without refinement or
        without the settle)."""
        return self.pose_cal is not None and self.pose_cal.settled

    def given_turn_deg(self) -> float:
        """How far off the given poses were (mean turn, degrees; `PoseCalibration`); 0
        without pose refinement."""
        return 0.0 if self.pose_cal is None else self.pose_cal.given_turn_deg()

    def use_field(self, field: Field, at: float, now: float | None = None) -> None:
        """Weight and hold `field` from training progress `at` on, the poses frozen as they
        are (a new field: `field_restart`; its young gradient would move them) until
        refine_resume (`PoseCalibration.hold`; now: a resumed run's progress)."""
        if self.pose_cal is not None:
            self.pose_cal.field = field
            self.pose_cal.hold(at, now)

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
        if self.pose_cal is not None:
            rays_o, rays_d = self.pose_cal.rays(batch)
        if self.thresholds is not None:
            if batch.parts is None:
                raise ValueError("SelfCalibration: the sampler was built without with_parts")
            target = self.thresholds.target(batch.parts, batch.pix)
            reg = self.thresholds.regulariser(batch.pix)
        return rays_o, rays_d, target, reg

    @property
    def grad_rays(self) -> torch.Tensor | None:
        """(2B,) bool, the last `apply`'s rays whose gradient reaches the calibration (the
        field may skip the others'); None: every ray's, or none learnt from the rays."""
        return None if self.pose_cal is None else self.pose_cal.grad_rays

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
        if self.pose_cal is not None:
            self.pose_cal.share_gradient()
        if not self._placeholder:  # whose unfused step a CUDA graph could not capture
            self.optimizer.step()
        if self.pose_cal is not None:
            self.pose_cal.step(found_inf)
        if self.thresholds is not None:
            self.thresholds.project()
        return True

    # -- reporting ---------------------------------------------------------------------------

    def stats(self, on_device: bool = False) -> dict[str, Any]:
        """Step stats (metrics.jsonl, the viewer): the pose and threshold estimates.
        on_device: the estimates as 0-dim device tensors, read nowhere here: a device-paced
        step's pending stats, copied to the host at its flush (a read here would wait for
        every queued step, off the training clock)."""
        out: dict[str, Any] = {}
        if self.pose_cal is not None:
            out.update(self.pose_cal.stats(on_device))
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
        if self.pose_cal is not None:
            out["poses"] = self.pose_cal.report()
        return _finite(out)

    def corrections(self) -> np.ndarray | None:
        """(G, 6) float64 gauge-fixed pose corrections, or None without pose refinement."""
        if self.poses is None:
            return None
        with torch.no_grad():
            return self.poses.corrections().double().cpu().numpy()

    # -- checkpoints -------------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        pc = self.pose_cal
        return {
            "poses": None if self.poses is None else self.poses.state_dict(),
            "thresholds": None if self.thresholds is None else self.thresholds.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "pose_optimizer": None
            if self.pose_optimizer is None
            else self.pose_optimizer.state_dict(),
            "skipped_steps": self.skipped_steps,
            # a resume must still see the switch and forget
            "sharing": pc is not None and pc.sharing,
            "settle": None if pc is None or pc.settle is None else pc.settle.state_dict(),
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
        if self.pose_cal is not None:
            self.pose_cal.sharing = bool(state.get("sharing", False))
            if self.pose_cal.settle is not None:
                self.pose_cal.settle.load_state_dict(state.get("settle"))


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
