"""A trainer's checkpoint state, beside the trainer rather than in it.

`trainer_state` gathers everything a resumed run needs to take the same next steps as one
that never stopped (bit-identical on CPU): field, optimiser, step, clocks, every RNG and the
sampler's state. `check_compatible` refuses a resume whose scene or options differ;
`restore` puts a checkpoint back into a freshly built trainer.
"""

from __future__ import annotations

import dataclasses
import json
import random
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from .config import TrainConfig
from .errors import InputError
from .field_restart import RestartClock
from .fields import canonical_field_config
from .io import atomic_path
from .optim import fit_state
from .run import CHECKPOINT, CHECKPOINT_VERSION, METRICS_LOG, scene_fingerprint

if TYPE_CHECKING:
    from .train import Trainer

# Options that may change between a run and its resume: budget and bookkeeping only.
RESUMABLE_KEYS = {
    "steps",
    "minutes",
    "checkpoint_every_s",
    "checkpoint_every_steps",
    "step_mode",
    "eval_every_s",
    "eval_views",
    "eval_scale",
    "log_every",
    "chunk",
    "device",
}

# The sampler's window states a checkpoint holds: the current block's, and the lengths now.
WINDOW_STATES = ("windows", "windows_now")


def cpu_copy(obj: Any) -> Any:
    """A deep copy of a state dict with every tensor detached, cloned and on the CPU, so it
    can be written while training goes on."""
    if isinstance(obj, torch.Tensor):
        return obj.detach().to("cpu", copy=True)
    if isinstance(obj, dict):
        return {k: cpu_copy(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(cpu_copy(v) for v in obj)
    return obj


def trainer_state(tr: Trainer) -> dict[str, Any]:
    """The checkpoint of `tr` (tensors are live references: copy before training on)."""
    rng = {
        "torch": torch.get_rng_state(),
        "python": random.getstate(),
        "numpy": _np_state_to_torch(np.random.get_state()),
    }
    if torch.cuda.is_available():
        rng["cuda"] = torch.cuda.get_rng_state_all()
    sampler = tr.sampler.state_dict()
    # new dicts: the sampler's own state must not change when a checkpoint is written
    sampler = {**sampler, **{k: _windows_saved(sampler[k]) for k in WINDOW_STATES if k in sampler}}
    state = {
        "format": "fastenerf-checkpoint",
        "version": CHECKPOINT_VERSION,
        "backend": tr.cfg.backend,
        "field_config": tr.field.config_dict(),
        "field": tr.field.state_dict(),
        "optimizer": tr.optimizer.state_dict(),
        "step": tr.step_count,
        "train_seconds": tr.train_seconds,
        "eval_seconds": tr.eval_seconds,
        "wall_seconds": tr.wall_seconds,
        "last_eval_psnr": None if tr.last_eval_psnr is None else float(tr.last_eval_psnr),
        "skipped_steps": tr.skipped_steps,
        "train_config": tr.cfg.to_dict(),
        "scene_fingerprint": scene_fingerprint(tr.scene),
        "rng": rng,
        "sampler": sampler,
    }
    if tr.selfcal is not None:  # learnt poses / thresholds (issue #20)
        state["self_calibration"] = tr.selfcal.state_dict()
    if tr.clock != RestartClock():  # refine_restart's: made (its schedules' start) or declined
        state["restart"] = tr.clock.state_dict()
    if tr.batch_size is not None:  # the samples per ray its next decisions read
        state["batch_size"] = tr.batch_size.state_dict()
    return state


def progress_record(tr: Trainer, finished: bool) -> dict[str, Any]:
    """What progress.json says of `tr` at a checkpoint."""
    return {
        "step": tr.step_count,
        "train_seconds": tr.train_seconds,
        "eval_seconds": tr.eval_seconds,
        "wall_seconds": tr.wall_seconds,
        "last_eval_psnr": tr.last_eval_psnr,
        "finished": finished,
        **({"self_calibration": tr.selfcal.stats()} if tr.selfcal is not None else {}),
        **({"field_restart": tr.clock.state_dict()} if tr.clock != RestartClock() else {}),
    }


def check_compatible(tr: Trainer, ck: dict) -> None:
    """Refuse (one line) to resume `ck` with another backend, scene or training options."""
    where = tr.out_dir / CHECKPOINT
    if ck.get("backend") != tr.cfg.backend:
        raise InputError(
            f"{where}: cannot resume: the run uses backend "
            f"{ck.get('backend')!r}, not {tr.cfg.backend!r}"
        )
    fp = scene_fingerprint(tr.scene)
    if ck.get("scene_fingerprint") != fp:
        old = ck.get("scene_fingerprint") or {}
        diff = sorted(k for k in fp if old.get(k) != fp[k])
        raise InputError(
            f"{where}: cannot resume on a different scene (differs in {', '.join(diff)})"
        )
    saved = ck.get("train_config", {})
    now = tr.cfg.to_dict()
    diff = sorted(
        k for k in now if k not in RESUMABLE_KEYS and k in saved and saved.get(k) != now[k]
    )
    diff += sorted(k for k in now if k not in saved and not _is_default_of_new_key(k, now[k]))
    if diff:
        details = ", ".join(f"{k}: {saved.get(k)!r} -> {now[k]!r}" for k in diff[:4])
        raise InputError(f"{where}: cannot resume with different training options ({details})")


def _is_default_of_new_key(key: str, value: Any) -> bool:
    """A key added to TrainConfig after a run was saved is compatible at its default value."""
    f = TrainConfig.__dataclass_fields__.get(key)
    if f is None:
        return False
    if f.default is not dataclasses.MISSING:
        return value == f.default
    if f.default_factory is not dataclasses.MISSING:
        return value == f.default_factory()
    return False


def restore(tr: Trainer, ck: dict) -> None:
    """Load checkpoint `ck` into the freshly built trainer `tr`."""
    where = tr.out_dir / CHECKPOINT
    saved = canonical_field_config(ck.get("backend", tr.cfg.backend), ck.get("field_config") or {})
    if saved != tr.field.config_dict():
        raise InputError(
            f"{where}: cannot resume: the field was built differently (backend options changed)"
        )
    try:
        tr.field.load_state_dict(ck["field"])
        tr.optimizer.load_state_dict(ck["optimizer"])
        if hasattr(tr.field, "pad_legacy"):  # moments saved for an older layout of the field
            fit_state(tr.optimizer, tr.field.pad_legacy)
        if tr.selfcal is not None:
            tr.selfcal.load_state_dict(ck["self_calibration"])
        tr.clock.load_state_dict(ck.get("restart"))
        saved = ck["sampler"]
        state = {k: _windows_loaded(saved[k]) for k in WINDOW_STATES if k in saved}
        state.update(gen=saved["gen"], position=int(saved.get("position", 0)))
        state.update(
            per_window=saved.get("per_window"), per_window_next=saved.get("per_window_next")
        )
        if tr.batch_size is not None:
            tr.batch_size.load_state_dict(ck["batch_size"])
        tr.sampler.load_state_dict(state)
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
    tr.step_count = int(ck["step"])
    tr.train_seconds = float(ck["train_seconds"])
    tr.eval_seconds = float(ck["eval_seconds"])
    tr.wall_seconds = float(ck.get("wall_seconds", 0.0))
    tr.last_eval_psnr = ck.get("last_eval_psnr")
    tr.skipped_steps = int(ck.get("skipped_steps", 0))
    if tr.clock.restarts and tr.selfcal is not None:  # the poses held, or resumed by now
        tr.selfcal.use_field(tr.field, tr.clock.progress, now=tr.progress())


def trim_metrics(run_dir: Path, step: int) -> None:
    """Drop metrics.jsonl lines logged after `step` (a resumed run logs them again)."""
    path = run_dir / METRICS_LOG
    if not path.exists():
        return
    keep = []
    for line in path.read_text().splitlines():
        try:
            if json.loads(line).get("step", 0) <= step:
                keep.append(line)
        except json.JSONDecodeError:
            continue  # a line cut by a crash
    with atomic_path(path) as tmp:
        tmp.write_text("".join(line + "\n" for line in keep))


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


def _windows_saved(w: dict) -> dict:
    """A WindowSampler state for torch.save: lengths as a tensor (a new dict)."""
    lengths = w["lengths"]
    return {**w, "lengths": None if lengths is None else torch.from_numpy(lengths)}


def _windows_loaded(w: dict) -> dict:
    """The inverse of `_windows_saved`: lengths back as a numpy array."""
    lengths = w["lengths"]
    return {**w, "lengths": None if lengths is None else lengths.cpu().numpy()}
