"""A run's config.json, beside the trainer rather than in it (as `train_state` is).

`built` names the parts this scene switched on; `write_config` writes the resolved options,
the scene, the field's arguments, what was built and what the run measured about its data
(perturbation, pose smoothing, self-calibration): the record that `fastenerf eval`, `render`
and `view` read back (`fastenerf.run` describes the folder).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

from .io import write_json
from .run import scene_fingerprint

if TYPE_CHECKING:
    from .train import Trainer


def built(tr: Trainer) -> dict[str, Any]:
    """The parts `tr`'s scene and options switched on (config.json's "built")."""
    sc, cfg = tr.scene.config, tr.cfg
    return {
        "bayer": sc.bayer,
        "mono_luminance": sc.bayer is None,
        "distortion": tr.rig.intrinsics.distorted,
        "cylinder": sc.cylinder is not None,
        "background": tr.background is not None,
        "loop_wrap": sc.loop,
        "distortion_loss": cfg.distortion_weight > 0,
        "event_targets": tr.sampler.target_backend,
        "amp": "bf16" if tr.amp else "off",
        "device": str(tr.device),
        "pose_smoothing": cfg.smooth_poses > 0,
        "pose_refinement": cfg.refine_poses,
        "threshold_estimation": cfg.estimate_threshold,
        **tr.field.built(),
    }


def write_config(tr: Trainer) -> Path:
    """Write RUN/config.json (atomically) for trainer `tr`; returns its path."""
    from . import __version__

    return write_json(
        tr.out_dir / "config.json",
        {
            "train": tr.cfg.to_dict(),
            "scene": tr.scene.config.to_dict(),
            "scene_dir": str(Path(tr.scene.root).resolve()),
            "scene_fingerprint": scene_fingerprint(tr.scene),
            "field": tr.field.config_dict(),
            "built": built(tr),
            "perturbation": tr.perturbation,
            "pose_smoothing": tr.smoothing,
            "self_calibration": None if tr.selfcal is None else tr.selfcal.report(),
            "field_restart": tr.clock.state_dict() if tr.cfg.refine_restart else None,
            "versions": {"torch": torch.__version__, "fastenerf": __version__},
        },
    )
