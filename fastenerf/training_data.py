"""A run's training data: the data half of the pipeline, events -> windows -> rays (DESIGN §3).

`build_training_data` makes, from a scene and resolved options, the training rig (with the
studies' perturbation and the optional motion prior), the event index, the window sampler and
the ray sampler the trainer draws its batches from. `exact_grid_poses` is the truth a study
knows where it turned the training poses; `observed_poses` the training cameras a field is
told about.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .config import TrainConfig
from .data.events import EventIndex
from .data.formats.native import Scene
from .data.rig import Rig
from .perturb import perturb_training_data, pose_grid_times
from .pose_smoothing import smoothed_rig
from .sampling import RaySampler, WindowSampler

# Batches the sampler draws at once: its host cost per block is about that of one batch.
SAMPLER_PREFETCH = 16
# Training-camera poses the ngp occupancy grid is told about (space none sees stays empty).
OBSERVED_VIEWS = 100


@dataclass
class TrainingData:
    """What the trainer samples from.

    rig: the training rig (perturbed, then smoothed, where the options say); index: the
    training events; windows, sampler: the window and ray samplers; perturbation: the studies'
    report (`perturb_training_data`); smoothing: the motion prior's report, or None when off.
    """

    rig: Rig
    index: EventIndex
    windows: WindowSampler
    sampler: RaySampler
    perturbation: dict | None
    smoothing: dict | None


def build_training_data(scene: Scene, cfg: TrainConfig, device: torch.device) -> TrainingData:
    """The rig, event index and samplers for `scene` under the resolved options `cfg`; the
    ray sampler makes its batches on `device`."""
    sc = scene.config
    # the studies' perturbations (identity at zero levels); test views stay exact
    rig, events, perturbation = perturb_training_data(scene, cfg.perturb)
    index = EventIndex(
        events,
        sc.pos_threshold,
        sc.neg_threshold,
        sc.polarity_offset,
        t_start=sc.t_start_us,
        t_end=sc.t_end_us,
        loop=sc.loop,
    )
    windows = WindowSampler(
        sc.n_views,
        sc.t_start_us,
        sc.t_end_us,
        cfg.win_min,
        cfg.win_max,
        cfg.win_redraw,
        sc.loop,
        cfg.seed,
    )
    smoothing = None
    if cfg.smooth_poses:
        # the prior's report gives the error before and after where a study knows the truth
        exact, t = exact_grid_poses(scene, perturbation), pose_grid_times(sc)
        rig, smoothing = smoothed_rig(rig, t, cfg.smooth_poses, exact, cfg.smooth_order)
    sampler = RaySampler(
        index,
        rig,
        windows,
        rays_per_step=cfg.rays_per_step,
        windows_per_step=cfg.windows_per_step,
        neg_ratio=cfg.neg_ratio,
        device=device,
        seed=cfg.seed,
        prefetch=SAMPLER_PREFETCH,
        with_poses=cfg.refine_poses,
        with_parts=cfg.estimate_threshold,
    )
    return TrainingData(rig, index, windows, sampler, perturbation, smoothing)


def exact_grid_poses(scene: Scene, perturbation: dict | None) -> np.ndarray | None:
    """(n_views + 1, 4, 4) float64 unperturbed poses on the training grid where a study turned
    them (`perturbation`: its report), else None."""
    p = perturbation or {}
    if not (p.get("pose") or p.get("mount")):
        return None
    return scene.rig().pose(pose_grid_times(scene.config))


def observed_poses(sampler: RaySampler) -> np.ndarray:
    """(≤ OBSERVED_VIEWS, 4, 4) camera-to-world poses spread evenly over the training grid."""
    c2w = sampler.grid_c2w[:-1].cpu().numpy()
    return c2w[np.unique(np.linspace(0, len(c2w) - 1, OBSERVED_VIEWS).round().astype(int))]
