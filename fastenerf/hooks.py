"""Training callbacks: what happens around the steps of the one training loop.

`Trainer.run(hooks)` calls, for every hook in order, `on_start(trainer)` once, then
`after_step(trainer, stats)` after each step, `before_checkpoint(trainer)` before each
checkpoint is written, and `on_end(trainer, summary)` once. A hook may add keys to `stats`
(they reach metrics.jsonl) and may call `trainer.request_stop()` or `trainer.fail(msg)`.
The command line, the benchmarks and the viewer's live training differ only in their hooks;
none of them steps the trainer itself (nerfstudio's training callbacks are the model).
"""

from __future__ import annotations

import json
import math
import signal
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

from .evaluate import EvalSet, evaluate_field, make_eval_set
from .progress import progress_bar
from .run import METRICS_LOG

if TYPE_CHECKING:
    from .train import Trainer


class Hook:
    """A training callback; every method is a no-op by default."""

    def on_start(self, trainer: Trainer) -> None:
        pass

    def after_step(self, trainer: Trainer, stats: dict[str, Any]) -> None:
        pass

    def before_checkpoint(self, trainer: Trainer) -> None:
        pass

    def on_end(self, trainer: Trainer, summary: dict[str, Any]) -> None:
        pass


def evaluate_now(trainer: Trainer, ev: EvalSet) -> dict[str, float]:
    """Score the trainer's field on `ev` between steps; the time goes to `eval_seconds`."""
    t = time.perf_counter()
    with trainer.lock:
        metrics, _ = evaluate_field(trainer.field, ev, trainer.cfg.chunk)
    trainer.sync()
    trainer.eval_seconds += time.perf_counter() - t
    trainer.last_eval_psnr = metrics["psnr"]
    return metrics


class PeriodicEval(Hook):
    """Every `every_s` wall seconds, the colour-corrected PSNR on the run's evaluation set
    (`cfg.eval_views` views at `cfg.eval_scale`) as `eval_psnr` in the step's stats."""

    def __init__(self, every_s: float):
        self.every_s = every_s
        self.ev: EvalSet | None = None
        self.last = 0.0

    def on_start(self, trainer: Trainer) -> None:
        self.last = time.perf_counter()

    def after_step(self, trainer: Trainer, stats: dict[str, Any]) -> None:
        if self.every_s <= 0 or time.perf_counter() - self.last < self.every_s:
            return
        scene = trainer.scene
        if scene.test_c2w is None or not scene.test_rgb_paths:
            return
        if self.ev is None:
            c = trainer.cfg
            self.ev = make_eval_set(scene, c.eval_views, c.eval_scale)
        stats["eval_psnr"] = evaluate_now(trainer, self.ev)["psnr"]
        self.last = time.perf_counter()


