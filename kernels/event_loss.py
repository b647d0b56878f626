"""The event loss (fastenerf.losses.event_loss) as one Warp kernel each way.

    I(c)  = c_k**gamma (Bayer channel k) or sum_k LUMA_k c_k**gamma (mono), c clamped at 0
    pred  = log(I(c1) + eps) - log(I(c0) + eps)
    loss  = sum_u w_u (pred_u - E_u)**2 / W,     W = max(sum_u w_u, 1) (all w = 1: W = B)

The torch expression of the same loss dispatches tens of ops forward and autograd nodes
backward on the host every step; here it is one launch each way plus the sum.
"""

from __future__ import annotations

import torch
import warp as wp

from .common import as_float32, init, launch

init()

# Rec. 709 luminance of linear RGB: what a mono sensor integrates (approximately); the torch
# loss (fastenerf.losses) uses the same weights.
LUMA_709 = (0.2126, 0.7152, 0.0722)
LUMA_R, LUMA_G, LUMA_B = LUMA_709


@wp.func
def _lin(c: float, gamma: float):
    """Linear intensity of one display-space channel value; NaN stays NaN (a max would turn it
    into 0, and the trainer's finite-loss guard would miss a broken render)."""
    if wp.isnan(c):
        return c
    return wp.pow(wp.max(c, 0.0), gamma)


@wp.func
def _dlin(c: float, gamma: float):
    """d _lin / d c: 0 where the clamp holds (c <= 0)."""
    out = 0.0
    if c > 0.0:
        out = gamma * wp.pow(c, gamma - 1.0)
    return out


@wp.func
def _channel(channel: wp.array(dtype=wp.int64), i: int, mono: int):
    """Pixel i's Bayer channel (0 for a mono sensor, whose channel array is a stand-in)."""
    if mono != 0:
        return 0
    return int(channel[i])


@wp.func
def _intensity(rgb: wp.array2d(dtype=float), i: int, k: int, mono: int, gamma: float):
    """What pixel row i of rgb (N, 3) gives its sensor: channel k, or the luminance."""
    if mono != 0:
        r = LUMA_R * _lin(rgb[i, 0], gamma)
        return r + LUMA_G * _lin(rgb[i, 1], gamma) + LUMA_B * _lin(rgb[i, 2], gamma)
    return _lin(rgb[i, k], gamma)


@wp.func
def _scatter_grad(
    rgb: wp.array2d(dtype=float),
    i: int,
    k: int,
    mono: int,
    gamma: float,
    s: float,
    grad: wp.array2d(dtype=float),
):
    """grad[i] = s * d intensity / d rgb[i] (every channel written: zero where it is unseen)."""
    for c in range(3):
        grad[i, c] = 0.0
    if mono != 0:
        grad[i, 0] = s * LUMA_R * _dlin(rgb[i, 0], gamma)
        grad[i, 1] = s * LUMA_G * _dlin(rgb[i, 1], gamma)
        grad[i, 2] = s * LUMA_B * _dlin(rgb[i, 2], gamma)
    else:
        grad[i, k] = s * _dlin(rgb[i, k], gamma)


@wp.kernel(enable_backward=False)
def _event_loss_forward(
    rgb: wp.array2d(dtype=float),
    b: int,
    target: wp.array(dtype=float),
    channel: wp.array(dtype=wp.int64),
    mono: int,
    weight: wp.array(dtype=float),
    weighted: int,
    gamma: float,
    eps: float,
    err: wp.array(dtype=float),
    wres: wp.array(dtype=float),
):
    i = wp.tid()
    k = _channel(channel, i, mono)
    i0 = _intensity(rgb, i, k, mono, gamma)
    i1 = _intensity(rgb, b + i, k, mono, gamma)
    r = wp.log(i1 + eps) - wp.log(i0 + eps) - target[i]
    w = 1.0
    if weighted != 0:
        w = weight[i]
    err[i] = w * r * r
    wres[i] = w * r


