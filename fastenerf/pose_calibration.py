"""The pose part of self-calibration (`--refine-poses`, #20): the `pose_refine.PoseRefiner`
a run's config asks for and how its corrections step.

They step with the lazy row Adam (`pose_refine.RowAdam`, refine_optimizer "row-adam", its
own optimiser) or as one group of `SelfCalibration`'s Adam ("adam"); their lr follows
`pose_lr`, the row Adam's significance gate `row_gate`, and refine_decay shrinks the rows a
batch saw after each step. Until refine_shared_until every pose shares one correction (the
rows' summed gradient); meanwhile the coarse-to-fine schedule weights the field's encoding.
Until the poses settle (or refine_diffuse_until) the colour may be held view-independent, and
every 1 % of the budget a row that ran past refine_reset_deg is put back (`pose_guard`).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from .coarse_to_fine import set_encoding_window
from .config import TrainConfig
from .errors import InputError
from .fields.base import Field
from .pose_guard import reset_runaways
from .pose_refine import PoseRefiner, RowAdam
from .pose_settle import PoseSettle
from .sampling import RayBatch, RaySampler

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
        start = pose_lr_start(cfg)
    r = (progress - start) / (1.0 - start)
    ramp = 1.0 if cfg.refine_warmup <= 0 else min(1.0, r / cfg.refine_warmup)
    return ramp * cfg.refine_lr * (cfg.refine_lr_final / cfg.refine_lr) ** r


def pose_lr_start(cfg: TrainConfig) -> float:
    """Where the per-pose schedule of `pose_lr` starts (budget fraction): refine_start, or the
    end of the shared phase (refine_shared_until) when that is later."""
    return max(cfg.refine_start, cfg.refine_shared_until)


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


class PoseCalibration:
    """The learnt pose corrections of one run (`refiner`) and their schedule and steps.

    cfg: the resolved TrainConfig (refine_poses on); sampler: the run's RaySampler (built
    with_poses); field: the field whose encoding the coarse-to-fine schedule weights;
    true_c2w: optional (G, 4, 4) exact grid poses, for the error stats; prior_turn_deg: the
    motion prior's mean turn of the given poses (degrees), or None, for the gate (`row_gate`).
    `optimizer` is the row Adam, or None where `adam_groups` hold the poses' group for the
    caller's Adam.
    """

    def __init__(
        self,
        cfg: TrainConfig,
        sampler: RaySampler,
        field: Field,
        true_c2w: torch.Tensor | None = None,
        prior_turn_deg: float | None = None,
    ):
        self.cfg, self.field, self.prior_turn_deg = cfg, field, prior_turn_deg
        row_adam = cfg.refine_optimizer == "row-adam"
        self.gate = row_gate(cfg, prior_turn_deg) if row_adam else 0.0
        self.decay = cfg.refine_defaults()[1]
        check_knots(cfg.refine_knots, len(sampler.grid_c2w))
        rows, w = int(used_rows(sampler).sum()), cfg.refine_settle_smooth
        if w > rows:  # odd and >= 5 is the config's own check
            why = f"{w} is longer than the {rows} grid poses it would smooth"
            raise InputError(f"train config: refine_settle_smooth {why}")
        self.refiner = PoseRefiner(
            sampler.grid_c2w,
            used_rows(sampler),
            pose_gauge(cfg),
            true_c2w,
            translation=cfg.refine_translation,
            shared=cfg.refine_shared,
            knots=cfg.refine_knots,
            knot_rows=cfg.refine_knot_rows,
        )
        betas = (cfg.refine_beta1, ADAM_BETAS[1])
        group = {"params": [self.refiner.delta], "lr": cfg.refine_lr, "name": "poses"}
        group["betas"] = betas
        self.optimizer: RowAdam | None = None
        self.adam_groups: list[dict] = []
        if row_adam:
            gate = {"gate": self.gate, "gate_beta": cfg.refine_gate_beta}
            self.optimizer = RowAdam([group], cfg.refine_lr, betas, ADAM_EPS, **gate)
        else:
            self.adam_groups.append(group)
        self.settle: PoseSettle | None = None  # lengthens the windows (refine_settle_px)
        if cfg.refine_settle_px is not None:
            s0 = pose_lr_start(cfg)  # looks start once the pose lr's ramp is done
            start = s0 + cfg.refine_warmup * (1.0 - s0)
            self.settle = PoseSettle(cfg, sampler.windows, sampler.rig.intrinsics.fx, start)
        self.seen: torch.Tensor | None = None  # (G,) bool rows the last batch saw
        # (2B,) bool rays of the last batch whose gradient reaches a pose (None: every ray)
        self.grad_rays: torch.Tensor | None = None
        self.c2f: float | None = None  # fraction of the coarse-to-fine schedule done
        self.sharing = False  # the poses share one correction now (refine_shared_until)
        self.lr = 0.0  # this step's lr, on the host (the device may hold a copy)
        self.frozen = False  # the poses settled and refine_freeze stopped their learning
        self.held = False  # a new field trains on the poses as they are (refine_restart)
        self.held_at: float | None = None  # the budget fraction of that restart
        self.view_held = False  # the colour ignores the view direction (refine_diffuse_until)
        self.resets: torch.Tensor | None = None  # rows put back (refine_reset_deg), on device
        self._guard_look = -1  # the budget percent last guarded

    @property
    def settled(self) -> bool:
        """Whether the poses have settled (`refine_settle_px`; False without the settle)."""
        return self.settle is not None and self.settle.settled_at is not None

    def hold(self, at: float, now: float | None = None) -> None:
        """A new field trains from training progress `at` on (refine_restart): the poses stay
        as they are until refine_resume of the budget left then is spent (to the end where it
        is 0). now: the progress at which this is said, if later (a resumed checkpoint's):
        past that point the poses learn already."""
        self.held_at = at
        self.held = now is None or not self._resumes(now)

    def _resumes(self, progress: float) -> bool:
        """Whether held poses learn again at training `progress` (refine_resume)."""
        r = self.cfg.refine_resume
        return r > 0 and progress >= self.held_at + r * (1.0 - self.held_at)

    def schedule(self, progress: float) -> bool:
        """The lr and the shared phase at training `progress` in [0, 1]; returns whether the
        optimiser's moments are stale now, where the shared phase ended or held poses resume
        (the caller then calls `forget_moments`). From the step after the poses settled,
        refine_freeze holds the lr at 0 (`frozen`), as a restart does (`hold`) until
        refine_resume; until they settle or refine_diffuse_until, the colour ignores the view
        direction (`view_held`)."""
        settled, resumed = self.settled, self.held and self._resumes(progress)
        self.held = self.held and not resumed
        self.frozen = (self.cfg.refine_freeze and settled) or self.held
        self.lr = 0.0 if self.frozen else pose_lr(self.cfg, progress)
        held = progress < self.cfg.refine_diffuse_until and not settled
        if held != self.view_held:
            self.field.color_net.hold_view(held)
            self.view_held = held
        was = self.sharing
        self.sharing = progress < self.cfg.refine_shared_until
        return (was and not self.sharing) or resumed

    def given_turn_deg(self) -> float:
        """How far off the given poses were, as a mean turn (degrees): the motion prior's
        (smooth_poses) where there is one, else the corrections' now (one host read)."""
        if self.prior_turn_deg is not None:
            return float(self.prior_turn_deg)
        with torch.no_grad():
            turns = self.refiner.corrections()[self.refiner.used, :3]
            return float(torch.rad2deg(turns.double().norm(dim=1)).mean())

    def window(self, progress: float) -> None:
        """The coarse-to-fine encoding window at training `progress` in [0, 1], and the event
        windows' length once the poses settle (`pose_settle`; one host read per look)."""
        c = self.cfg
        self.c2f = set_encoding_window(
            self.field, progress, c.refine_c2f_start, c.refine_c2f_end, c.refine_c2f_mode
        )
        if self.settle is not None and self.settle.due(progress):
            with torch.no_grad():
                turns = self.refiner.corrections()[self.refiner.used, :3]
            if self.settle.look(progress, turns) and c.refine_settle_smooth:
                self.refiner.smooth_turns(c.refine_settle_smooth)

    def guard(self, progress: float, opt: torch.optim.Optimizer) -> None:
        """Once every 1 % of the budget, put back the rows whose correction turned further
        than refine_reset_deg, and their state in the pose optimiser `opt` (`pose_guard`)."""
        look = int(progress * 100)
        if self.cfg.refine_reset_deg <= 0 or look == self._guard_look:
            return
        self._guard_look = look
        state = opt.state.get(self.refiner.delta, {})
        n = reset_runaways(self.refiner.delta, state, np.radians(self.cfg.refine_reset_deg))
        self.resets = n if self.resets is None else self.resets + n

    @torch.no_grad()
    def forget_moments(self, opt: torch.optim.Optimizer) -> None:
        """Zero the pose optimiser's (`opt`) moments and step counts in place (a captured
        step keeps its buffers) where the shared phase ends: they hold the summed gradient of
        every row, hundreds of times one row's, which would shrink each pose's own steps for
        as long as the second moment takes to forget it (~1/(1 − β2) visits)."""
        for v in opt.state.get(self.refiner.delta, {}).values():
            if torch.is_tensor(v):
                v.zero_()

    def rays(self, batch: RayBatch) -> tuple[torch.Tensor, torch.Tensor]:
        """rays_o, rays_d (2B, 3) of a batch through the corrected poses; keeps its rows."""
        if batch.pose_idx is None:
            raise ValueError("SelfCalibration: the sampler was built without with_poses")
        # the batch's own rays: what the fused path returns on uncorrected rows (δ = 0);
        # frozen, none carries a gradient, so the field skips its position gradient too
        with torch.set_grad_enabled(torch.is_grad_enabled() and not self.frozen):
            rays_o, rays_d, self.seen = self.refiner.rays_and_rows(
                batch.dirs, batch.pose_idx, batch.rays_d
            )
        if self.frozen:
            self.grad_rays = None
        if self.frozen or self.cfg.refine_win_max is None:
            return rays_o, rays_d
        return self._short_windows_only(batch.pose_idx, rays_o, rays_d)

    def _short_windows_only(
        self, pose_idx: torch.Tensor, rays_o: torch.Tensor, rays_d: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The rays of windows longer than refine_win_max views, detached: same values, no
        pose gradient; `seen` keeps only the rows a short window touched and `grad_rays` the
        short windows' rays, for the field to skip the others' gradient (no host read).
        pose_idx: (2B,) grid rows (t0 rows, then t1 rows); rays_o, rays_d: (2B, 3)."""
        b, n = pose_idx.shape[0] // 2, len(self.refiner.base) - 1  # the n + 1 grid rows
        views = pose_idx[b:] - pose_idx[:b]
        views = torch.where(views < 0, views + n, views)  # a loop's t0 row wraps to its end
        long = views > self.cfg.refine_win_max
        long = long.repeat(2)[:, None]
        self.grad_rays = ~long[:, 0]
        short = torch.zeros(len(self.refiner.base), dtype=torch.int32, device=pose_idx.device)
        short.scatter_add_(0, pose_idx, (~long[:, 0]).to(torch.int32))
        self.seen = self.refiner.param_rows(short > 0)
        return torch.where(long, rays_o.detach(), rays_o), torch.where(
            long, rays_d.detach(), rays_d
        )

    def share_gradient(self) -> None:
        """In the shared phase, the rows' summed gradient for every row (before either
        optimiser steps them)."""
        if self.sharing and self.refiner.delta.grad is not None:
            self.seen = self.refiner.share_gradient()

    def step(self, found_inf: torch.Tensor | None) -> None:
        """The row Adam's step, or refine_decay alone, after the caller's Adam stepped;
        found_inf: the device-paced step's 0-dim flag (non-zero: nothing moves), or None."""
        if self._row_adam_steps():  # the row Adam decays the rows it steps, in its launch
            self.optimizer.step(self.seen, found_inf=found_inf, decay=self.decay)
        elif self.decay > 0:  # plain Adam, the pose lr still 0, or no pose gradient
            self._decay(found_inf)

    def _row_adam_steps(self) -> bool:
        """Whether the row Adam steps the poses now (lr > 0 and a gradient); it then also
        applies refine_decay (`RowAdam.step`'s decay, the same ops as `_decay`)."""
        opt = self.optimizer
        return opt is not None and self.lr > 0 and self.refiner.delta.grad is not None

    @torch.no_grad()
    def _decay(self, found_inf: torch.Tensor | None) -> None:
        """Shrink the corrections of the rows this batch saw by lr x refine_decay (decoupled
        from Adam: its normalised step would scale a prior's pull up to the lr), after the
        optimiser's step; skipped with it (found_inf). Where the row Adam steps the poses it
        does this itself (`RowAdam.step(decay=...)`); this is for the other cases."""
        lr = self.lr
        if lr * self.decay == 0:
            return  # a factor of exactly 1: nothing changes
        seen = self.seen
        if found_inf is not None:
            seen = seen & found_inf.to(seen.device).eq(0)
        rate = min(1.0, lr * self.decay)
        self.refiner.delta.mul_(1.0 - rate * seen[:, None].to(self.refiner.delta.dtype))

    def stats(self, on_device: bool = False) -> dict[str, Any]:
        """The refiner's stats (`PoseRefiner.stats`) and c2f, the schedule's fraction done."""
        out: dict[str, Any] = self.refiner.stats(on_device)
        out["c2f"] = 1.0 if self.c2f is None else self.c2f
        if self.settle is not None:
            out.update(self.settle.stats())
        if self.cfg.refine_freeze or self.cfg.refine_restart:
            out["poses_frozen"] = float(self.frozen)
        if self.cfg.refine_diffuse_until > 0:
            out["view_held"] = float(self.view_held)
        if self.cfg.refine_reset_deg > 0:
            n = self.resets
            if n is None:
                n = torch.zeros((), device=self.refiner.delta.device)
            out["pose_rows_reset"] = n.float() if on_device else float(n)
        return out

    def report(self) -> dict[str, Any]:
        """What config.json records of the corrections."""
        return {
            "rows": 1 if self.refiner.shared else int(self.refiner.used.sum()),
            "shared": self.refiner.shared,
            "knots": self.cfg.refine_knots,
            "knot_rows": self.cfg.refine_knot_rows,
            "gate": self.gate,
            "gauge": self.refiner.gauge,
            "corrections": "world-frame [rotation vector (rad), shift (world units)]",
            **({} if self.settle is None else {"settled_at": self.settle.settled_at}),
            "frozen": self.frozen,
            **({} if self.resets is None else {"rows_reset": int(self.resets)}),
        }
