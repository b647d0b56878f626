"""What the viewer looks at: a field, its scene's cameras, and (optionally) a live trainer.

`ViewSource.from_run(RUN)` loads a trained (or still training, in another process) run and
reloads its checkpoint when it changes; `ViewSource.from_training(SCENE)` starts a Trainer in
a background thread, stepping it while the viewer renders the current weights under the
trainer's lock; `ViewSource.from_field(field, ...)` wraps a field that is already in memory.
"""

from __future__ import annotations

import threading
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from fastenerf.data.rig import Intrinsics, Rig
from fastenerf.errors import InputError

from .camera import OrbitCamera, scene_up


def pose_grid(cfg, root: str | Path | None = None, poses=None) -> np.ndarray:
    """The scene's `n_views` poses, uniform in time over [t_start, t_end) (closed loops) or
    [t_start, t_end]: (n_views, 4, 4) float64 c2w."""
    rig = Rig.from_scene(cfg, root, poses)  # poses: in memory (EventNeRF folders)
    t = np.linspace(cfg.t_start_us, cfg.t_end_us, cfg.n_views, endpoint=not cfg.loop)
    return rig.pose(np.round(t).astype(np.int64))


@dataclass
class TrainStats:
    """Training progress as the viewer shows it: the loss curve and the latest stats."""

    steps: list[int] = field(default_factory=list)
    losses: list[float] = field(default_factory=list)
    last: dict[str, Any] = field(default_factory=dict)
    error: str | None = None
    done: bool = False

    @property
    def rays_per_s(self) -> float:
        return float(self.last.get("rays_per_s", 0.0))

    def add(self, stats: dict[str, Any]) -> None:
        """Append one step's stats dict (step, loss, rays_per_s, ...), in step order."""
        step = int(stats.get("step", (self.steps[-1] + 1) if self.steps else 0))
        if self.steps and step <= self.steps[-1]:
            return
        self.last = dict(stats)
        loss = stats.get("loss")
        if loss is not None and np.isfinite(float(loss)):
            self.steps.append(step)
            self.losses.append(float(loss))

    def sync(self, history) -> None:
        """Take the stats of steps newer than ours from a Trainer's `history` deque (call it
        while holding the trainer's lock: the deque grows during steps)."""
        last = self.steps[-1] if self.steps else -1
        new = []
        for st in reversed(history):
            if int(st.get("step", -1)) <= last:
                break
            new.append(st)
        for st in reversed(new):
            self.add(st)

    @classmethod
    def from_metrics(cls, path: Path) -> TrainStats:
        """Read a run's metrics.jsonl (one stats object per logged step)."""
        import json

        st = cls()
        try:
            lines = path.read_text().splitlines()
        except OSError:
            return st
        for line in lines:
            try:
                st.add(json.loads(line))
            except (ValueError, TypeError):
                continue  # a line being written right now
        return st


class TrainThread:
    """Runs `trainer.run()` (its own loop: metrics.jsonl, checkpoints, budget) in a daemon
    thread; `stop()` asks it to finish the step, checkpoint and return.

    The Trainer holds its `.lock` during each step; the viewer holds the same lock while it
    renders, so a frame always sees one consistent set of weights. Pausing holds that lock
    from the GUI thread (between steps), so renders while paused need no lock.
    """

    def __init__(self, trainer, stats: TrainStats):
        self.trainer = trainer
        self.stats = stats
        self.paused = False
        self._thread = threading.Thread(target=self._loop, name="fastenerf-train", daemon=True)

    def start(self) -> TrainThread:
        self._thread.start()
        return self

    def _loop(self) -> None:
        try:
            self.trainer.run(progress=False)
        except Exception:
            self.stats.error = traceback.format_exc(limit=3).strip().splitlines()[-1]
        finally:
            self.stats.done = True

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    @property
    def render_lock(self):
        """The lock a render must hold now (None while paused: this thread holds it)."""
        return None if self.paused else self.trainer.lock

    def pause(self) -> None:
        if not self.paused:
            self.trainer.lock.acquire()
            self.paused = True

    def resume(self) -> None:
        if self.paused:
            self.paused = False
            self.trainer.lock.release()

    def poll(self) -> None:
        """Bring `stats` up to date with the trainer's history."""
        if self.paused:
            self.stats.sync(self.trainer.history)
            return
        with self.trainer.lock:
            self.stats.sync(self.trainer.history)

    def stop(self, timeout: float = 120.0) -> None:
        """Finish the current step, write the checkpoint, and end the thread."""
        self.resume()
        deadline = time.monotonic() + timeout
        while self._thread.is_alive() and time.monotonic() < deadline:
            # again and again: `run()` clears a request made before it started
            self.trainer.request_stop()
            self._thread.join(0.1)
        self.poll()


