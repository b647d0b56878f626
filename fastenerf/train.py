"""The training loop: windows -> rays -> field -> event loss -> Adam (DESIGN §1, §3).

A run folder holds
    config.json       resolved TrainConfig, SceneConfig, scene path, and `built`: the parts
                      this scene switched on (Bayer, distortion, cylinder, background, ...)
    checkpoint.pt     field, optimiser, step, times, every RNG state and the sampler state
                      (written atomically every `checkpoint_every_s`, at the end, on Ctrl-C)
    progress.json     step and train/eval seconds of the last checkpoint
    metrics.jsonl     one JSON object per logged step: step, elapsed_s, loss, rays_per_s, lr,
                      loss parts, and eval_psnr when a quick evaluation ran
`--resume` restores all of it, so a resumed run takes the same next steps as one that never
stopped (bit-identical on CPU). Training time excludes evaluation and checkpoint time; both
are recorded.
"""

from __future__ import annotations

import json
import math
import pickle
import random
import signal
import threading
import time
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.profiler import record_function

from .config import SceneConfig, TrainConfig
from .data.events import EventIndex
from .data.formats.native import Scene
from .data.rig import Intrinsics
from .errors import InputError
from .fields import Field, field_from_config, make_field
from .io import atomic_path, write_json
from .losses import total_loss
from .sampling import RaySampler, WindowSampler

CHECKPOINT = "checkpoint.pt"
CHECKPOINT_VERSION = 1
HISTORY_MAX = 100_000
# Batches the sampler draws at once: its host cost per block is about that of one batch.
SAMPLER_PREFETCH = 16
# Options that may change between a run and its resume: budget and bookkeeping only.
RESUMABLE_KEYS = {
    "steps",
    "minutes",
    "checkpoint_every_s",
    "eval_every_s",
    "eval_views",
    "eval_scale",
    "log_every",
    "chunk",
    "device",
}


