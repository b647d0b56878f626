"""The Field interface shared by the `ngp` and `vanilla` backends.

A field owns its sampler (occupancy-grid marching for ngp, stratified + hierarchical for
vanilla) because the two are inseparable from how each represents space; everything outside
the field (losses, trainer, eval, viewer, mesh) sees only this interface, and may call every
method of it on any field: the optional parts (`param_groups`, `observe_cameras`, `update`,
`built`) have defaults here, so no caller probes with `hasattr`.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Iterator
from typing import TypedDict

import numpy as np
import torch

from ..errors import InputError

_VIEW = threading.local()  # per thread: the viewer's render and a trainer's eval run side by side


@contextlib.contextmanager
def view_cone(cone_angle: float | None) -> Iterator[None]:
    """In this thread, inference renders march with a cone angle of at least `cone_angle`
    (ngp; the vanilla sampler has none): an interactive view's speed setting. Evaluation, the
    trainer and other threads keep the field's own. None: the field's own."""
    old = getattr(_VIEW, "cone", None)
    _VIEW.cone = cone_angle
    try:
        yield
    finally:
        _VIEW.cone = old


def view_cone_angle() -> float | None:
    """The cone angle `view_cone` set in this thread, or None."""
    return getattr(_VIEW, "cone", None)


class RenderOutput(TypedDict, total=False):
    rgb: torch.Tensor  # (R, 3) display-space colour in [0, 1], composited over the background
    depth: torch.Tensor  # (R,) expected distance along the unit ray, world units
    opacity: torch.Tensor  # (R,) accumulated alpha in [0, 1]
    distortion: torch.Tensor  # () mip-NeRF 360 distortion loss (mean over rays), when computed
    n_samples: int | torch.Tensor  # samples the field ran on (stats; a device count when fixed)
    n_marched: int | torch.Tensor  # samples marched, where fewer were kept (ngp early_stop_eps)
    valid: torch.Tensor  # (R,) bool, False for rays a fixed sample buffer had no room for


class Field(torch.nn.Module):
    """A radiance field over the scene box.

    aabb: (6,) float32 buffer, world units [xmin, ymin, zmin, xmax, ymax, zmax].
    """

    backend: str = "base"

    def density(self, x: torch.Tensor) -> torch.Tensor:
        """Volume density σ ≥ 0, (N,) float32, 1/world units, at world points x: (N, 3)."""
        raise NotImplementedError

    def color(self, x: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        """Display-space colour (N, 3) in [0, 1] at points x (N, 3) along unit dirs d (N, 3)."""
        raise NotImplementedError

    def render(
        self,
        rays_o: torch.Tensor,
        rays_d: torch.Tensor,
        *,
        near: float,
        background: torch.Tensor | None,
        train: bool,
        grad_rays: torch.Tensor | None = None,
    ) -> RenderOutput:
        """Volume-render rays: rays_o (R, 3) world units, rays_d (R, 3) unit.

        background: (3,) display-space colour composited behind the field, or None (black,
        no background term). `train` turns on stochastic sampling and training-only extras.
        grad_rays: optional (R,) bool, the rays whose gradient w.r.t. rays_o and rays_d the
        caller reads (it detached the others); a field may skip the others' (None: all).
        """
        raise NotImplementedError

    def config_dict(self) -> dict:
        """What rebuilds this field (`fields.field_from_config`): {"aabb", "options" (the
        backend's options dataclass as a dict), "cylinder" (CylinderConfig as a dict or None)},
        saved in checkpoints."""
        raise NotImplementedError

    # -- optional parts: the defaults below make every call safe on any field ----------------

    def param_groups(self) -> list[dict]:
        """Optimiser parameter groups (torch.optim style dicts with "params" and optional
        "lr"); default: one group of every trainable parameter at the run's learning rate."""
        return [{"params": [p for p in self.parameters() if p.requires_grad]}]

    def observe_cameras(
        self, K: np.ndarray, c2ws: np.ndarray, width: int, height: int, near: float = 0.0
    ) -> None:
        """Learn which space the training cameras see (ngp: cells no camera sees stay empty).

        K: (3, 3) pinhole intrinsics in pixels; c2ws: (M, 4, 4) OpenCV camera-to-world;
        width, height: image size in pixels; near: world units. A no-op by default.
        """

    def graph_key(self) -> tuple | None:
        """What a CUDA graph of a training step bakes in from this field (buffer sizes, the
        march's cone): a captured step is replayed only while it is unchanged
        (`fastenerf.graph_step`). None (the default): training steps are not captured."""
        return None

    def graph_state(self) -> object:
        """What a captured step reads outside its own memory that the field replaces when its
        `graph_key` changes; None (the default): nothing."""
        return None

    def set_graph_state(self, state: object) -> None:
        """Put back a `graph_state()` when a kept graph replays again; a no-op by default."""

    def update(self, step: int) -> None:
        """Per-step housekeeping before training step `step` (the ngp occupancy grid); a no-op
        by default."""

    def built(self) -> dict:
        """Which optional parts this field runs, {name: bool} (for RUN/config.json); {} by
        default."""
        return {}


def park_non_finite(rays_o: torch.Tensor, rays_d: torch.Tensor):
    """Training rays with a NaN or inf value replaced by a harmless one (kernels index memory
    with them; an MLP's NaN would spread to every weight's gradient), without a host read.

    Returns (rays_o, rays_d, bad (R, 1) bool, shaped to broadcast over a pixel's colour); the
    caller makes the bad rays' pixels NaN, so the step's loss is NaN and the trainer's guard
    skips it.
    """
    # one check of both (R, 6) and scalar fills: fewer ops on a step's path than two checks,
    # an `&` and two constant tensors
    bad = ~torch.isfinite(torch.cat([rays_o, rays_d], -1)).all(-1, keepdim=True)
    rays_o = torch.where(bad, 0.0, rays_o)
    rays_d = torch.where(bad, 3**-0.5, rays_d)
    return rays_o.contiguous(), rays_d.contiguous(), bad


def check_points(name: str, v: torch.Tensor, where: str, finite: bool = True) -> None:
    """Reject what would corrupt the weights: a NaN point reaches the hash-grid backward as a
    NaN gradient, and one NaN row poisons Adam's moments for good (DESIGN §5).

    finite: also read every value on the host (a device sync). A training step passes False:
    its rays come from validated poses, and a non-finite one makes the loss non-finite, which
    the step's guard skips before it reaches the weights.
    """
    if v.ndim != 2 or v.shape[-1] != 3:
        raise InputError(f"{where}: {name} must be (N, 3), got {tuple(v.shape)}")
    if not finite:
        return
    bad = ~torch.isfinite(v).all(-1)
    if bool(bad.any()):
        raise InputError(
            f"{where}: {name} has NaN or inf in {int(bad.sum())} of {len(v)} rows "
            f"(first at row {int(bad.nonzero()[0, 0])})"
        )
