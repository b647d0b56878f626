"""The training loop: windows -> rays -> field -> event loss -> Adam (DESIGN §1, §3).

`Trainer` builds what a run needs and takes one optimisation step at a time; `Trainer.run`
is THE loop, and everything around the steps (evaluation, logging, progress, checkpoints,
stopping) is a hook (`fastenerf.hooks`). What it trains on is `fastenerf.training_data`'s, a
step's update `fastenerf.step_update`'s and its stats `fastenerf.step_stats`'s. The run
folder's files are `fastenerf.run`'s; the checkpoint's contents are `fastenerf.train_state`'s,
config.json's `fastenerf.run_config`'s.
A resumed run takes the same next steps as one that never stopped (bit-identical on CPU).
Training time excludes evaluation and checkpoint time; both are recorded.
"""

from __future__ import annotations

import math
import random
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.profiler import record_function

from . import run_config, train_state
from .batch_size import QUANTUM, BatchSize, lag_blocks
from .config import TrainConfig
from .data.formats.native import Scene
from .device_step import FiniteGuard, PendingStats, supports_device_guard
from .errors import InputError
from .field_restart import RestartClock, restart_due
from .fields import Field, make_field
from .graph_step import graphed_step
from .hooks import Hook, default_hooks
from .losses import total_loss
from .memory import check_ray_batch
from .optim import field_adam, lr_as_floats, set_lr
from .run import (
    CHECKPOINT,
    CheckpointWriter,
    load_checkpoint,
    resolve_device,
    scene_background,
)
from .self_calibration import SelfCalibration, measured_ratio
from .step_stats import STATS_FLUSH_EVERY, append_history, step_stats
from .step_update import update_on_device, update_plain
from .training_data import build_training_data, exact_grid_poses, observed_poses

# (samples per ray, float32 values autograd keeps per sample) of a training step, for the
# memory check before the first batch: vanilla's 64 + 128 samples through 8×256 layers (kept
# for both passes); ngp's typical samples per ray once carved (the fog's first steps take more,
# up to the marcher's cap) through the hash features and two 64-wide MLPs.
BATCH_MEMORY = {"vanilla": (192, 4096), "ngp": (256, 512)}