@dataclass
class ViewSource:
    """A field to view and the context that makes it navigable.

    intrinsics: the scene camera (default field of view, `--view-index` snapshots), or None.
    views: (M, 4, 4) poses for `--view-index` (test views when the scene has them, else its
    pose grid); snap_poses: (K, 4, 4) poses the N key snaps to (test views and the grid).
    up (3,): the scene's up axis; center (3,): the orbit pivot, world units.
    """

    field: Any
    intrinsics: Intrinsics | None = None
    views: np.ndarray | None = None
    snap_poses: np.ndarray | None = None
    up: np.ndarray = field(default_factory=lambda: np.array([0.0, 1.0, 0.0]))
    center: np.ndarray = field(default_factory=lambda: np.zeros(3))
    near: float = 1e-4
    background: tuple[float, float, float] | None = None
    name: str = "field"
    out_dir: Path | None = None
    trainer: Any = None
    train_thread: TrainThread | None = None
    stats: TrainStats | None = None
    watcher: Any = None  # RunWatcher for a run folder on disk

    @property
    def lock(self):
        """The lock a render must hold (a live trainer's), or None."""
        if self.train_thread is not None:
            return self.train_thread.render_lock
        return getattr(self.trainer, "lock", None)

    # ---- constructors -----------------------------------------------------------------

    @classmethod
    def from_field(cls, f, scene=None, **kw) -> ViewSource:
        """Wrap `f`; `scene` (a loaded Scene, a SceneConfig, or None) gives cameras and up."""
        aabb = np.asarray(f.aabb.detach().cpu().numpy(), np.float64)
        src = cls(field=f, center=(aabb[:3] + aabb[3:]) / 2, **kw)
        if scene is not None:
            src._adopt_scene(scene)
        return src

    def _adopt_scene(self, scene) -> None:
        cfg = getattr(scene, "config", scene)
        root = getattr(scene, "root", None)
        self.intrinsics = Intrinsics.from_config(cfg.intrinsics, cfg.width, cfg.height)
        self.up = scene_up(cfg)
        self.near = cfg.near
        # as the trainer composites: an unset or black background means no background term
        bg = cfg.background
        self.background = None if bg is None or not any(bg) else tuple(float(c) for c in bg)
        self.name = cfg.name
        grid = None
        try:
            grid = pose_grid(cfg, root, getattr(scene, "poses", None))
        except InputError:
            pass  # a timed trajectory whose poses file is not reachable from here
        test = getattr(scene, "test_c2w", None)
        parts = [p for p in (test, grid) if p is not None and len(p)]
        self.views = test if test is not None and len(test) else grid
        self.snap_poses = np.concatenate(parts) if parts else None
        if cfg.trajectory.kind == "turntable":
            self.center = np.asarray(cfg.trajectory.center, np.float64)

    @classmethod
    def from_run(cls, run_dir: str | Path) -> ViewSource:
        """A run folder written by `fastenerf train` (finished, or still training)."""
        from fastenerf.run import load_run

        run_dir = Path(run_dir)
        if not run_dir.is_dir():
            raise InputError(f"{run_dir}: no such run folder")
        f, scene, _ = load_run(run_dir)
        src = cls.from_field(f, scene, name=run_dir.name, out_dir=run_dir)
        src.watcher = RunWatcher(run_dir)
        src.stats = src.watcher.stats()
        return src

    @classmethod
    def from_training(
        cls,
        scene_dir: str | Path,
        backend: str = "ngp",
        *,
        out_dir: str | Path | None = None,
        preset: str = "fast",
        resume: bool = False,
        **overrides,
    ) -> ViewSource:
        """Train on `scene_dir` in a background thread (`start_training()` starts it).

        overrides: TrainConfig fields (minutes, steps, rays_per_step, ...); None = preset's.
        """
        from fastenerf.config import train_preset
        from fastenerf.data.formats.native import load_scene
        from fastenerf.train import Trainer

        scene = load_scene(scene_dir)
        cfg = train_preset(preset, backend, **overrides)
        out = Path(out_dir) if out_dir else Path("runs") / f"{scene.config.name}-{backend}-view"
        trainer = Trainer(scene, cfg, out, resume=resume)
        if cfg.step_mode == "auto" and trainer.step_mode == "graph":
            # the GUI thread's own CUDA work (a frame's copy to the host) may not run while
            # this thread captures a step
            trainer.set_step_mode("device")
        return cls.from_field(
            trainer.field,
            scene,
            name=f"{scene.config.name} ({backend})",
            out_dir=out,
            trainer=trainer,
            stats=TrainStats(),
        )

    def start_training(self) -> None:
        if self.trainer is not None and self.train_thread is None:
            self.train_thread = TrainThread(self.trainer, self.stats).start()

    def close(self) -> None:
        """Stop live training (it checkpoints first)."""
        if self.train_thread is not None:
            self.train_thread.stop()
            self.train_thread = None

    def poll(self) -> bool:
        """Per GUI frame: refresh training stats; reload a run whose checkpoint changed on
        disk. True when the field was replaced."""
        if self.train_thread is not None:
            self.train_thread.poll()
        if self.trainer is not None and self.trainer.field is not self.field:
            self.field = self.trainer.field  # a new field (refine_restart)
            return True
        if self.watcher is not None:
            f = self.watcher.newer_field()
            if self.watcher.metrics_changed():
                self.stats = self.watcher.stats()
            if f is not None:
                self.field = f
                return True
        return False

    # ---- cameras ------------------------------------------------------------------------

    def default_camera(self) -> OrbitCamera:
        """The first view when there is one (orbiting the scene centre), else a level camera
        on +z at three box radii."""
        if self.views is not None and len(self.views):
            cam = OrbitCamera(np.eye(4), 1.0, self.up)
            cam.set_pose(self.views[0], self.center)
            cam.home = (cam.c2w.copy(), cam.distance)
            return cam
        aabb = np.asarray(self.field.aabb.detach().cpu().numpy(), np.float64)
        r = float(np.linalg.norm(aabb[3:] - aabb[:3])) / 2
        return OrbitCamera.looking_at(self.center + np.array([0, 0, 3 * r]), self.center, self.up)

    def model_version(self):
        """Changes whenever the weights may have changed (the step count, live or on disk)."""
        if self.stats is not None and self.stats.steps:
            return self.stats.steps[-1]
        return None


