"""A field started afresh once the poses settle (issue #20's `refine_restart`).

Refining poses that start ~1° off, the field learns the wrong poses' blur until they settle
(~40 % of a 60 s budget) and does not shed it in what is left. With `refine_restart` the
trainer builds a new field at the settle (weights, occupancy grid, optimiser) and trains it
on the settled poses, frozen, over the rest of the budget. The field's schedules (the
learning rate, its warm-up and decay; the occupancy updates and the early cone, which count
the field's own steps) then start again as in a run of the budget left: `RestartClock` is
where they count from.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass


@dataclass
class RestartClock:
    """Where the field's schedules count from: the trainer's step and budget fraction at the
    field's last (re)start, and how many restarts there were (0: the run's first field)."""

    step: int = 0
    progress: float = 0.0
    restarts: int = 0
    declined: bool = False  # the poses settled close to the given ones: no restart

    def local_step(self, step: int) -> int:
        """The field's own step count at trainer step `step`."""
        return step - self.step

    def local_progress(self, progress: float) -> float:
        """The fraction of the field's own budget (what was left at its start) spent at the
        run's budget fraction `progress`, in [0, 1]."""
        if self.restarts == 0:
            return progress
        left = 1.0 - self.progress
        if left <= 0.0:
            return 1.0
        return min(1.0, max(0.0, (progress - self.progress) / left))

    def state_dict(self) -> dict:
        return asdict(self)

    def load_state_dict(self, state: dict | None) -> None:
        """Put back a `state_dict()`; None (a checkpoint from before restarts): no restart."""
        state = state or {}
        self.step = int(state.get("step", 0))
        self.progress = float(state.get("progress", 0.0))
        self.restarts = int(state.get("restarts", 0))
        self.declined = bool(state.get("declined", False))


def restart_due(cfg, selfcal, clock: RestartClock) -> bool:
    """True when `cfg.refine_restart` asks for a new field now: the poses of `selfcal` (the
    run's `SelfCalibration`, or None) have settled, no restart was made or declined yet, and
    the given poses were off by more than `cfg.refine_restart_deg` (mean turn: the motion
    prior's, or the corrections'); where they were not, the restart is declined for good
    (`clock.declined`): a field trained on poses that close has little blur to shed."""
    if not getattr(cfg, "refine_restart", False) or selfcal is None:
        return False
    if clock.restarts or clock.declined or not selfcal.settled():
        return False
    if selfcal.given_turn_deg() <= cfg.refine_restart_deg:
        clock.declined = True
        return False
    return True
