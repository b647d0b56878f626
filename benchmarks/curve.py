"""One timed training run of a benchmark: a curve of error against training time.

`train_curve` trains through the one training loop (`Trainer.run`) with hooks: a scheduled
evaluation on a fixed `EvalSet` (the one evaluation path, `fastenerf.evaluate`), a curve
writer that saves curve.json before every checkpoint, stop on a signal or a deadline. The
training clock is the trainer's own, the device's time for the steps taken: synchronised
after every step on the plain path (`Trainer.sync_clock`), and at every evaluation point on
the device-paced one (`Trainer.settle_clock`); set-up, evaluation and checkpoint writes are
outside it. Before a
run's clock starts, a throwaway copy takes `warmup_steps` steps and one evaluation, so
one-time costs (Warp kernel compilation, CUDA context, cuBLAS handles) are not charged to
whichever run happens to come first.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import signal
import tempfile
import time
from pathlib import Path
from typing import Any

import torch

from benchmarks.session import jsonable
from fastenerf.errors import InputError
from fastenerf.evaluate import EvalSet, evaluate_field
from fastenerf.hooks import Checkpointer, Deadline, Hook, ProgressBar, ScheduledEval, StopOnSignal
from fastenerf.io import write_json
from fastenerf.run import CHECKPOINT

# Nice geometric training times (s); the budget is always the last point. "dense" has ~6 points
# per decade so that a time to reach a PSNR is bracketed within a factor 1.5 (the ratio target
# is 50x: a factor-2 ladder could not tell 32x from 60x).
SCHEDULES = {
    "coarse": (1, 2, 4, 8, 15, 30, 60, 120, 300, 600, 1200, 1800, 3600, 7200, 14400),
    "dense": (
        1,
        1.5,
        2,
        3,
        4,
        5,
        6,
        8,
        10,
        12,
        15,
        20,
        25,
        30,
        40,
        50,
        60,
        90,
        120,
        180,
        240,
        300,
        450,
        600,
        900,
        1200,
        1800,
        3600,
        7200,
        14400,
    ),
}
SCHEDULE_S = SCHEDULES["coarse"]
DEFAULT_SCHEDULES = {"ngp": "dense", "vanilla": "coarse"}
DEFAULT_BUDGETS = {"ngp": 300.0, "vanilla": 480.0}


def schedule(budget_s: float, first_s: float = 1.0, ladder: str = "coarse") -> list[float]:
    """Training times (s) at which to evaluate: the nice geometric `ladder` (SCHEDULES) from
    `first_s` up to the budget, plus the budget itself; a budget below `first_s` gives
    [budget_s]."""
    if ladder not in SCHEDULES:
        raise InputError(f"--schedule: {ladder!r} is not one of {sorted(SCHEDULES)}")
    steps = SCHEDULES[ladder]
    times = [float(t) for t in steps if first_s <= t < budget_s]
    if first_s < steps[0]:  # sub-second starts (tiny CPU budgets): halve down from 1 s
        t = steps[0] / 2.0
        while t >= first_s:
            times.insert(0, t)
            t /= 2.0
        times = [x for x in times if x < budget_s]
    return sorted(set(times)) + [float(budget_s)]


def read_curve(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None


def make_config(
    backend: str,
    preset: str,
    budget_s: float,
    device: str,
    train: dict | None = None,
    backend_options: dict | None = None,
):
    """The TrainConfig of one benchmark run: preset + overrides, lr schedule over the budget."""
    from fastenerf.config import train_preset

    train = dict(train or {})
    opts = {**train.pop("backend_options", {}), **(backend_options or {})}
    train.update(minutes=budget_s / 60.0, device=device, eval_every_s=0.0, checkpoint_every_s=0.0)
    cfg = train_preset(preset, backend, **train)
    cfg.backend_options = {**cfg.backend_options, **opts}  # keep the preset's budget-made choices
    return cfg


def load_scene_dir(path: str | Path):
    from fastenerf.data.formats import load_any
    from fastenerf.data.formats.native import Scene

    scene = load_any(path)
    if not isinstance(scene, Scene):
        raise InputError(f"{path}: not a scene folder")
    return scene


def warm_up(scene, cfg, ev: EvalSet, steps: int, parent: Path) -> float:
    """Run `steps` steps and one evaluation on a throwaway trainer; returns the seconds taken."""
    from fastenerf.train import Trainer

    if steps <= 0:
        return 0.0
    t = time.perf_counter()
    parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".warmup-", dir=parent))
    try:
        tr = Trainer(scene, dataclasses.replace(cfg, steps=steps, minutes=None), tmp)
        tr.run(hooks=[])
        evaluate_field(tr.field, ev.subset(1), tr.cfg.chunk)
        tr.sync()
        del tr
        if torch.cuda.is_available():
            torch.cuda.empty_cache()
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return time.perf_counter() - t


class CurveWriter(Hook):
    """Writes the curve to curve.json before every checkpoint: a point taken after the last
    checkpoint is dropped on resume and taken again, never lost."""

    def __init__(self, curve: dict, path: Path):
        self.curve = curve
        self.path = path

    def before_checkpoint(self, trainer) -> None:
        self.curve.update(train_s=trainer.train_seconds, step=trainer.step_count)
        write_json(self.path, jsonable(self.curve))


def train_curve(
    scene,
    cfg,
    run_dir: str | Path,
    ev: EvalSet,
    times: list[float],
    *,
    label: dict[str, Any],
    session: dict[str, Any],
    resume: bool = False,
    deadline: float | None = None,
    warmup_steps: int = 1,
    checkpoint_every_s: float = 60.0,
    stop: StopOnSignal | None = None,
    progress: bool = True,
    extra_hooks: list[Hook] | None = None,
) -> dict[str, Any]:
    """Train `cfg` on `scene` in `run_dir`, evaluating on `ev` when the training clock passes
    each of `times` (s); returns the curve (also written to run_dir/curve.json).

    label: fields copied into the curve and every point (e.g. scene, backend); session: from
    `session_info`; resume: continue from run_dir's checkpoint and curve (a run without a
    checkpoint starts afresh); deadline: `time.perf_counter()` value after which the run
    checkpoints and returns unfinished; SIGTERM and Ctrl-C do the same (`stop`: one
    StopOnSignal shared by the runs of a call, so a signal ends them all). Each point: see
    `fastenerf.hooks.ScheduledEval`, plus the label and `session` (index into sessions).
    """
    from fastenerf.train import Trainer

    run_dir = Path(run_dir)
    curve_path = run_dir / "curve.json"
    has_ckpt = (run_dir / CHECKPOINT).is_file()
    if has_ckpt and not resume:
        raise InputError(
            f"{run_dir}: already holds a benchmark run; pass --resume to continue "
            "it or choose another --out"
        )
    budget = float(times[-1])
    curve = (read_curve(curve_path) if has_ckpt else None) or {}
    curve.update(label)
    curve.update(
        budget_s=budget, schedule_s=list(times), eval_views=ev.views.tolist(), eval_scale=ev.scale
    )
    curve.setdefault("points", [])
    curve.setdefault("sessions", [])
    if has_ckpt and curve.get("train_s", 0.0) >= budget and curve.get("finished"):
        return curve  # nothing left to do for this budget
    if stop is not None and stop.received:
        return curve
    if warmup_steps > 0 and not (deadline is not None and time.perf_counter() >= deadline):
        curve["last_warmup_s"] = warm_up(scene, cfg, ev, warmup_steps, run_dir.parent)
    trainer = Trainer(scene, cfg, run_dir, resume=has_ckpt)
    trainer.sync_clock = trainer.step_mode == "plain"  # device-paced: settled at each point
    curve["train_config"] = trainer.cfg.to_dict()
    curve["session_started"] = len(curve["sessions"])
    curve["sessions"].append(session)
    sess = len(curve["sessions"]) - 1
    # Points logged after the checkpoint will be taken again (the curve is written first).
    curve["points"] = [p for p in curve["points"] if p["step"] <= trainer.step_count]
    done_targets = {p.get("target_s") for p in curve["points"]}

    def on_point(point: dict) -> None:
        curve["points"].append({**label, **point, "session": sess})

    sched = ScheduledEval(ev, [t for t in times if t not in done_targets], on_point)
    hooks: list[Hook] = [
        sched,
        CurveWriter(curve, curve_path),
        Checkpointer(checkpoint_every_s),
        Deadline(deadline),
        stop or StopOnSignal((signal.SIGINT, signal.SIGTERM)),
        ProgressBar(progress),
        *(extra_hooks or []),
    ]
    trainer.sync()
    trainer.run(hooks)
    curve["finished"] = sched.finished
    curve.update(train_s=trainer.train_seconds, step=trainer.step_count)
    write_json(curve_path, jsonable(curve))
    return curve