def resolve_device(name: str = "auto") -> torch.device:
    """ "auto" -> the first CUDA device if there is one, else the CPU."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(name)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise InputError(f"device {name!r} requested but CUDA is not available")
    return dev


def scene_background(sc: SceneConfig) -> list[float] | None:
    """The background the field composites over, or None: unset or black means no term."""
    if sc.background is None or not any(sc.background):
        return None
    return [float(c) for c in sc.background]


def scene_fingerprint(scene: Scene) -> dict[str, Any]:
    """What must not change under a resumed run: sensor, time range, events."""
    sc, ev = scene.config, scene.events
    return {
        "name": sc.name,
        "width": sc.width,
        "height": sc.height,
        "n_events": len(ev),
        "t_first": int(ev.t[0]) if len(ev) else None,
        "t_last": int(ev.t[-1]) if len(ev) else None,
        "t_start_us": sc.t_start_us,
        "t_end_us": sc.t_end_us,
        "n_views": sc.n_views,
    }


class Trainer:
    """Trains one field on one scene into `out_dir` (see the module docstring).

    scene: a loaded Scene; cfg: TrainConfig (None values resolved for the scene and device);
    resume: continue from out_dir/checkpoint.pt (options other than the budget must match).
    Attributes: field, rig, lock (held during a step: a viewer thread may render between
    steps), history (recent stats dicts), step_count, train_seconds, eval_seconds.
    """

    def __init__(self, scene: Scene, cfg: TrainConfig, out_dir: str | Path, resume: bool = False):
        self.out_dir = Path(out_dir)
        self.device = resolve_device(cfg.device if cfg.device else "auto")
        self.cfg = cfg.resolved(scene.config, str(self.device))
        self.scene = scene
        sc = scene.config
        ckpt_path = self.out_dir / CHECKPOINT
        if not resume and ckpt_path.exists():
            raise InputError(
                f"{self.out_dir}: already holds a training run; pass --resume to "
                "continue it or choose another --out"
            )
        if resume and not ckpt_path.exists():
            raise InputError(f"{self.out_dir}: no {CHECKPOINT} to resume from")
        checkpoint = load_checkpoint(ckpt_path) if resume else None
        if checkpoint is not None:
            self._check_compatible(checkpoint)

        seed = self.cfg.seed
        random.seed(seed)
        np.random.seed(seed)
        torch.manual_seed(seed)

        self.rig = scene.rig()
        self.index = EventIndex(
            scene.events,
            sc.pos_threshold,
            sc.neg_threshold,
            sc.polarity_offset,
            t_start=sc.t_start_us,
            t_end=sc.t_end_us,
            loop=sc.loop,
        )
        self.field: Field = make_field(self.cfg.backend, sc, self.cfg).to(self.device)
        self.optimizer = self._make_optimizer()
        self.windows = WindowSampler(
            sc.n_views,
            sc.t_start_us,
            sc.t_end_us,
            self.cfg.win_min,
            self.cfg.win_max,
            self.cfg.win_redraw,
            sc.loop,
            seed,
        )
        self.sampler = RaySampler(
            self.index,
            self.rig,
            self.windows,
            rays_per_step=self.cfg.rays_per_step,
            windows_per_step=self.cfg.windows_per_step,
            neg_ratio=self.cfg.neg_ratio,
            device=self.device,
            seed=seed,
            prefetch=SAMPLER_PREFETCH,
        )
        bg = scene_background(sc)
        self.background = None if bg is None else torch.tensor(bg, device=self.device)
        self.amp = bool(self.cfg.amp and self.device.type == "cuda")
        self.lock = threading.Lock()
        self.history: list[dict] = []  # recent steps' stats (trimmed to HISTORY_MAX)
        self.step_count = 0
        self.train_seconds = 0.0
        self.eval_seconds = 0.0
        self.wall_offset = 0.0
        self.last_eval_psnr: float | None = None
        self.skipped_steps = 0
        self._stop = False
        self._eval_cache: tuple | None = None
        self.out_dir.mkdir(parents=True, exist_ok=True)
        if hasattr(self.field, "observe_cameras"):
            # Space no training camera sees stays empty (DESIGN §4): up to 100 grid views.
            c2w = self.sampler.grid_c2w[:-1].cpu().numpy()
            c2w = c2w[np.unique(np.linspace(0, len(c2w) - 1, 100).round().astype(int))]
            self.field.observe_cameras(self.rig.intrinsics.K, c2w, sc.width, sc.height, sc.near)
        if checkpoint is not None:
            self._restore(checkpoint)
            self._trim_metrics()
        self.write_config()

    # -- set-up ------------------------------------------------------------------------------

    def _make_optimizer(self) -> torch.optim.Optimizer:
        groups = (
            self.field.param_groups()
            if hasattr(self.field, "param_groups")
            else [{"params": [p for p in self.field.parameters() if p.requires_grad]}]
        )
        for g in groups:
            g.setdefault("lr", self.cfg.lr)
            g["lr_scale"] = g.get("lr", self.cfg.lr) / self.cfg.lr
        return torch.optim.Adam(
            groups, lr=self.cfg.lr, betas=tuple(self.cfg.adam_betas), eps=self.cfg.adam_eps
        )

    def built(self) -> dict[str, Any]:
        """The parts this scene switched on (saved in config.json)."""
        sc = self.scene.config
        parts = {
            "bayer": sc.bayer,
            "mono_luminance": sc.bayer is None,
            "distortion": self.rig.intrinsics.distorted,
            "cylinder": sc.cylinder is not None,
            "background": self.background is not None,
            "loop_wrap": sc.loop,
            "distortion_loss": self.cfg.distortion_weight > 0,
            "event_targets": self.sampler.target_backend,
            "amp": "bf16" if self.amp else "off",
            "device": str(self.device),
        }
        if hasattr(self.field, "built"):
            parts.update(self.field.built())
        return parts

    def write_config(self) -> Path:
        return write_json(
            self.out_dir / "config.json",
            {
                "train": self.cfg.to_dict(),
                "scene": self.scene.config.to_dict(),
                "scene_dir": str(Path(self.scene.root).resolve()),
                "scene_fingerprint": scene_fingerprint(self.scene),
                "field": self.field.config_dict(),
                "built": self.built(),
                "versions": {"torch": torch.__version__, "fastenerf": _version()},
            },
        )

    # -- one step ----------------------------------------------------------------------------

    def lr_at(self, step: int) -> float:
        """Learning rate for `step`: warm-up, then constant or exponential decay to lr_final."""
        c = self.cfg
        lr = c.lr
        if c.lr_final is not None and c.lr_final != c.lr:
            lr = c.lr * (c.lr_final / c.lr) ** self.progress(step)
        if c.lr_warmup_steps > 0:
            lr *= min(1.0, (step + 1) / c.lr_warmup_steps)
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

    def step(self) -> dict[str, Any]:
        """One optimisation step; returns stats (step, loss, rays_per_s, elapsed_s, lr, ...)."""
        with self.lock:
            t_begin = time.perf_counter()
            cfg = self.cfg
            lr = self.lr_at(self.step_count)
            for g in self.optimizer.param_groups:
                g["lr"] = lr * g.get("lr_scale", 1.0)
            self.field.train()
            # The named ranges are what benchmarks.profile_step attributes time to (a range
            # costs ~1 µs when no profiler runs).
            with record_function("grid_update"):
                self.field.update(self.step_count)
            with record_function("sample_rays"):
                batch = self.sampler.sample()
            with (
                record_function("render"),
                torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.amp),
            ):
                out = self.field.render(
                    batch.rays_o,
                    batch.rays_d,
                    near=self.scene.config.near,
                    background=self.background,
                    train=True,
                )
            with record_function("loss"):
                loss, parts = total_loss(
                    out,
                    batch.target,
                    batch.channel,
                    gamma=cfg.gamma,
                    eps=cfg.log_eps,
                    distortion_weight=cfg.distortion_weight,
                )
                self.optimizer.zero_grad(set_to_none=True)
                loss_value = float(loss.detach())
            if math.isfinite(loss_value):
                with record_function("backward"):
                    loss.backward()
                with record_function("optimizer"):
                    self.optimizer.step()
            else:  # never let a non-finite loss reach the weights
                self.skipped_steps += 1
            self.step_count += 1
            dt = time.perf_counter() - t_begin
            self.train_seconds += dt
            n_rays = int(batch.rays_o.shape[0])
            stats = {
                "step": self.step_count,
                "loss": loss_value,
                "rays_per_s": n_rays / max(dt, 1e-9),
                "elapsed_s": self.train_seconds,
                "lr": lr,
                "positive_fraction": float(batch.positive.float().mean()),
                **{k: float(v) for k, v in parts.items()},
            }
            if "n_samples" in out:
                stats["samples_per_ray"] = int(out["n_samples"]) / n_rays
            if self.skipped_steps:
                stats["skipped_steps"] = self.skipped_steps
            self.history.append(stats)
            if len(self.history) > HISTORY_MAX:
                del self.history[: HISTORY_MAX // 2]
            return stats

    # -- the loop ----------------------------------------------------------------------------

    def done(self) -> bool:
        c = self.cfg
        if c.steps is not None and self.step_count >= c.steps:
            return True
        return c.minutes is not None and self.train_seconds >= 60.0 * c.minutes

    def request_stop(self) -> None:
        """Ask `run()` to stop after the current step (and checkpoint); thread-safe."""
        self._stop = True

    def run(self, progress: bool = True) -> dict[str, Any]:
        """Train until the budget is spent or Ctrl-C; checkpoint; return a summary.

        The first Ctrl-C finishes the current step, writes a checkpoint and returns with
        `interrupted: True`; a second one aborts at once (the last checkpoint stays valid).
        """
        from tqdm import tqdm

        cfg = self.cfg
        self._stop = False
        wall_start = time.perf_counter() - self.wall_offset
        last_ckpt = last_eval = time.perf_counter()
        by_steps = cfg.steps is not None
        total = cfg.steps if by_steps else int(round(60 * cfg.minutes))
        pbar = tqdm(
            total=total,
            initial=self.step_count if by_steps else int(self.train_seconds),
            unit="step" if by_steps else "s",
            disable=not progress,
            dynamic_ncols=True,
            desc=f"train {cfg.backend}",
        )
        old_handler = self._install_sigint()
        metrics = open(self.out_dir / "metrics.jsonl", "a")  # noqa: SIM115 - closed in finally
        interrupted = False
        last_bar = 0.0
        try:
            while not self.done() and not self._stop:
                stats = self.step()
                now = time.perf_counter()
                if cfg.eval_every_s > 0 and now - last_eval >= cfg.eval_every_s:
                    stats["eval_psnr"] = self.quick_eval()
                    last_eval = time.perf_counter()
                if (
                    self.step_count % cfg.log_every == 0
                    or self.step_count <= 10
                    or "eval_psnr" in stats
                    or self.done()
                ):
                    stats["wall_s"] = time.perf_counter() - wall_start
                    metrics.write(json.dumps(stats) + "\n")
                    metrics.flush()
                if now - last_bar > 0.25 or self.done():
                    pbar.n = self.step_count if by_steps else min(total, int(self.train_seconds))
                    pbar.set_postfix(self._postfix(stats), refresh=True)
                    last_bar = now
                if cfg.checkpoint_every_s > 0 and now - last_ckpt >= cfg.checkpoint_every_s:
                    self.wall_offset = time.perf_counter() - wall_start
                    self.save_checkpoint()
                    last_ckpt = time.perf_counter()
            interrupted = self._stop
        # A second Ctrl-C (KeyboardInterrupt) propagates: the state may be torn mid-step, so
        # no checkpoint is written and the last one on disk stays valid.
        finally:
            self._restore_sigint(old_handler)
            metrics.close()
            pbar.close()
        self.wall_offset = time.perf_counter() - wall_start
        path = self.save_checkpoint(finished=not interrupted)
        return {
            "steps": self.step_count,
            "train_seconds": self.train_seconds,
            "eval_seconds": self.eval_seconds,
            "wall_seconds": self.wall_offset,
            "loss": self.history[-1]["loss"] if self.history else None,
            "last_eval_psnr": self.last_eval_psnr,
            "interrupted": interrupted,
            "checkpoint": str(path),
            "out_dir": str(self.out_dir),
        }

    def _postfix(self, stats: dict) -> dict[str, str]:
        post = {
            "loss": f"{stats['loss']:.4f}",
            "rays/s": f"{stats['rays_per_s']:.3g}",
            "t": f"{self.train_seconds:.0f}s",
        }
        if self.last_eval_psnr is not None:
            post["psnr"] = f"{self.last_eval_psnr:.2f}"
        return post

    def _install_sigint(self):
        if threading.current_thread() is not threading.main_thread():
            return None

        def handler(signum, frame):
            if self._stop:  # second Ctrl-C: abort now
                raise KeyboardInterrupt
            self._stop = True

        return signal.signal(signal.SIGINT, handler)

    @staticmethod
    def _restore_sigint(old) -> None:
        if old is not None and threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, old)

    # -- quick evaluation --------------------------------------------------------------------

    def quick_eval(self) -> float | None:
        """Colour-corrected PSNR on a few test views at reduced size (time not counted)."""
        from .evaluate import load_gt, quick_psnr
        from .render import render_image

        sc = self.scene.config
        if self.scene.test_c2w is None or not self.scene.test_rgb_paths:
            return None
        t = time.perf_counter()
        with self.lock:
            if self._eval_cache is None:
                n = len(self.scene.test_c2w)
                views = np.unique(
                    np.linspace(0, n - 1, max(1, self.cfg.eval_views)).round().astype(int)
                )
                intr = Intrinsics.from_config(sc.intrinsics, sc.width, sc.height)
                intr = intr.scaled(self.cfg.eval_scale)
                gt = load_gt(self.scene, views, (intr.height, intr.width))
                self._eval_cache = (views, intr, gt)
            views, intr, gt = self._eval_cache
            with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.amp):
                pred = np.stack(
                    [
                        render_image(
                            self.field,
                            self.scene.test_c2w[i],
                            intr,
                            near=sc.near,
                            background=self.background,
                            chunk=self.cfg.chunk,
                        )["rgb"]
                        .clamp(0, 1)
                        .cpu()
                        .numpy()
                        for i in views
                    ]
                )
        self.last_eval_psnr = float(quick_psnr(pred, gt))
        self.eval_seconds += time.perf_counter() - t
        return self.last_eval_psnr

    # -- checkpoints -------------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        rng = {
            "torch": torch.get_rng_state(),
            "python": random.getstate(),
            "numpy": _np_state_to_torch(np.random.get_state()),
        }
        if torch.cuda.is_available():
            rng["cuda"] = torch.cuda.get_rng_state_all()
        sampler = self.sampler.state_dict()
        lengths = sampler["windows"]["lengths"]
        # a new dict: the sampler's own state must not change when a checkpoint is written
        lengths = None if lengths is None else torch.from_numpy(lengths)
        sampler = {**sampler, "windows": {**sampler["windows"], "lengths": lengths}}
        return {
            "format": "fastenerf-checkpoint",
            "version": CHECKPOINT_VERSION,
            "backend": self.cfg.backend,
            "field_config": self.field.config_dict(),
            "field": self.field.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "step": self.step_count,
            "train_seconds": self.train_seconds,
            "eval_seconds": self.eval_seconds,
            "wall_seconds": self.wall_offset,
            "last_eval_psnr": None if self.last_eval_psnr is None else float(self.last_eval_psnr),
            "skipped_steps": self.skipped_steps,
            "train_config": self.cfg.to_dict(),
            "scene_fingerprint": scene_fingerprint(self.scene),
            "rng": rng,
            "sampler": sampler,
        }

    def save_checkpoint(self, finished: bool = False) -> Path:
        """Write RUN/checkpoint.pt atomically (and progress.json); returns its path."""
        path = self.out_dir / CHECKPOINT
        with self.lock:
            state = self.state_dict()
            with atomic_path(path) as tmp:
                torch.save(state, tmp)
        write_json(
            self.out_dir / "progress.json",
            {
                "step": self.step_count,
                "train_seconds": self.train_seconds,
                "eval_seconds": self.eval_seconds,
                "wall_seconds": self.wall_offset,
                "last_eval_psnr": self.last_eval_psnr,
                "finished": finished,
            },
        )
        return path

    def _check_compatible(self, ck: dict) -> None:
        where = self.out_dir / CHECKPOINT
        if ck.get("backend") != self.cfg.backend:
            raise InputError(
                f"{where}: cannot resume: the run uses backend "
                f"{ck.get('backend')!r}, not {self.cfg.backend!r}"
            )
        fp = scene_fingerprint(self.scene)
        if ck.get("scene_fingerprint") != fp:
            old = ck.get("scene_fingerprint") or {}
            diff = sorted(k for k in fp if old.get(k) != fp[k])
            raise InputError(
                f"{where}: cannot resume on a different scene (differs in {', '.join(diff)})"
            )
        saved = ck.get("train_config", {})
        now = self.cfg.to_dict()
        diff = sorted(k for k in now if k not in RESUMABLE_KEYS and saved.get(k) != now[k])
        if diff:
            details = ", ".join(f"{k}: {saved.get(k)!r} -> {now[k]!r}" for k in diff[:4])
            raise InputError(f"{where}: cannot resume with different training options ({details})")

    def _restore(self, ck: dict) -> None:
        where = self.out_dir / CHECKPOINT
        if ck.get("field_config") != self.field.config_dict():
            raise InputError(
                f"{where}: cannot resume: the field was built differently (backend options changed)"
            )
        try:
            self.field.load_state_dict(ck["field"])
            self.optimizer.load_state_dict(ck["optimizer"])
            self.sampler.load_state_dict(
                {
                    "windows": {
                        "rng": ck["sampler"]["windows"]["rng"],
                        "lengths": _maybe_numpy(ck["sampler"]["windows"]["lengths"]),
                    },
                    "gen": ck["sampler"]["gen"],
                    "position": int(ck["sampler"].get("position", 0)),
                }
            )
            rng = ck["rng"]
            torch.set_rng_state(rng["torch"])
            random.setstate(rng["python"])
            np.random.set_state(_np_state_from_torch(rng["numpy"]))
            if "cuda" in rng and torch.cuda.is_available():
                torch.cuda.set_rng_state_all(rng["cuda"])
        except (KeyError, RuntimeError, ValueError, TypeError) as e:
            raise InputError(
                f"{where}: checkpoint does not match this run ({e})".split("\n")[0]
            ) from None
        self.step_count = int(ck["step"])
        self.train_seconds = float(ck["train_seconds"])
        self.eval_seconds = float(ck["eval_seconds"])
        self.wall_offset = float(ck.get("wall_seconds", 0.0))
        self.last_eval_psnr = ck.get("last_eval_psnr")
        self.skipped_steps = int(ck.get("skipped_steps", 0))

    def _trim_metrics(self) -> None:
        """Drop metrics.jsonl lines logged after the checkpoint (they will be redone)."""
        path = self.out_dir / "metrics.jsonl"
        if not path.exists():
            return
        keep = []
        for line in path.read_text().splitlines():
            try:
                if json.loads(line).get("step", 0) <= self.step_count:
                    keep.append(line)
            except json.JSONDecodeError:
                continue  # a line cut by a crash
        with atomic_path(path) as tmp:
            tmp.write_text("".join(line + "\n" for line in keep))


# -- checkpoints and runs on disk ------------------------------------------------------------


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> dict:
    """Read a checkpoint (weights-only unpickling) or raise a one-line InputError."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: checkpoint not found")
    try:
        ck = torch.load(path, map_location=map_location, weights_only=True)
    except (
        RuntimeError,
        EOFError,
        OSError,
        ValueError,
        pickle.UnpicklingError,
        zipfile.BadZipFile,
        AttributeError,
        KeyError,
    ) as e:
        msg = str(e).split("\n")[0][:120]
        if "Weights only load failed" in msg:
            msg = "holds objects other than tensors and plain values"
        raise InputError(f"{path}: checkpoint is corrupt or truncated ({msg})") from None
    if not isinstance(ck, dict) or ck.get("format") != "fastenerf-checkpoint":
        raise InputError(f"{path}: not a fastenerf checkpoint")
    if ck.get("version") != CHECKPOINT_VERSION:
        raise InputError(
            f"{path}: checkpoint version {ck.get('version')} is not supported "
            f"(expected {CHECKPOINT_VERSION})"
        )
    return ck


