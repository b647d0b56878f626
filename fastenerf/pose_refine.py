"""Learnable corrections of the training poses on the window grid (issue #20).

Every window starts and ends on a grid pose (`sampling.WindowSampler`), so a ray's camera is
one row of the sampler's (n + 1)-pose table and a correction per row is a correction of
every pose training sees. Row i learns (ω_i, u_i) in its CAMERA's frame (radians, world
units), applied as the world-frame correction δ_i = (R_i ω_i, R_i u_i) = (w_i, v_i):

    R'_i = Exp(w_i) · R_i        a turn about the camera centre
    t'_i = t_i + v_i             a shift of the centre

Camera-frame parameters let Adam scale each camera axis on its own: the roll about the
optical axis gets far smaller gradients than pan and tilt, and in world coordinates it would
share (and lose) their step sizes. The gauge is fixed in the world frame, where a rigid
motion of the whole scene is (to first order) the same δ for every row: "mean" makes the
world-frame corrections zero-mean, which removes exactly that motion; "first" keeps the
first row fixed instead (the scene keeps that camera's frame, errors included); "none"
leaves the scene free to drift. Rows no window uses (a loop's last row, the twin of its
first) keep a zero correction and are left out of the gauge. That motion is a gauge only
when the centres move too: learning turns alone, with the centres held at the given ones, a
turn shared by every camera about its own centre is no rigid motion of the scene, and
"mean" would keep the mean of the pose errors for good (`pose_calibration.pose_gauge`:
the default "auto" then takes "none").

`shared=True` learns ONE camera-frame row (1, 6) for every pose, a camera mis-mounted on its
rig: R'_i = R_i · Exp(ω) = Exp(R_i ω) · R_i, the same maths with every row's δ tied to the
one parameter (broadcast to the G rows; its gradient sums theirs). Every ray's parameter row
is 0 (`rays_and_rows` reports one row seen); the grid rows still give each ray its pose. It
has no gauge: the same turn in every camera's own frame is no rigid motion of the world (a
mean gauge would remove all of it), so `shared` needs gauge "none".

`knots=K` learns K rows spread evenly along the grid instead of one per grid pose; a grid
row's correction is the linear interpolation of its two knots (`knot_matrix`, periodic on a
loop), δ = B · knots. An error that is smooth along the path (what a motion prior leaves of
per-pose jitter, a slow drift) is then learnt from the pooled gradients of the ~G/K rows
about each knot, and a batch's few windows reach a knot every few steps instead of a row
every G/windows steps. The lazy Adam steps the knots a seen row interpolates from.
"""

from __future__ import annotations

import functools

import torch
from torch import nn

from .render import generate_rays
from .se3 import mean_world_rotation, relative_angle_deg, so3_exp, so3_log

GAUGES = ("mean", "first", "none")


@functools.cache
def _pose_rays():
    """The Warp module `kernels.pose_rays`, or None where Warp cannot be loaded."""
    try:
        from .kernels import pose_rays
    except ImportError:  # pragma: no cover - Warp is a dependency; the torch path remains
        return None
    return pose_rays


def knot_matrix(rows: int, knots: int, loop: bool) -> torch.Tensor:
    """(rows, knots) float32 linear interpolation weights of `knots` values spread evenly over
    `rows` grid rows: each row has weights on two neighbouring knots summing to 1, and a row on
    a knot has weight 1 there. loop: the last row is the first's twin (the path closes), so
    knot K-1 interpolates towards knot 0 and the last row equals the first; else the first
    and last rows sit on the first and last knots."""
    if knots < 2 or knots > rows - int(loop):
        raise ValueError(f"knot_matrix: {knots} knots need 2 to {rows - int(loop)} for {rows} rows")
    span = (rows - 1) / (knots if loop else knots - 1)  # rows per knot interval
    x = torch.arange(rows, dtype=torch.float64) / span
    j = x.floor().clamp(max=knots - 1 if loop else knots - 2)
    f = (x - j).float()
    j = j.long()
    B = torch.zeros(rows, knots)
    B[torch.arange(rows), j % knots] += 1.0 - f
    B[torch.arange(rows), (j + 1) % knots] += f
    return B


