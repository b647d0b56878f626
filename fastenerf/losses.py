"""The EventNeRF objective (DESIGN §3, §9) and its regularisers.

    L(c)    = log(c**gamma + eps)                        c: display-space colour in [0, 1]
    pred(u) = L(c(u, t1))[k(u)] - L(c(u, t0))[k(u)]      k(u): the pixel's Bayer channel
    loss    = mean_u (pred(u) - E(u; t0, t1])**2

Mono sensors see the luminance of linear intensity, Y = 0.2126 R + 0.7152 G + 0.0722 B
(Rec. 709 weights on the linear values c**gamma), so L = log(Y + eps) there.
`eps` is the guard against log(0): a field that renders black (c = 0) would give -inf
and NaN gradients without it; the config refuses eps <= 0.
"""

from __future__ import annotations

import torch

from .kernels import event_loss as fused_event
from .kernels.common import as_float32
from .kernels.event_loss import LUMA_709


def linear_intensity(
    rgb: torch.Tensor, channel: torch.Tensor | None, gamma: float = 2.2
) -> torch.Tensor:
    """Linear intensity a pixel sees: rgb (B, 3) display space -> (B,).

    channel: (B,) int64 Bayer channel (0 R, 1 G, 2 B), or None for a mono sensor (luminance).
    Computed in float32 whatever the autocast dtype of `rgb`.
    """
    lin = as_float32(rgb).clamp_min(0.0) ** gamma
    if channel is None:
        return lin @ lin.new_tensor(LUMA_709)
    return lin.gather(1, channel.view(-1, 1)).squeeze(1)


def log_intensity(
    rgb: torch.Tensor, channel: torch.Tensor | None, gamma: float = 2.2, eps: float = 0.1
) -> torch.Tensor:
    """L = log(intensity + eps) per pixel, (B,) float32 (see `linear_intensity`)."""
    return torch.log(linear_intensity(rgb, channel, gamma) + eps)


def event_prediction(
    rgb0: torch.Tensor,
    rgb1: torch.Tensor,
    channel: torch.Tensor | None,
    gamma: float = 2.2,
    eps: float = 0.1,
) -> torch.Tensor:
    """Predicted log-intensity change L(rgb1) - L(rgb0), (B,); rgb0/rgb1 (B, 3) at t0/t1."""
    return log_intensity(rgb1, channel, gamma, eps) - log_intensity(rgb0, channel, gamma, eps)


def event_loss(
    rgb0: torch.Tensor,
    rgb1: torch.Tensor,
    target: torch.Tensor,
    channel: torch.Tensor | None,
    gamma: float = 2.2,
    eps: float = 0.1,
    weight: torch.Tensor | None = None,
) -> torch.Tensor:
    """MSE between predicted and measured log change; target: (B,) E(u; t0, t1], log units.

    weight: (B,) float32 0/1, the pixels that count (None: all); the mean is over them.
    """
    pred = event_prediction(rgb0, rgb1, channel, gamma, eps)
    err = (pred - as_float32(target)) ** 2
    if weight is None:
        return torch.mean(err)
    return (err * weight).sum() / weight.sum().clamp_min(1.0)


def _halves(t: torch.Tensor, b: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(t[:b], t[b:]) in one op: the backward of a split is one concatenation, that of two
    slices two zero-filled copies and a sum (the same gradient)."""
    return t.split([b, t.shape[0] - b])


def total_loss(
    out: dict,
    target: torch.Tensor,
    channel: torch.Tensor | None,
    *,
    gamma: float,
    eps: float,
    distortion_weight: float = 0.0,
    fused: bool = False,
) -> tuple[torch.Tensor, dict]:
    """The training objective from one RenderOutput over 2B rays: B pixels at t0, then at t1.

    Event loss on `rgb`, plus on `rgb_coarse` when the field renders a coarse level too (the
    reference sums the loss over its coarse and fine networks), plus `distortion_weight` times
    the field's `distortion` term when the weight is > 0 and the field gives one.
    target: (B,) E(u; t0, t1]; channel: (B,) Bayer channel or None (mono).
    A render that could not march every ray (`out["valid"]`, (2B,) bool: a fixed sample buffer
    overflowed) leaves out the pixels whose t0 or t1 ray is missing; parts["dropped"] is their
    share. fused: the event loss as one Warp kernel each way (`kernels.event_loss`, the same
    loss in a few host ops), else the torch expression above.
    Returns (loss, parts) with parts detached scalar tensors, for logging.
    """
    b = target.shape[0]
    rgb = out["rgb"]
    weight = None
    parts = {}
    if out.get("valid") is not None:
        valid0, valid1 = _halves(out["valid"], b)
        weight = (valid0 & valid1).float()
        parts["dropped"] = 1.0 - weight.mean()

    def events(rgb):
        if fused:
            return fused_event.event_loss(rgb, target, channel, gamma, eps, weight)
        return event_loss(*_halves(rgb, b), target, channel, gamma, eps, weight)

    ev = events(rgb)
    loss = ev
    parts["event"] = ev
    if "rgb_coarse" in out:
        evc = events(out["rgb_coarse"])
        loss = loss + evc
        parts["event_coarse"] = evc
    if distortion_weight > 0 and "distortion" in out:
        loss = loss + distortion_weight * out["distortion"]
        parts["distortion"] = out["distortion"]
    return loss, {k: v.detach() if v.requires_grad else v for k, v in parts.items()}