class Trainer:
    """Trains one field on one scene into the run folder `out_dir`.

    scene: a loaded Scene; cfg: TrainConfig (None values resolved for the scene and device);
    resume: continue from out_dir/checkpoint.pt (options other than the budget must match).
    Attributes: field, rig, sampler, optimizer, lock (held during a step and an evaluation: a
    viewer thread may render between steps), history (recent stats dicts), step_count,
    train_seconds, eval_seconds, wall_seconds, failure (a one-line reason a run was stopped).
    `sync_clock`: synchronise the device before reading the training clock after each step
    (the step time is then the device's, not the host's, at the cost of the device idling while
    the host prepares the next step); `settle_clock()` does it once, e.g. before an evaluation.
    """

    def __init__(self, scene: Scene, cfg: TrainConfig, out_dir: str | Path, resume: bool = False):
        self.out_dir = Path(out_dir)
        self.device = resolve_device(cfg.device)
        self.cfg = cfg.resolved(scene.config, str(self.device))
        self.scene = scene
        checkpoint = self._checkpoint_to_resume(resume)
        seed = self.cfg.seed
        random.seed(seed)
        np.random.seed(seed)
        torch.manual_seed(seed)
        self._check_batch_memory()
        d = build_training_data(scene, self.cfg, self.device)
        self.rig, self.index, self.windows, self.sampler = d.rig, d.index, d.windows, d.sampler
        self.perturbation, self.smoothing = d.perturbation, d.smoothing
        self.field: Field = make_field(self.cfg.backend, scene.config, self.cfg).to(self.device)
        self.optimizer = field_adam(self.field, self.cfg, self.device)
        self.clock = RestartClock()  # where the field's schedules count from
        self.selfcal = self._make_self_calibration()  # None unless refine/estimate is on
        self.batch_size = self._make_batch_size()  # None unless samples_per_step is set
        bg = scene_background(scene.config)
        self.background = None if bg is None else torch.tensor(bg, device=self.device)
        self.amp = bool(self.cfg.amp and self.device.type == "cuda")
        self.lock = threading.Lock()
        self.history: list[dict] = []  # recent steps' stats (trimmed to step_stats.HISTORY_MAX)
        self.step_count = 0
        self.train_seconds = self.eval_seconds = self.wall_seconds = 0.0
        self._queued = False  # steps the device may still be running (settle_clock)
        self.last_eval_psnr: float | None = None
        self.skipped_steps = 0
        self.nonfinite_run = 0  # consecutive steps with a non-finite loss
        self.failure: str | None = None
        self.stopped = False
        self.sync_clock = False
        self._hooks: list[Hook] = []
        self._writer = CheckpointWriter(self.out_dir)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self._observe_training_cameras()
        if checkpoint is not None:
            train_state.restore(self, checkpoint)
            train_state.trim_metrics(self.out_dir, self.step_count)
        self.pending = PendingStats()
        self.guard: FiniteGuard | None = None
        self.set_step_mode(self.cfg.step_mode)
        self.write_config()

    # -- set-up ------------------------------------------------------------------------------

    def _checkpoint_to_resume(self, resume: bool) -> dict | None:
        path = self.out_dir / CHECKPOINT
        if not resume and path.exists():
            raise InputError(
                f"{self.out_dir}: already holds a training run; pass --resume to "
                "continue it or choose another --out"
            )
        if resume and not path.exists():
            raise InputError(f"{self.out_dir}: no {CHECKPOINT} to resume from")
        if not resume:
            return None
        ck = load_checkpoint(path)
        train_state.check_compatible(self, ck)
        return ck

    def _check_batch_memory(self) -> None:
        """Refuse (one line, with the estimate and the limit) a ray batch that cannot fit."""
        spr, floats = BATCH_MEMORY[self.cfg.backend]
        what = f"a step's rays (--rays {self.cfg.rays_per_step:,} at t0 and t1):"
        check_ray_batch(self.rays_per_step_total, spr, floats, str(self.device), what)

    def _observe_training_cameras(self) -> None:
        sc = self.scene.config
        c2w = observed_poses(self.sampler)
        self.field.observe_cameras(self.rig.intrinsics.K, c2w, sc.width, sc.height, sc.near)

    def set_step_mode(self, mode: str, capture: bool | None = None) -> str:
        """Choose the step: "plain" (host reads the loss), "device" (`device_step`), "graph"
        (device, replayed from a CUDA graph: `graph_step`; capture=False runs it eagerly) or
        "auto" (graph on CUDA, plain on the CPU). Returns the mode in use: graph falls back to
        device where the step cannot be captured (field, self-calibration), device to plain
        without fused Adam."""
        self.flush_stats()
        self.step_mode_asked = mode
        want = mode if mode != "auto" else ("graph" if self.device.type == "cuda" else "plain")
        self.graph = None
        if want in ("device", "graph") and supports_device_guard(self.optimizer):
            params = [p for g in self.optimizer.param_groups for p in g["params"]]
            if self.selfcal is not None:  # one flag: a non-finite gradient anywhere skips all
                params += self.selfcal.parameters()
            self.guard = FiniteGuard(params, self.device)
            self._skipped_before_guard = self.skipped_steps
            self.step_mode = "device"
        else:
            if self.guard is not None:
                self.guard.disarm(self.optimizer)
            self.guard = None
            self.step_mode = "plain"
        if hasattr(self.field, "use_fixed_capacity"):  # no host read of the sample count
            self.field.use_fixed_capacity(self.step_mode == "device")
        lr_as_floats(self.optimizer)
        if self.selfcal is not None:
            self.selfcal.lr_as_floats()
        if want == "graph" and self.step_mode == "device":
            args = (self.field, self.optimizer, self.selfcal, self.device, capture)
            copies, keys = self.cfg.graph_copies, self.cfg.graph_keys
            self.graph = graphed_step(self._graph_body, *args, copies=copies, keys=keys)
            self.step_mode = "device" if self.graph is None else "graph"
        return self.step_mode

    def _graph_body(self, batch) -> tuple[dict, torch.Tensor, dict]:
        """What a graphed step captures: render, loss, backward, guard and update."""
        out, loss, parts = self._forward(batch)
        return out, update_on_device(loss, self.optimizer, self.guard, self.selfcal), parts

    def _make_self_calibration(self) -> SelfCalibration | None:
        if not SelfCalibration.wanted(self.cfg):
            return None
        sc = self.scene.config
        true_c2w = exact_grid_poses(self.scene, self.perturbation)  # a study's truth
        if true_c2w is not None:
            true_c2w = torch.as_tensor(true_c2w, device=self.device)
        thresholds = (sc.pos_threshold, sc.neg_threshold)
        turn = (self.smoothing or {}).get("mean_turn_deg")  # the prior's, for the gate
        args = (thresholds, self.field, true_c2w, measured_ratio(self.scene, self.cfg), turn)
        return SelfCalibration(self.cfg, self.sampler, *args)

    def restart_field(self) -> None:
        """A new field and optimiser from this step on, their schedules counted from here
        (`field_restart`; refine_restart once the poses settle); the step mode asked for last
        is set up again for them."""
        self.flush_stats()
        with torch.random.fork_rng(devices=[]):  # the first field's init; the run's stream stays
            torch.manual_seed(self.cfg.seed)
            field = make_field(self.cfg.backend, self.scene.config, self.cfg)
        self.field = field.to(self.device)
        self._observe_training_cameras()
        self.optimizer = field_adam(self.field, self.cfg, self.device)
        self.clock = RestartClock(self.step_count, self.progress(), self.clock.restarts + 1)
        if self.selfcal is not None:
            self.selfcal.use_field(self.field, self.clock.progress)
        old = self.graph
        self.set_step_mode(self.step_mode_asked)
        if old is not None and self.graph is not None:  # the run's counts, not the new field's
            for key in ("captures", "replays", "returns"):
                setattr(self.graph, key, getattr(self.graph, key) + getattr(old, key))

    def _make_batch_size(self) -> BatchSize | None:
        """The pixels-per-step rule of samples_per_step (`batch_size`), between one quantum
        (or the windows a step draws) and rays_per_step; None without the option."""
        c = self.cfg
        if c.samples_per_step is None:
            return None
        hi = c.rays_per_step
        lo = min(hi, max(QUANTUM, c.windows_per_step))
        block = self.sampler.prefetch
        lag = lag_blocks(block, STATS_FLUSH_EVERY)
        return BatchSize(c.samples_per_step, lo, hi, block, lag)

    @property
    def rays_per_step_total(self) -> int:
        """Rays rendered per step: each pixel at t0 and at t1, pixels split over the windows."""
        w = self.cfg.windows_per_step
        return 2 * w * max(1, self.cfg.rays_per_step // w)

    def write_config(self) -> Path:
        """Write RUN/config.json (`run_config`: options, scene, what was built)."""
        return run_config.write_config(self)

    # -- one step ----------------------------------------------------------------------------

    def lr_at(self, step: int) -> float:
        """Learning rate for `step`: warm-up, then constant or exponential decay to lr_final
        (held at lr until the budget fraction lr_decay_start, then decayed over the rest)."""
        c, clock = self.cfg, self.clock
        lr = c.lr
        if c.lr_final is not None and c.lr_final != c.lr:
            s, p = c.lr_decay_start, clock.local_progress(self.progress(step))
            lr = c.lr * (c.lr_final / c.lr) ** max(0.0, (p - s) / (1.0 - s))
        if c.lr_warmup_steps > 0:
            lr *= min(1.0, (clock.local_step(step) + 1) / c.lr_warmup_steps)
        return lr

    def progress(self, step: int | None = None) -> float:
        """Fraction of the budget spent (the larger of steps and time), in [0, 1]."""
        step = self.step_count if step is None else step
        p = 0.0
        if self.cfg.steps:
            p = max(p, step / self.cfg.steps)
        if self.cfg.minutes:
            p = max(p, self.train_seconds / (60.0 * self.cfg.minutes))
        return min(1.0, p)

    def sync(self) -> None:
        """Wait for queued device work (Warp launches on the same stream included)."""
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)

    def settle_clock(self) -> None:
        """Wait for the steps the device still has queued and charge the wait to the training
        clock: after it, train_seconds is the device's time for every step taken so far."""
        if not self._queued:  # nothing to wait for: a second settle must not add its own time
            return
        t = time.perf_counter()
        self.sync()
        self.train_seconds += time.perf_counter() - t
        self._queued = False

    def step(self) -> dict[str, Any]:
        """One optimisation step; returns stats (step, loss, rays_per_s, elapsed_s, lr, ...).

        The loop (`run`) calls it; the stats it returns are what hooks and metrics.jsonl see.
        """
        with self.lock:
            t_begin = time.perf_counter()
            lr = self.lr_at(self.step_count)
            if self.selfcal is not None:
                self.selfcal.before_step(self.progress(), lr / self.cfg.lr)
                if restart_due(self.cfg, self.selfcal, self.clock):
                    self.restart_field()
                    lr = self.lr_at(self.step_count)
                    # again, held: this step is the new field's, whose gradient moves no pose
                    self.selfcal.before_step(self.progress(), lr / self.cfg.lr)
            set_lr(self.optimizer, lr)
            self.field.train()
            # The named ranges are what benchmarks.profile_step attributes time to (a range
            # costs ~1 µs when no profiler runs).
            with record_function("grid_update"):
                self.field.update(self.clock.local_step(self.step_count))
            with record_function("sample_rays"):
                if self.batch_size is not None and self.sampler.block_done():
                    n = self.batch_size.decide(self.step_count, self.sampler.pixels)
                    if n is not None:
                        self.sampler.set_pixels(n)
                batch = self.sampler.sample()
            if self.graph is not None:
                out, loss_value, parts = self.graph(batch)
            else:
                out, loss, parts = self._forward(batch)
                if self.guard is None:
                    loss_value = update_plain(loss, self.optimizer, self.selfcal)
                    if math.isfinite(loss_value):
                        self.nonfinite_run = 0
                    else:  # the device path's counters are its guard's, read at a flush
                        self.skipped_steps += 1
                        self.nonfinite_run += 1
                else:
                    loss_value = update_on_device(loss, self.optimizer, self.guard, self.selfcal)
            self.step_count += 1
            if self.sync_clock:
                self.sync()
            self._queued = self.device.type == "cuda" and not self.sync_clock
            dt = time.perf_counter() - t_begin
            self.train_seconds += dt
            return self._record(batch, out, parts, loss_value, lr, dt)

    def flush_stats(self) -> list[dict]:
        """Bring device-held stats to the host (one copy) and into `history`; update the
        non-finite counters. A no-op on the plain path. Returns the flushed stats."""
        p = getattr(self, "pending", None)
        if p is None or self.guard is None or not (len(p) or p.in_flight):
            return []
        t = time.perf_counter()  # the copy waits for the queued steps: training time
        done = self._took(self.pending.flush([self.guard.run, self.guard.skipped]))
        self.train_seconds += time.perf_counter() - t
        self._queued = False  # the copy came after every queued step
        return done

    def _took(self, flushed: tuple[list[dict], list[float]]) -> list[dict]:
        done, (run, skipped) = flushed
        self.nonfinite_run = int(run)
        self.skipped_steps = self._skipped_before_guard + int(skipped)
        for st in done:
            append_history(self.history, st, self.skipped_steps)
        if self.batch_size is not None:
            self.batch_size.observe(done)
        return done

    def _forward(self, batch):
        """Render the batch and compute the event loss; gradients zeroed for the backward."""
        cfg = self.cfg
        rays_o, rays_d, target, reg = batch.rays_o, batch.rays_d, batch.target, None
        grad_rays = None
        if self.selfcal is not None:
            rays_o, rays_d, target, reg = self.selfcal.apply(batch)
            grad_rays = self.selfcal.grad_rays
        with (
            record_function("render"),
            # a captured step must not keep autocast's cast weights from one replay to the next
            torch.autocast(self.device.type, torch.bfloat16, self.amp, self.graph is None),
        ):
            out = self.field.render(
                rays_o,
                rays_d,
                near=self.scene.config.near,
                background=self.background,
                train=True,
                grad_rays=grad_rays,
            )
        with record_function("loss"):
            loss, parts = total_loss(
                out,
                target,
                batch.channel,
                gamma=cfg.gamma,
                eps=cfg.log_eps,
                distortion_weight=cfg.distortion_weight,
                fused=True,
            )
            if reg is not None:
                loss = loss + reg
                parts["threshold_reg"] = reg.detach()
            self.optimizer.zero_grad(set_to_none=True)
            if self.selfcal is not None:
                self.selfcal.zero_grad()
        return out, loss, parts

    def _record(self, batch, out, parts, loss_value, lr: float, dt: float) -> dict:
        """The step's stats; on the device path its tensor values stay tensors until the next
        `flush_stats` (every STATS_FLUSH_EVERY steps, or when a hook asks)."""
        on_device = self.guard is not None
        stats = step_stats(
            batch, out, parts, loss_value, lr, dt, self.step_count, self.train_seconds, on_device
        )
        # the calibration's estimates: every step on the plain path, at the flush steps (as
        # device tensors the flush copies) on the device-paced one
        flush_step = len(self.pending) + 1 >= STATS_FLUSH_EVERY
        if self.selfcal is not None and (not on_device or flush_step):
            stats.update(self.selfcal.stats(on_device))
        if self.cfg.refine_restart:  # a host count: the viewer's and the log's
            stats["field_restarts"] = float(self.clock.restarts)
        if not on_device:
            append_history(self.history, stats, self.skipped_steps)
            if self.batch_size is not None:
                self.batch_size.observe([stats])
            return stats
        self.pending.add(stats)
        if len(self.pending) >= STATS_FLUSH_EVERY:  # on CUDA read one flush later: no wait
            if self.device.type != "cuda":
                self.flush_stats()
            elif got := self.pending.rotate([self.guard.run, self.guard.skipped]):
                self._took(got)
        return stats

    # -- the loop ----------------------------------------------------------------------------

    def done(self) -> bool:
        c = self.cfg
        if c.steps is not None and self.step_count >= c.steps:
            return True
        return c.minutes is not None and self.train_seconds >= 60.0 * c.minutes

    def request_stop(self) -> None:
        """Ask `run()` to stop after the current step (and checkpoint); thread-safe."""
        self.stopped = True

    def fail(self, reason: str) -> None:
        """Stop the run for `reason` (one line); `run()` returns it as `failure`."""
        self.failure = reason
        self.stopped = True

    def run(self, hooks: list[Hook] | None = None, progress: bool = True) -> dict[str, Any]:
        """THE training loop: step until the budget is spent or a hook stops it.

        hooks: the callbacks (default: `hooks.default_hooks`, what `fastenerf train` uses).
        Returns a summary: steps, train/eval/wall seconds, loss, last_eval_psnr, interrupted
        (stopped before the budget), failure (None or a one-line reason), checkpoint, out_dir.
        """
        self._hooks = default_hooks(self, progress) if hooks is None else list(hooks)
        self.stopped = False
        self.failure = None
        wall_start = time.perf_counter() - self.wall_seconds
        for h in self._hooks:
            h.on_start(self)
        summary: dict[str, Any] = {}
        try:
            while not self.done() and not self.stopped:
                stats = self.step()
                self.wall_seconds = time.perf_counter() - wall_start
                for h in self._hooks:
                    h.after_step(self, stats)
        # A second Ctrl-C (KeyboardInterrupt) propagates: the state may be torn mid-step, so
        # no checkpoint is written and the last one on disk stays valid.
        finally:
            self.flush_stats()
            self.wall_seconds = time.perf_counter() - wall_start
            if self.selfcal is not None:  # config.json records the final estimates
                self.write_config()
            summary.update(
                steps=self.step_count,
                train_seconds=self.train_seconds,
                eval_seconds=self.eval_seconds,
                wall_seconds=self.wall_seconds,
                loss=self.history[-1]["loss"] if self.history else None,
                last_eval_psnr=self.last_eval_psnr,
                interrupted=self.stopped and not self.done() and self.failure is None,
                failure=self.failure,
                checkpoint=None,
                out_dir=str(self.out_dir),
            )
            for h in reversed(self._hooks):
                h.on_end(self, summary)
            self._hooks = []
        return summary

    # -- checkpoints -------------------------------------------------------------------------

    def save_checkpoint(self, finished: bool = False, background: bool = False) -> Path:
        """Write RUN/checkpoint.pt and progress.json atomically; returns the checkpoint path.

        The state is copied (to the CPU) under the lock; with `background` a thread writes it
        while training goes on (one write at a time, the next waits for the last).
        """
        for h in self._hooks:
            h.before_checkpoint(self)
        self.flush_stats()
        self.settle_clock()  # the copy below would wait for queued steps off the clock
        self.wait_for_checkpoint()  # one CPU copy of the state at a time: the last write ends first
        with self.lock:
            state = train_state.cpu_copy(train_state.trainer_state(self))
        progress = train_state.progress_record(self, finished)
        return self._writer.write(state, progress, background)

    def wait_for_checkpoint(self) -> None:
        """Block until a checkpoint being written in the background is on disk."""
        self._writer.wait()