class PoseRefiner(nn.Module):
    """Corrected camera-to-world poses and the rays through them.

    grid_c2w: (G, 4, 4) the training poses of the grid rows (OpenCV camera-to-world);
    used: (G,) bool, the rows windows use; gauge: one of GAUGES; true_c2w: optional (G, 4, 4)
    exact poses (a study's unperturbed rig), only for the error stats; translation: False
    learns rotations only (the centres stay); fused: `rays` runs the Warp kernels
    (`kernels.pose_rays`) where Warp loads and delta is float32, else the torch reference.
    shared: one row for every pose (module docstring; needs gauge "none"). knots: K >= 2
    learnt rows interpolated along the grid (module docstring; 0: one per row); loop: whether
    the grid's last row is its first's twin (None: an unused last row equal to the first).
    knot_rows: with knots, each grid row also learns its own correction, added to the knots'.
    Parameter `delta`: (G, 6) camera-frame [ω (rad), u (world units)] before the gauge fix;
    (1, 6) when shared, (K, 6) with knots, (G + K, 6) with knots and knot_rows (each grid
    row's own correction on top of the knots': the knots pool a smooth error's gradient along
    the path, the rows take what is each view's own).
    """

    def __init__(
        self,
        grid_c2w: torch.Tensor,
        used: torch.Tensor,
        gauge: str = "mean",
        true_c2w: torch.Tensor | None = None,
        translation: bool = True,
        fused: bool = True,
        shared: bool = False,
        knots: int = 0,
        loop: bool | None = None,
        knot_rows: bool = False,
    ):
        super().__init__()
        self.fused, self.shared = fused, shared
        if gauge not in GAUGES:
            raise ValueError(f"PoseRefiner: gauge must be one of {GAUGES}, got {gauge!r}")
        if shared and gauge != "none":
            raise ValueError(f"PoseRefiner: a shared correction has no gauge, got {gauge!r}")
        if not bool(used.any()):
            raise ValueError("PoseRefiner: no grid row is used")
        if shared and knots:
            raise ValueError("PoseRefiner: a shared correction has no knots")
        if knot_rows and not knots:
            raise ValueError("PoseRefiner: knot_rows adds rows to knots: give knots")
        self.gauge = gauge
        self.register_buffer("base", grid_c2w.detach().float().clone())
        mask = used.to(self.base.device, torch.float32)
        if shared:  # every row is the one camera: its loop twin too
            mask = torch.ones_like(mask)
        if gauge == "first":
            mask[int(used.nonzero()[0, 0])] = 0.0
        self.register_buffer("used", used.to(self.base.device, torch.bool))
        cols = torch.tensor([1.0] * 3 + [float(translation)] * 3, device=mask.device)
        self.register_buffer("mask", mask[:, None] * cols)
        self.register_buffer("true_c2w", None if true_c2w is None else true_c2w.float().clone())
        if loop is None:
            twin = torch.allclose(grid_c2w[0].float(), grid_c2w[-1].float(), atol=1e-5)
            loop = twin and not bool(used[-1])
        self.loop = bool(loop)
        B = knot_matrix(len(grid_c2w), knots, loop).to(mask.device) if knots else None
        self.register_buffer("interp", B)
        rows = 1 if shared else knots or len(grid_c2w)
        self.knot_rows = bool(knot_rows)
        rows += len(grid_c2w) if knot_rows else 0  # the grid's own rows first, then the knots
        self.delta = nn.Parameter(torch.zeros(rows, 6, device=self.base.device))

    def row_delta(self) -> torch.Tensor:
        """Every grid row's camera-frame correction before the gauge fix, (G, 6): `delta`
        itself, the shared row broadcast, the knots interpolated, or (knot_rows) each row's
        own plus the knots interpolated."""
        if self.knot_rows:
            G = len(self.base)
            return self.delta[:G] + self.interp @ self.delta[G:]
        if self.interp is not None:
            return self.interp @ self.delta
        return self.delta.expand(len(self.base), 6)

    def corrections(self) -> torch.Tensor:
        """The gauge-fixed world-frame corrections δ = [w, v], (G, 6): zero on unused rows (and
        on a fixed first row); shared: the one row in every camera's frame."""
        R = self.base[:, :3, :3]
        d = torch.einsum("gij,gkj->gki", R, (self.row_delta() * self.mask).view(-1, 2, 3))
        d = d.reshape(-1, 6)
        if self.gauge == "mean":
            rows = self.mask[:, :1]
            d = d - rows * (d.sum(0, keepdim=True) / rows.sum())
        return d

    def rotations(self, d: torch.Tensor | None = None) -> torch.Tensor:
        """Corrected rotations R' = Exp(ω) R, (G, 3, 3)."""
        d = self.corrections() if d is None else d
        return so3_exp(d[:, :3]) @ self.base[:, :3, :3]

    @torch.no_grad()
    def smooth_turns(self, window: int, order: int = 1) -> None:
        """Fit the corrected rotations to a smooth path along the grid (`smooth_poses` over
        `window` poses, degree `order`) and set each row's turn to reach it (in place, one
        host round trip; shifts kept). A correction per row only (no knots, not shared): the
        noise each row's own estimate carries goes, a correction smooth along the path stays.
        With the mean gauge the fitted path is reached up to the turn every row shares."""
        from .pose_smoothing import smooth_poses

        if self.interp is not None or self.shared:
            raise ValueError("PoseRefiner.smooth_turns: needs a correction per row")
        base = self.base.double()
        c2w = base.clone()
        c2w[:, :3, :3] = self.rotations().double()
        smooth = torch.from_numpy(smooth_poses(c2w.cpu().numpy(), window, self.loop, order))
        R = base[:, :3, :3]
        w = so3_log(smooth[:, :3, :3].to(R) @ R.transpose(-1, -2))  # world-frame turns
        omega = torch.einsum("gji,gj->gi", R, w)  # Rᵀ w: each camera's own frame
        rows = self.mask[:, :1] > 0
        self.delta[:, :3].copy_(torch.where(rows, omega.to(self.delta), self.delta[:, :3]))

    def c2w(self) -> torch.Tensor:
        """Corrected camera-to-world poses, (G, 4, 4) float32."""
        d = self.corrections()
        out = self.base.clone()
        out[:, :3, :3] = self.rotations(d)
        out[:, :3, 3] = self.base[:, :3, 3] + d[:, 3:]
        return out

    def rays(
        self,
        dirs: torch.Tensor,
        pose_idx: torch.Tensor,
        rays_d: torch.Tensor | None = None,
        *,
        fused: bool | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Rays through the corrected poses, differentiable w.r.t. the corrections.

        dirs: (B, 3) camera-frame directions of B pixels; pose_idx: (kB,) int64 grid row of
        each ray, the B pixels seen from k poses in turn (k = 2: at t0, then at t1).
        rays_d: optional (kB, 3) the uncorrected directions (the sampler's batch.rays_d), which
        the fused path returns as they are on rows without a rotation correction (computed
        here when not given); fused: the Warp kernels (`kernels.pose_rays`, a few launches)
        or the torch reference (None: `self.fused`).
        Returns rays_o (kB, 3) world units and rays_d (kB, 3) unit; bit-identical to
        `render.generate_rays` on the uncorrected rows while δ = 0.
        """
        return self.rays_and_rows(dirs, pose_idx, rays_d, fused=fused)[:2]

    def rays_and_rows(
        self,
        dirs: torch.Tensor,
        pose_idx: torch.Tensor,
        rays_d: torch.Tensor | None = None,
        *,
        fused: bool | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """`rays`, and the bool rows of `delta` pose_idx holds (what the lazy row Adam steps):
        (G,), or (1,) when shared."""
        kernels = _pose_rays() if (self.fused if fused is None else fused) else None
        if kernels is not None and self.delta.dtype == torch.float32:
            if rays_d is None:
                k = pose_idx.shape[0] // max(dirs.shape[0], 1)
                rays_d = generate_rays(dirs.float().repeat(k, 1), self.base[pose_idx])[1]
            centre = self.gauge == "mean"
            o, d, seen = kernels.pose_rays(
                self.row_delta(), self.base, self.mask, dirs, pose_idx, rays_d, centre
            )
            return o, d, self.param_rows(seen)
        d = self.corrections()
        # index_select: its backward adds into the few rows a batch sees by atomics; advanced
        # indexing's (a sorted index_put) walks each row's thousands of duplicates serially
        R = self.rotations(d).index_select(0, pose_idx)
        o = (self.base[:, :3, 3] + d[:, 3:]).index_select(0, pose_idx)
        k = pose_idx.shape[0] // dirs.shape[0]
        rd = torch.einsum("nij,nj->ni", R, dirs.to(R.dtype).repeat(k, 1))
        seen = torch.zeros(len(self.base), dtype=torch.bool, device=o.device)
        seen[pose_idx] = True
        return o.contiguous(), nn.functional.normalize(rd, dim=-1), self.param_rows(seen)

    @torch.no_grad()
    def share_gradient(self) -> torch.Tensor:
        """Every used row's gradient becomes the rows' sum, the gradient one correction shared
        by every camera would get (`shared`), so rows that start equal move as one; returns
        the rows to step, (G,) bool: every used one. In place, no host read."""
        g = self.delta.grad
        g.copy_(g.sum(0, keepdim=True) * self.mask)
        return self.used

    def param_rows(self, seen: torch.Tensor) -> torch.Tensor:
        """The grid rows seen (G,) as rows of `delta`: shared, (1,) whether any was; with
        knots, (K,) the knots a seen row takes a weight from; with knot_rows, (G + K,) the rows
        seen and then those knots (on the device, no host read)."""
        if self.interp is not None:
            knots = (seen.to(self.interp.dtype) @ self.interp) > 0
            return torch.cat([seen, knots]) if self.knot_rows else knots
        return seen.any(0, keepdim=True) if self.shared else seen

    @torch.no_grad()
    def stats(self, on_device: bool = False) -> dict[str, float | torch.Tensor]:
        """Mean / max size of the corrections on the used rows (degrees, world units) and,
        with true poses, the corrected poses' remaining rotation error and centre offset, the
        angle of the world rotation they share against the truth (pose_gauge_deg,
        `se3.mean_world_rotation`), the error left once it is taken out
        (pose_error_aligned_deg) and the error's pose-to-pose part (pose_jitter_deg).
        on_device: the values as 0-dim device tensors, no host read (a device-paced step's
        stats, copied to the host with the rest at its flush)."""
        # masked reductions over every row, not boolean indexing: one host read, at the end
        d, used = self.corrections().double(), self.used
        n = used.sum()

        def mean(v):
            return torch.where(used, v, 0.0).sum() / n

        def vmax(v):
            return torch.where(used, v, 0.0).max()  # sizes and errors are >= 0

        rot = d[:, :3].norm(dim=-1).rad2deg()
        vals = {
            "pose_correction_deg": mean(rot),
            "pose_correction_max_deg": vmax(rot),
            "pose_shift": mean(d[:, 3:].norm(dim=-1)),
        }
        if self.true_c2w is not None:
            true = self.true_c2w.double()
            R = so3_exp(d[:, :3]) @ self.base[:, :3, :3].double()
            err = relative_angle_deg(R, true[:, :3, :3])
            centre = self.base[:, :3, 3].double() + d[:, 3:]
            vals["pose_error_deg"] = mean(err)
            vals["pose_error_max_deg"] = vmax(err)
            vals["pose_centre_error"] = mean((centre - true[:, :3, 3]).norm(dim=-1))
            W = mean_world_rotation(R, true[:, :3, :3], used.double())
            vals["pose_gauge_deg"] = relative_angle_deg(
                W, torch.eye(3, dtype=W.dtype, device=W.device)
            )
            # W itself (radians, a rotation vector), so a study can score its test views
            # turned by it (benchmarks/study_report.py, BARF's aligned protocol)
            for axis, w in zip("xyz", so3_log(W).unbind(), strict=True):
                vals[f"pose_gauge_w{axis}"] = w
            vals["pose_error_aligned_deg"] = mean(relative_angle_deg(R, W @ true[:, :3, :3]))
            vals["pose_jitter_deg"] = pose_jitter_deg(R, true[:, :3, :3], used)
        return _stacked(vals, on_device)


def pose_jitter_deg(R: torch.Tensor, true_R: torch.Tensor, used: torch.Tensor) -> torch.Tensor:
    """The part of the rotation error that changes from one grid pose to the next, degrees
    (0-dim): the mean angle between neighbouring used rows' world-frame errors E_i = R_i true_iᵀ,
    over √2. R, true_R: (G, 3, 3) in grid (time) order; used: (G,) bool.

    Why: an event window compares two nearby poses, so an error that is each pose's own
    (independent from one pose to the next) reads as motion that did not happen, while one
    smooth along the path moves both ends alike. For errors independent per pose this is
    about the mean error itself (a difference of two has √2 its size); for one smooth along
    the path it is ~0. Masked reductions, no host read (`stats(on_device=True)`)."""
    E = R @ true_R.transpose(-1, -2)
    pair = used[1:] & used[:-1]
    step = relative_angle_deg(E[1:], E[:-1])
    n = pair.sum().clamp(min=1)
    return torch.where(pair, step, 0.0).sum() / n / 2**0.5


def _stacked(vals: dict[str, torch.Tensor], on_device: bool) -> dict[str, float | torch.Tensor]:
    """0-dim tensors as floats (one host read) or, on_device, as float32 device tensors."""
    keys = list(vals)
    row = torch.stack([vals[k] for k in keys])
    return dict(zip(keys, row.float().unbind() if on_device else row.tolist(), strict=True))


class RowAdam(torch.optim.Optimizer):
    """Lazy Adam over the rows of (G, k) parameters: a row's moments, its step count (bias
    correction) and its update change only on steps whose batch saw that row (`step(rows)`).

    Why: a batch sees a few of the grid's rows; plain Adam keeps moving every other row on
    its momentum (about ten steps' worth after each visit, each normalised to the lr), so the
    noise of one visit becomes a full-size step of a pose nothing looked at; and with a gauge
    fix every row gets a tiny gradient (the mean's) that Adam scales up to the lr.

    gate > 0, a significance gate: Adam's m̂/√v̂ is about ±1 on a row's first visits and
    √((1 − β1)/(1 + β1)) on noise after, so a row whose true correction is zero still walks by
    a fraction of the lr per visit. Each component's step is scaled by min(1, max(0, z/gate −
    1)), z = |ḡ| / √(ŝ c): the mean gradient in standard errors of a zero-mean one, ḡ and ŝ
    the bias-corrected gate_beta-averages of the gradient and its square (state "gate_m",
    "gate_sq"), c = (1 − β)(1 + βᵗ) / ((1 + β)(1 − βᵗ)) the variance of such an average of t
    unit draws. A consistent gradient opens it within a few visits (β 0.9: z = 1/√c = 1.0,
    1.4, 1.7, 2.0 at t = 1..4); a longer average (β nearer 1) also finds a weak steady pull,
    z ≈ SNR·√((1 + β)/(1 − β)) per visit.
    """

    def __init__(
        self,
        params,
        lr: float,
        betas=(0.9, 0.999),
        eps: float = 1e-12,
        fused: bool = True,
        gate: float = 0.0,
        gate_beta: float = 0.9,
    ):
        if gate < 0 or not 0 <= gate_beta < 1:
            why = f"gate must be >= 0 and gate_beta in [0, 1), got {gate} and {gate_beta}"
            raise ValueError(f"RowAdam: {why}")
        super().__init__(params, {"lr": lr, "betas": tuple(betas), "eps": eps})
        self.fused = fused  # one Warp launch per float32 parameter (`kernels.pose_rays`)
        self.gate, self.gate_beta = float(gate), float(gate_beta)

    def lr_as_tensors(self, device: torch.device) -> None:
        """Each group's lr a (1,) float32 tensor on `device` that the step kernel reads: a
        captured step replays the value `optim.set_group_lr` fills in before it (undo:
        `optim.lr_as_floats`)."""
        for g in self.param_groups:
            g["lr"] = torch.full((1,), float(g["lr"]), dtype=torch.float32, device=device)

    @torch.no_grad()
    def step(
        self,
        rows: torch.Tensor | None = None,
        closure=None,
        found_inf=None,
        decay: float = 0.0,
    ):  # noqa: D102
        """A group's lr is a float or a 1-element float32 tensor on the parameters' device
        (`lr_as_tensors`: what a captured step reads). rows: (G,) bool, the rows to step (None:
        every row with a gradient); found_inf:
        optional 0-dim device flag (non-zero: step no row, as torch's fused Adam skips);
        decay: decoupled decay (AdamW's, after the Adam update): each row stepped is then
        multiplied by 1 − min(1, lr · decay); 0: none. A parameter without a gradient is
        skipped, decay included. The gate (the class docstring) is the constructor's.

        Nothing waits for the device: the fused kernel reads the flags there, and the torch
        reference computes every row and keeps the unseen ones by a select (no boolean
        indexing; the rows are few, the arithmetic is cheap).
        """
        if decay < 0:
            raise ValueError(f"RowAdam: decay must be >= 0, got {decay}")
        kernels = _pose_rays() if self.fused else None
        for group in self.param_groups:
            for p in group["params"]:
                if p.grad is None:
                    continue
                st = self.state[p]
                if not st:
                    st["exp_avg"] = torch.zeros_like(p)
                    st["exp_avg_sq"] = torch.zeros_like(p)
                    st["row_steps"] = torch.zeros(p.shape[0], 1, device=p.device)
                for key in ("gate_m", "gate_sq") if self.gate > 0 else ():
                    if key not in st:
                        st[key] = torch.zeros_like(p)
                gate = (self.gate, self.gate_beta)
                if kernels is not None and _fusable(p, st):
                    lr, betas, eps = group["lr"], group["betas"], group["eps"]
                    kernels.row_adam(p, p.grad, st, rows, found_inf, lr, betas, eps, decay, *gate)
                else:
                    self._step_torch(p, st, group, rows, found_inf, decay, gate)
        return None

    @staticmethod
    def _step_torch(
        p, st: dict, group: dict, rows, found_inf, decay: float = 0.0, gate=(0.0, 0.9)
    ) -> None:
        """The reference step of one parameter (any dtype, any device)."""
        b1, b2 = group["betas"]
        seen = p.grad.ne(0).any(-1) if rows is None else rows.to(p.device)
        if found_inf is not None:
            seen = seen & found_inf.to(p.device).eq(0)
        s = seen[:, None]
        g = p.grad
        m = torch.where(s, st["exp_avg"] * b1 + g * (1 - b1), st["exp_avg"])
        v = torch.where(s, st["exp_avg_sq"] * b2 + g * g * (1 - b2), st["exp_avg_sq"])
        t = st["row_steps"] + s.to(st["row_steps"].dtype)
        st["exp_avg"].copy_(m)
        st["exp_avg_sq"].copy_(v)
        st["row_steps"].copy_(t)
        tc = t.clamp_min(1.0)  # unseen rows that never stepped: kept by the select
        m_hat, v_hat = m / (1 - b1**tc), v / (1 - b2**tc)
        lr = group["lr"]
        lr = lr.to(p.device, p.dtype).reshape(()) if torch.is_tensor(lr) else lr
        update = lr * m_hat / (v_hat.sqrt() + group["eps"])
        if gate[0] > 0:
            update = update * _gate_factor(st, g, s, tc, *gate)
        p.sub_(torch.where(s, update, torch.zeros_like(update)))
        if decay > 0:  # the ops `PoseCalibration._decay` ran after the step, in order
            rate = (lr * decay).clamp(max=1.0) if torch.is_tensor(lr) else min(1.0, lr * decay)
            p.mul_(1.0 - rate * s.to(p.dtype))


def _gate_factor(st: dict, g, seen, t, gate: float, b: float) -> torch.Tensor:
    """`RowAdam`'s significance gate in [0, 1] (updates st["gate_m"], st["gate_sq"] on the rows
    seen); t: (G, 1) the rows' visits."""
    m = torch.where(seen, st["gate_m"] * b + g * (1 - b), st["gate_m"])
    sq = torch.where(seen, st["gate_sq"] * b + g * g * (1 - b), st["gate_sq"])
    st["gate_m"].copy_(m)
    st["gate_sq"].copy_(sq)
    bc = 1 - b**t
    var = (sq / bc) * ((1 - b) * (1 + b**t) / ((1 + b) * bc))
    z = (m / bc).abs() / var.clamp_min(torch.finfo(var.dtype).tiny).sqrt()
    return torch.where(var > 0, (z / gate - 1).clamp(0.0, 1.0), torch.zeros_like(z))


def _fusable(p: torch.Tensor, st: dict) -> bool:
    """The kernel's case: a (G, k) float32 parameter, gradient and state, contiguous."""
    ts = (p, p.grad, *(v for v in st.values() if torch.is_tensor(v)))
    return p.ndim == 2 and all(t.dtype == torch.float32 and t.is_contiguous() for t in ts)
