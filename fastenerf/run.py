"""The run folder: what `fastenerf train` writes and every later command reads.

A run folder holds
    config.json       resolved TrainConfig, SceneConfig, scene path, scene fingerprint, the
                      field's constructor arguments and `built`: the parts this scene switched on
    checkpoint.pt     field, optimiser, step, times, RNG and sampler state (atomic writes)
    progress.json     step and train/eval seconds of the last checkpoint, `finished`
    metrics.jsonl     one JSON object per logged step
    metrics.json      the last `fastenerf eval` of it (eval/ holds its pictures)

This module knows the files, not the training: it imports the config, the data formats and
the fields, nothing above them (the trainer and the evaluation import it).
"""

from __future__ import annotations

import json
import pickle
import threading
import zipfile
from pathlib import Path
from typing import Any

import torch

from .config import SceneConfig, TrainConfig
from .data.formats import load_scene_folder
from .data.formats.native import Scene
from .errors import InputError
from .fields import Field, field_from_config
from .io import atomic_path, read_json_object, write_json

CHECKPOINT = "checkpoint.pt"
CONFIG = "config.json"
PROGRESS = "progress.json"
METRICS_LOG = "metrics.jsonl"
CHECKPOINT_VERSION = 1


def resolve_device(name: str | None = "auto") -> torch.device:
    """ "auto" (or None) -> the first CUDA device if there is one, else the CPU."""
    if not name or name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(name)
    except (RuntimeError, ValueError):
        raise InputError(f"device {name!r} is not one of auto, cpu, cuda, cuda:N") from None
    if dev.type not in ("cpu", "cuda"):
        raise InputError(f"device {name!r} is not one of auto, cpu, cuda, cuda:N")
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


def read_json_file(path: Path, what: str) -> dict:
    """A JSON object from `path`, or a one-line InputError naming the file."""
    if not path.is_file():
        raise InputError(f"{path.parent}: not a {what} (no {path.name})")
    return read_json_object(path)


def read_run_config(run_dir: str | Path) -> dict:
    return read_json_file(Path(run_dir) / CONFIG, "training run")


def read_progress(run_dir: str | Path) -> dict:
    """progress.json of a run, or {} when it has none yet (a run still starting)."""
    try:
        return json.loads((Path(run_dir) / PROGRESS).read_text())
    except (OSError, json.JSONDecodeError):
        return {}


def write_progress(run_dir: str | Path, progress: dict) -> Path:
    return write_json(Path(run_dir) / PROGRESS, progress)


def save_checkpoint(path: str | Path, state: dict) -> Path:
    """torch.save `state` to `path` through a temporary file and a rename (never half-written)."""
    path = Path(path)
    with atomic_path(path) as tmp:
        torch.save(state, tmp)
    return path


class CheckpointWriter:
    """Writes RUN/checkpoint.pt and then RUN/progress.json, each atomically; in a background
    thread when asked, one write at a time (a write waits for the one before it)."""

    def __init__(self, run_dir: str | Path):
        self.run_dir = Path(run_dir)
        self._thread: threading.Thread | None = None

    def write(self, state: dict, progress: dict, background: bool = False) -> Path:
        """Write `state` (CPU tensors: training may go on meanwhile) and `progress`; returns
        the checkpoint's path."""
        self.wait()
        path = self.run_dir / CHECKPOINT

        def write() -> None:
            save_checkpoint(path, state)
            write_progress(self.run_dir, progress)

        if background:
            self._thread = threading.Thread(target=write, name="fastenerf-checkpoint")
            self._thread.start()
        else:
            write()
        return path

    def wait(self) -> None:
        """Block until a checkpoint being written in the background is on disk."""
        if self._thread is not None:
            self._thread.join()
            self._thread = None


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


def field_from_checkpoint(ck: dict, where: Path) -> Field:
    """The field a checkpoint saved (rebuilt from its config, weights loaded), on the CPU."""
    field = field_from_config(ck["backend"], ck["field_config"])
    try:
        field.load_state_dict(ck["field"])
    except RuntimeError as e:
        raise InputError(
            f"{where}: weights do not fit the field ({str(e).splitlines()[0][:120]})"
        ) from None
    return field


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
        cfg = TrainConfig.from_dict(conf["train"], f"{run_dir}/{CONFIG} train")
        sc = SceneConfig.from_dict(conf["scene"], f"{run_dir}/{CONFIG} scene")
    except KeyError as e:
        raise InputError(f"{run_dir}/{CONFIG}: missing section {e}") from None
    dev = resolve_device(device)
    ck = load_checkpoint(run_dir / CHECKPOINT, map_location=dev)
    field = field_from_checkpoint(ck, run_dir / CHECKPOINT).to(dev).eval()
    scene: Scene | SceneConfig = sc
    scene_dir = Path(conf.get("scene_dir", ""))
    if scene_dir.is_dir():
        try:
            scene = load_scene_folder(scene_dir)
            scene.config.cylinder = sc.cylinder  # --cylinder may have overridden the folder's
        except InputError:
            scene = sc
    return field, scene, cfg