class ScheduledEval(Hook):
    """Evaluates on `ev` at the first step whose training clock passes each of `times` (s),
    hands each point to `on_point(point)` and stops the run after the last one.

    A point: target_s, train_s, step, psnr, ssim, psnr_uncorrected, eval_s, the means
    since the previous point of loss, samples_per_step (the samples the field ran on),
    marched_per_step, rays_per_step (rendered, two a pixel) and step_ms, compacted_share
    (the share of those steps that ran on compacted samples: `MarcherOptions.early_stop_eps`),
    trained_slots (the slots, padding
    included, of the fixed-capacity buffer the field trains on now; None where buffers are
    exactly sized), graph_captures (CUDA graphs captured so far in this process: one more at
    every change of the step's graph key, e.g. a buffer's capacity, unless the key's graphs
    were kept: `TrainConfig.graph_keys`; None without a graphed step), graph_returns (the key
    changes so far that replayed kept graphs instead; None without a graphed step),
    compositing_share (the share of marched samples compositing used, as
    `compaction_auto`'s switch last read it; None without the switch), capacity_readings
    (the marched buffer's readings since the previous point, each the most samples a march
    wanted between two occupancy updates, which its capacity followed: `SampleCapacity`;
    None where buffers are exactly sized), and the learnt
    calibration's latest stats (CALIBRATION_KEYS, where the run learns it): how the poses
    and thresholds move over a run, not only where they end.
    """

    def __init__(self, ev: EvalSet, times: list[float], on_point: Callable[[dict], None]):
        self.ev = ev
        self.pending = sorted(times)
        self.on_point = on_point
        self._reset()

    def _reset(self) -> None:
        self.acc: list[dict] = []  # the steps' stats since the last point
        self.clock = None

    def on_start(self, trainer: Trainer) -> None:
        # a target the clock passed is not taken late, except the last one of a run that
        # resumes after its budget (its point lost to an interruption): taken at the end
        last = self.pending[-1:] if trainer.done() else []
        self.pending = [t for t in self.pending if t > trainer.train_seconds] or last
        self.clock = trainer.train_seconds
        if not self.pending:
            trainer.request_stop()

    def after_step(self, trainer: Trainer, stats: dict[str, Any]) -> None:
        self.acc.append(stats)  # values may still be on the device until the point
        if self.pending and trainer.train_seconds >= self.pending[0]:
            stats["eval_psnr"] = self._take(trainer)

    def on_end(self, trainer: Trainer, summary: dict[str, Any]) -> None:
        # The budget can be spent between two checks of this hook (another hook's checkpoint
        # settles the clock past the last target): that target is taken now, not lost.
        passed = self.pending and trainer.train_seconds >= self.pending[0]
        if passed and trainer.failure is None and trainer.done():
            summary["last_eval_psnr"] = self._take(trainer)

    def _take(self, trainer: Trainer) -> float:
        """Evaluate now for the targets the clock has passed; returns the point's PSNR."""
        train_s = trainer.train_seconds
        target = self.pending.pop(0)
        while self.pending and train_s >= self.pending[0]:  # one long step passed several
            target = self.pending.pop(0)
        trainer.flush_stats()
        trainer.settle_clock()  # the point's time includes the steps still queued
        train_s = trainer.train_seconds
        te = time.perf_counter()
        metrics = evaluate_now(trainer, self.ev)
        losses = [s["loss"] for s in self.acc if math.isfinite(s["loss"])]
        # each step's own rays: samples_per_step changes them within a run
        rays = [s.get("rays", trainer.rays_per_step_total) for s in self.acc]
        samples = [
            s.get("samples_per_ray", float("nan")) * r for s, r in zip(self.acc, rays, strict=True)
        ]
        # a compacted step marched more than the field ran on (no marched_per_ray: the same)
        marched = [
            s.get("marched_per_ray", s.get("samples_per_ray", float("nan"))) * r
            for s, r in zip(self.acc, rays, strict=True)
        ]
        compacted = sum("marched_per_ray" in s for s in self.acc)
        point = {
            "target_s": target,
            "train_s": train_s,
            "step": trainer.step_count,
            **{k: v for k, v in metrics.items() if k != "render_seconds_per_view"},
            "eval_s": time.perf_counter() - te,
            "loss": sum(losses) / len(losses) if losses else float("nan"),
            "samples_per_step": sum(samples) / max(len(samples), 1),
            "marched_per_step": sum(marched) / max(len(marched), 1),
            "rays_per_step": sum(rays) / max(len(rays), 1),
            "compacted_share": compacted / max(len(self.acc), 1),
            "trained_slots": trained_slots_now(trainer),
            "graph_captures": getattr(trainer.graph, "captures", None),
            "graph_returns": getattr(trainer.graph, "returns", None),
            "compositing_share": _compositing_share(trainer),
            "capacity_readings": _capacity_readings(trainer),
            "step_ms": 1e3 * (train_s - self.clock) / max(len(self.acc), 1),
            **_latest(self.acc, CALIBRATION_KEYS),
        }
        self._reset()
        self.clock = train_s
        self.on_point(point)
        if not self.pending:
            trainer.request_stop()
        trainer.save_checkpoint(finished=not self.pending)
        return metrics["psnr"]

    @property
    def finished(self) -> bool:
        return not self.pending


CALIBRATION_KEYS = (
    "pose_correction_deg",
    "pose_correction_max_deg",
    "pose_error_deg",
    "pose_error_aligned_deg",
    "pose_jitter_deg",
    "pose_settle_px",
    "field_win_max",
    "poses_frozen",
    "field_restarts",
    "threshold_pos",
    "threshold_neg",
    "threshold_ratio",
)