class RunWatcher:
    """Watches a run folder that may still be training in another process: a newer
    checkpoint.pt means new weights, a grown metrics.jsonl new stats. Checks at most every
    `interval_s` seconds."""

    def __init__(self, run_dir: Path, interval_s: float = 2.0):
        self.run_dir = Path(run_dir)
        self.interval_s = interval_s
        self._ckpt = self._stamp("checkpoint.pt")
        self._metrics = self._stamp("metrics.jsonl")
        self._checked = time.monotonic()
        self._metrics_dirty = False

    def _stamp(self, name: str):
        try:
            st = (self.run_dir / name).stat()
        except OSError:
            return None
        return st.st_mtime_ns, st.st_size

    def newer_field(self):
        """A freshly loaded field when the checkpoint changed since the last call, else None."""
        now = time.monotonic()
        if now - self._checked < self.interval_s:
            return None
        self._checked = now
        m = self._stamp("metrics.jsonl")
        if m != self._metrics:
            self._metrics, self._metrics_dirty = m, True
        s = self._stamp("checkpoint.pt")
        if s == self._ckpt:
            return None
        from fastenerf.run import load_run

        try:
            f, _, _ = load_run(self.run_dir)
        except InputError:
            return None  # caught between writes: try again next time
        self._ckpt = s
        return f

    def metrics_changed(self) -> bool:
        dirty, self._metrics_dirty = self._metrics_dirty, False
        return dirty

    def stats(self) -> TrainStats | None:
        from fastenerf.run import read_progress

        path = self.run_dir / "metrics.jsonl"
        if not path.is_file():
            return None
        st = TrainStats.from_metrics(path)
        st.done = bool(read_progress(self.run_dir).get("finished"))
        return st
