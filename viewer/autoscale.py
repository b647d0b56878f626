"""Resolution scale that holds a frame rate while the camera moves and refines when still."""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass
class AutoScale:
    """Chooses the render resolution scale (fraction of the viewport's side) per frame.

    A frame's cost is about proportional to its pixel count (scale²), so from a frame that
    took `t` seconds at scale `s` the scale that fits the budget is `s * sqrt(budget / t)`.
    `moving_scale` follows that estimate (damped in log space against oscillation, kept in
    [min_scale, max_scale]) and is used while the camera moves; when still the scale is
    `max_scale` (the full-quality refine), and `moving_scale` is remembered for the next move.
    """

    target_fps: float = 30.0
    min_scale: float = 0.125
    max_scale: float = 1.0
    damping: float = 0.5  # fraction of the log-step taken per frame (1 = jump straight there)
    scale: float = 1.0  # the scale last returned: the next frame time is measured at it
    # Start low: a first frame at full scale can take minutes on a CPU (an untrained ngp
    # field marches every cell), and while training it would hold the trainer's lock.
    moving_scale: float = 0.25

    @property
    def budget_s(self) -> float:
        """Seconds per frame."""
        return 1.0 / self.target_fps

    def update(self, frame_time_s: float | None, moving: bool) -> float:
        """Feed the render time (s) of the frame drawn at `self.scale`; return the next scale."""
        if frame_time_s is not None and frame_time_s > 0.0 and math.isfinite(frame_time_s):
            ideal = self.scale * math.sqrt(self.budget_s / frame_time_s)
            s = self.moving_scale * (ideal / self.moving_scale) ** self.damping
            self.moving_scale = min(max(s, self.min_scale), self.max_scale)
        self.scale = self.moving_scale if moving else self.max_scale
        return self.scale