def trained_slots_now(trainer: Trainer) -> int | None:
    """The field's fixed training buffer's slots now (a host int, no device read), or None."""
    slots = getattr(getattr(trainer.field, "sampler", None), "trained_slots", None)
    return None if slots is None else slots()


def _compositing_share(trainer: Trainer) -> float | None:
    """The compaction switch's last reading (a host float, no device read), or None."""
    switch = getattr(getattr(trainer.field, "sampler", None), "compaction", None)
    return None if switch is None else switch.share


def _capacity_readings(trainer: Trainer) -> list[int] | None:
    """The marched buffer's capacity readings since the last point (host ints), or None."""
    cap = getattr(getattr(trainer.field, "sampler", None), "sample_capacity", None)
    return None if cap is None else cap.take_readings()


def _latest(acc: list[dict], keys: tuple[str, ...]) -> dict[str, float]:
    """The latest value of each of `keys` among the steps' stats `acc` (flushed: floats)."""
    out: dict[str, float] = {}
    for stats in reversed(acc):
        for k in keys:
            if k not in out and k in stats and not torch.is_tensor(stats[k]):
                out[k] = float(stats[k])
    return out


class MetricsLog(Hook):
    """Appends a JSON line of the step's stats to RUN/metrics.jsonl every `log_every` steps,
    for the first ten steps, at every evaluation and at the last step."""

    def __init__(self, log_every: int):
        self.log_every = log_every
        self.file = None
        self.wall_start = 0.0

    def on_start(self, trainer: Trainer) -> None:
        self.file = open(Path(trainer.out_dir) / METRICS_LOG, "a")  # noqa: SIM115 - on_end
        self.queue: list[dict] = []
        self.wall_start = time.perf_counter() - trainer.wall_seconds

    def after_step(self, trainer: Trainer, stats: dict[str, Any]) -> None:
        s = trainer.step_count
        if s % self.log_every == 0 or s <= 10 or "eval_psnr" in stats or trainer.done():
            stats["wall_s"] = time.perf_counter() - self.wall_start
            self.queue.append(stats)
        if "eval_psnr" in stats or trainer.done():
            trainer.flush_stats()
        # a line is written once the trainer has brought its values to the host (the device
        # path does every few steps), so logging costs no extra wait for the device
        while self.queue and not any(torch.is_tensor(v) for v in self.queue[0].values()):
            self.file.write(json.dumps(self.queue.pop(0)) + "\n")
        self.file.flush()

    def on_end(self, trainer: Trainer, summary: dict[str, Any]) -> None:
        if self.file is not None:
            trainer.flush_stats()
            for stats in self.queue:
                self.file.write(json.dumps(stats) + "\n")
            self.queue = []
            self.file.close()
            self.file = None


class ProgressBar(Hook):
    """A tqdm bar over the budget (steps or seconds), quiet when stderr is not a terminal."""

    def __init__(self, enabled: bool = True):
        self.enabled = enabled
        self.bar = None
        self.last = 0.0

    def on_start(self, trainer: Trainer) -> None:
        c = trainer.cfg
        self.by_steps = c.steps is not None
        self.total = c.steps if self.by_steps else int(round(60 * c.minutes))
        self.bar = progress_bar(
            total=self.total,
            initial=trainer.step_count if self.by_steps else int(trainer.train_seconds),
            unit="step" if self.by_steps else "s",
            desc=f"train {c.backend}",
            enabled=self.enabled,
        )

    def after_step(self, trainer: Trainer, stats: dict[str, Any]) -> None:
        now = time.perf_counter()
        if now - self.last < 0.25 and not trainer.done():
            return
        self.last = now
        trainer.flush_stats()  # a few times a second: the loss shown is this step's
        n = trainer.step_count if self.by_steps else int(trainer.train_seconds)
        self.bar.n = min(self.total, n)
        post = {
            "loss": f"{stats['loss']:.4f}",
            "rays/s": f"{stats['rays_per_s']:.3g}",
            "t": f"{trainer.train_seconds:.0f}s",
        }
        if trainer.last_eval_psnr is not None:
            post["psnr"] = f"{trainer.last_eval_psnr:.2f}"
        self.bar.set_postfix(post, refresh=True)

    def on_end(self, trainer: Trainer, summary: dict[str, Any]) -> None:
        if self.bar is not None:
            self.bar.close()


