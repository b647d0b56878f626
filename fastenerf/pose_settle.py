"""Long field windows once the poses settle (`--refine-settle-px`, #20).

A refined run's field learns from short event windows while the pose corrections still move:
long windows fit the given poses so fast that they explain the pose error away, and the poses
stop further from the truth even when their own gradient comes from short windows only
(benchmarks/RESULTS.md, the twenty-fourth session). Without pose error the long windows are
what a short run gains most from. So the field starts on win_max, and once the corrections'
turns moved less than refine_settle_px pixels over CHECK_EVERY of the budget, the window
sampler draws up to settle_win_max views; the corrections keep learning from windows up to
refine_win_max (`PoseCalibration.rays`).
"""

from __future__ import annotations

import torch

from .config import TrainConfig
from .sampling import WindowSampler

CHECK_EVERY = 0.05  # budget fraction between two looks at the corrections (one host read each)


class PoseSettle:
    """Watches a run's pose corrections and lengthens its windows once they settle.

    cfg: the resolved TrainConfig (refine_settle_px and settle_win_max set); windows: the run's
    WindowSampler, whose win_max this sets; fx: the focal length, pixels (a turn of θ radians
    moves the image by ~θ·fx pixels); start: the budget fraction from which to look (the pose
    lr's warm-up done: before it the corrections move little whatever the pose error).
    """

    def __init__(self, cfg: TrainConfig, windows: WindowSampler, fx: float, start: float):
        self.tol_px, self.long = float(cfg.refine_settle_px), int(cfg.settle_win_max)
        self.windows, self.fx, self.start = windows, float(fx), float(start)
        self.last: tuple[float, torch.Tensor] | None = None  # (progress, turns) of the last look
        self.moved_px: float | None = None  # RMS movement between the last two looks, pixels
        self.settled_at: float | None = None  # budget fraction where the windows lengthened

    def due(self, progress: float) -> bool:
        """Whether to `look` at `progress`: from `start`, once per CHECK_EVERY of the budget,
        until the windows lengthened."""
        if self.settled_at is not None or progress < self.start:
            return False
        # (a step-counted budget's fractions are sums of floats: 0.15 − 0.1 < 0.05)
        return self.last is None or progress - self.last[0] >= CHECK_EVERY - 1e-9

    def look(self, progress: float, turns: torch.Tensor) -> bool:
        """Where `due`: compare the corrections' `turns` ((R, 3) rotation vectors, radians, the
        used rows) with the last look's and lengthen the windows when their RMS movement is
        below the tolerance. Returns whether it lengthened them now."""
        now = turns.detach().double().cpu()
        last, self.last = self.last, (progress, now)
        if last is None:
            return False
        moved = (now - last[1]).norm(dim=-1)
        self.moved_px = float(moved.square().mean().sqrt()) * self.fx
        if self.moved_px >= self.tol_px:
            return False
        self.windows.set_win_max(self.long)
        self.settled_at = progress
        return True

    def stats(self) -> dict[str, float]:
        """field_win_max (views) and, after two looks, pose_settle_px (pixels)."""
        out = {"field_win_max": float(self.windows.win_max)}
        if self.moved_px is not None:
            out["pose_settle_px"] = self.moved_px
        return out

    def state_dict(self) -> dict:
        """What a resume needs to look where the whole run would (the window length itself is
        the sampler's state)."""
        last = (None, None) if self.last is None else self.last
        state = {"settled_at": self.settled_at, "moved_px": self.moved_px}
        return {**state, "last_progress": last[0], "last_turns": last[1]}

    def load_state_dict(self, state: dict | None) -> None:
        state = state or {}
        self.settled_at, self.moved_px = state.get("settled_at"), state.get("moved_px")
        turns = state.get("last_turns")
        self.last = None if turns is None else (float(state["last_progress"]), turns.cpu())