@wp.kernel(enable_backward=False)
def _event_loss_backward(
    rgb: wp.array2d(dtype=float),
    b: int,
    channel: wp.array(dtype=wp.int64),
    mono: int,
    gamma: float,
    eps: float,
    wres: wp.array(dtype=float),
    scale: wp.array(dtype=float),
    grad_rgb: wp.array2d(dtype=float),
    grad_target: wp.array(dtype=float),
    want_target: int,
):
    i = wp.tid()
    k = _channel(channel, i, mono)
    s = scale[0] * wres[i]  # d loss / d pred
    i0 = _intensity(rgb, i, k, mono, gamma)
    i1 = _intensity(rgb, b + i, k, mono, gamma)
    _scatter_grad(rgb, b + i, k, mono, gamma, s / (i1 + eps), grad_rgb)
    _scatter_grad(rgb, i, k, mono, gamma, -s / (i0 + eps), grad_rgb)
    if want_target != 0:
        grad_target[i] = -s


_DUMMIES: dict = {}


def _dummy(dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """A one-element stand-in for an absent input (made once per dtype and device)."""
    key = (dtype, device)
    if key not in _DUMMIES:
        _DUMMIES[key] = torch.zeros(1, dtype=dtype, device=device)
    return _DUMMIES[key]


class _EventLoss(torch.autograd.Function):
    @staticmethod
    def forward(ctx, rgb, target, channel, weight, gamma, eps):
        b = target.shape[0]
        err = torch.empty(b, dtype=torch.float32, device=rgb.device)
        wres = torch.empty_like(err)
        mono = channel is None
        ch = _dummy(torch.int64, rgb.device) if mono else channel
        w = _dummy(torch.float32, rgb.device) if weight is None else weight
        args = [rgb, b, target, ch, int(mono), w, int(weight is not None), gamma, eps, err, wres]
        launch(_event_loss_forward, b, rgb, args)
        total = weight.sum().clamp_min(1.0) if weight is not None else None
        ctx.save_for_backward(rgb, ch, wres, total)
        ctx.consts = (b, int(mono), gamma, eps)
        return err.sum() / (total if total is not None else max(b, 1))

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_out):
        rgb, ch, wres, total = ctx.saved_tensors
        b, mono, gamma, eps = ctx.consts
        scale = grad_out.reshape(1).float() * (2.0 / max(b, 1) if total is None else 2.0)
        if total is not None:
            scale = scale / total
        grad_rgb = torch.empty_like(rgb)
        want_target = ctx.needs_input_grad[1]
        grad_target = torch.empty_like(wres) if want_target else _dummy(torch.float32, rgb.device)
        args = [rgb, b, ch, mono, gamma, eps, wres, scale, grad_rgb, grad_target, int(want_target)]
        launch(_event_loss_backward, b, rgb, args)
        return grad_rgb, grad_target if want_target else None, None, None, None, None


def event_loss(
    rgb: torch.Tensor,
    target: torch.Tensor,
    channel: torch.Tensor | None,
    gamma: float,
    eps: float,
    weight: torch.Tensor | None = None,
) -> torch.Tensor:
    """The event loss of 2B rays, scalar float32, differentiable in rgb and target.

    rgb: (2B, 3) display-space colours, the B pixels at t0 then at t1 (cast to float32);
    target: (B,) float32 E(u; t0, t1], log units; channel: (B,) int64 Bayer channel
    (0 R, 1 G, 2 B) or None for a mono sensor (luminance); weight: (B,) float32 0/1, the
    pixels that count (None: all); gamma > 0, eps > 0 as `fastenerf.losses.log_intensity`.
    """
    b = target.shape[0]
    if rgb.ndim != 2 or rgb.shape != (2 * b, 3):
        raise ValueError(f"event_loss: rgb must be (2B, 3) = ({2 * b}, 3), got {tuple(rgb.shape)}")
    if channel is not None and channel.dtype != torch.int64:
        channel = channel.long()
    w = None if weight is None else as_float32(weight)
    return _EventLoss.apply(as_float32(rgb), as_float32(target), channel, w, gamma, eps)