class Checkpointer(Hook):
    """A checkpoint every `every_s` training seconds or `every_steps` steps (0: never), and
    one at the end (marked finished unless the run was interrupted). Not while losses are
    non-finite, and not at the end of a run stopped for divergence: the last checkpoint
    written then is the last good one."""

    def __init__(self, every_s: float, every_steps: int = 0):
        self.every_s = every_s
        self.every_steps = every_steps

    def on_start(self, trainer: Trainer) -> None:
        self.last_t = time.perf_counter()
        self.last_step = trainer.step_count

    def after_step(self, trainer: Trainer, stats: dict[str, Any]) -> None:
        if trainer.nonfinite_run > 0:
            return
        due_t = self.every_s > 0 and time.perf_counter() - self.last_t >= self.every_s
        due_s = self.every_steps > 0 and trainer.step_count - self.last_step >= self.every_steps
        if due_t or due_s:
            trainer.save_checkpoint(finished=False, background=True)
            self.last_t = time.perf_counter()
            self.last_step = trainer.step_count

    def on_end(self, trainer: Trainer, summary: dict[str, Any]) -> None:
        if trainer.failure is None:
            finished = not summary["interrupted"]
            summary["checkpoint"] = str(trainer.save_checkpoint(finished=finished))
        trainer.wait_for_checkpoint()


class DivergenceGuard(Hook):
    """Stops the run after `patience` consecutive non-finite losses (their steps never reach
    the weights), with one line saying so; the last checkpoint stays the last good one."""

    def __init__(self, patience: int = 20):
        self.patience = patience

    def after_step(self, trainer: Trainer, stats: dict[str, Any]) -> None:
        if trainer.nonfinite_run >= self.patience:
            trainer.fail(
                f"training diverged: the loss was not finite for {trainer.nonfinite_run} "
                f"steps in a row (at step {trainer.step_count}, lr {stats['lr']:.3g}); "
                f"the last good checkpoint is kept in {trainer.out_dir} "
                "(try a lower --lr)"
            )


class StopOnSignal(Hook):
    """The first Ctrl-C (or SIGTERM) finishes the current step, checkpoints and returns; a
    second Ctrl-C aborts at once (the last checkpoint on disk stays valid). Main thread only."""

    def __init__(self, signals: tuple[int, ...] = (signal.SIGINT,)):
        self.signals = signals
        self.old: dict[int, Any] = {}
        self.received = False  # stays set: one hook may watch several runs in a row

    def on_start(self, trainer: Trainer) -> None:
        if self.received:
            trainer.request_stop()
        self._install(trainer)

    def _install(self, trainer: Trainer) -> None:
        if threading.current_thread() is not threading.main_thread():
            return

        def handler(signum, frame):
            if self.received and signum == signal.SIGINT:
                raise KeyboardInterrupt
            self.received = True
            trainer.request_stop()

        for sig in self.signals:
            self.old[sig] = signal.signal(sig, handler)

    def on_end(self, trainer: Trainer, summary: dict[str, Any]) -> None:
        for sig, old in self.old.items():
            signal.signal(sig, old)
        self.old.clear()


class Deadline(Hook):
    """Stops the run once `time.perf_counter()` passes `deadline` (a call's wall budget)."""

    def __init__(self, deadline: float | None):
        self.deadline = deadline

    def after_step(self, trainer: Trainer, stats: dict[str, Any]) -> None:
        if self.deadline is not None and time.perf_counter() >= self.deadline:
            trainer.request_stop()


def default_hooks(trainer: Trainer, progress: bool = True) -> list[Hook]:
    """What `fastenerf train` runs with: periodic evaluation, metrics log, progress bar,
    divergence guard, checkpoints, Ctrl-C. Order matters: evaluation first, so its number
    reaches the log and the bar of the same step."""
    c = trainer.cfg
    return [
        PeriodicEval(c.eval_every_s),
        MetricsLog(c.log_every),
        ProgressBar(progress),
        DivergenceGuard(),
        Checkpointer(c.checkpoint_every_s, c.checkpoint_every_steps),
        StopOnSignal(),
    ]