def read_run_config(run_dir: str | Path) -> dict:
    path = Path(run_dir) / "config.json"
    if not path.is_file():
        raise InputError(f"{run_dir}: not a training run (no config.json)")
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise InputError(f"{path}: not valid JSON ({e})") from None


def read_progress(run_dir: str | Path) -> dict:
    path = Path(run_dir) / "progress.json"
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return {}


def load_run(
    run_dir: str | Path, device: str = "auto"
) -> tuple[Field, Scene | SceneConfig, TrainConfig]:
    """Rebuild the trained field of a run folder, in eval mode on `device`.

    Returns (field, scene, cfg): scene is the loaded Scene when its folder still exists,
    else the SceneConfig saved with the run.
    """
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise InputError(f"{run_dir}: no such run folder")
    conf = read_run_config(run_dir)
    try:
        cfg = TrainConfig.from_dict(conf["train"], f"{run_dir}/config.json train")
        sc = SceneConfig.from_dict(conf["scene"], f"{run_dir}/config.json scene")
    except KeyError as e:
        raise InputError(f"{run_dir}/config.json: missing section {e}") from None
    dev = resolve_device(device)
    ck = load_checkpoint(run_dir / CHECKPOINT, map_location=dev)
    field = field_from_config(ck["backend"], ck["field_config"])
    try:
        field.load_state_dict(ck["field"])
    except RuntimeError as e:
        raise InputError(
            f"{run_dir / CHECKPOINT}: weights do not fit the field ({str(e).splitlines()[0][:120]})"
        ) from None
    field.to(dev).eval()
    scene: Scene | SceneConfig = sc
    scene_dir = Path(conf.get("scene_dir", ""))
    if scene_dir.is_dir():
        from .data.formats import load_scene_folder

        try:
            scene = load_scene_folder(scene_dir)
        except InputError:
            scene = sc
    return field, scene, cfg


def _np_state_to_torch(state: tuple) -> dict:
    name, keys, pos, has_gauss, cached = state
    return {
        "name": name,
        "keys": torch.from_numpy(keys.astype(np.int64)),
        "pos": int(pos),
        "has_gauss": int(has_gauss),
        "cached": float(cached),
    }


def _np_state_from_torch(d: dict) -> tuple:
    return (d["name"], d["keys"].numpy().astype(np.uint32), d["pos"], d["has_gauss"], d["cached"])


def _maybe_numpy(x):
    return None if x is None else x.cpu().numpy()


def _version() -> str:
    from . import __version__

    return __version__
