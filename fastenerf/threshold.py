"""Contrast thresholds learnt with the field (issue #20).

A window's event target is linear in the thresholds: with n₊, n₋ the positive and negative
events of pixel u in the window and o the polarity offset (DESIGN §9),

    E(u) = a(u)·C₊ + b(u)·C₋,    a = (1 + o)·n₊,  b = (o − 1)·n₋

so the sampler hands over (a, b) per pixel and the target is re-weighted with learnt C₊, C₋.

What the events can and cannot tell (and so what is learnt):
- the RATIO C₊/C₋ is observable: a pixel that returns to the same brightness (every pixel of a
  closed loop, every static background pixel) must see its positive and negative steps
  cancel, which a biased ratio cannot do (the reconstruction drifts); it is learnt;
- the common SCALE is not: a field whose log contrast is s times smaller (s < 1; its colours
  mapped by c ↦ ((c^γ + ε)^s − ε)^(1/γ), which stays in [0, 1]) explains events s times
  smaller exactly, and colour-corrected PSNR does not see it either. Only the ends of the log
  range (the ε floor, colours saturating at 1) pin it, from one side. So by default the
  product C₊·C₋ stays at scene.json's value (the scale comes from the preset) and
  `free_scale` is for experiments (nothing in the loss holds the scale, and where the fit is
  imperfect smaller targets leave smaller residuals: expected to drift down);
- per-pixel factors (sensor mismatch, `per_pixel`) are observable through multi-view
  consistency; they are pulled towards 1 by a regulariser (their mean squared log).

Parametrisation (positive and finite by construction): log C± = log C±⁰ + s ± r/2 [+ p±(u)],
each clamped to [log C_MIN, log C_MAX]; the parameters are projected back into their
bounds after every step (`project`), so Adam's momentum cannot carry them far outside.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from .errors import InputError

C_MIN, C_MAX = 1e-3, 10.0  # thresholds, log-intensity units
RATIO_MAX = math.log(100.0)  # |log C₊/C₋| bound of the learnt ratio
SCALE_MAX = math.log(10.0)  # |s| bound: the scale within a factor 10 of the start
PIXEL_MAX = 1.0  # |p±(u)| bound: per-pixel factors within [1/e, e]


class ThresholdEstimator(nn.Module):
    """Learnt C₊, C₋ (global, and optionally per pixel).

    c_pos, c_neg: start values (scene.json's); n_pix: sensor pixels (per-pixel factors);
    per_pixel, free_scale: see the module docstring; pixel_weight: regulariser weight;
    ratio: a measured C₊/C₋ (`data/loop_ratio.py`): the ratio is set to it, product kept,
    and not learnt (None: learnt from the start's ratio).
    """

    def __init__(
        self,
        c_pos: float,
        c_neg: float,
        n_pix: int,
        *,
        per_pixel: bool = False,
        free_scale: bool = False,
        pixel_weight: float = 1.0,
        ratio: float | None = None,
        device: str | torch.device = "cpu",
    ):
        super().__init__()
        if not (C_MIN <= c_pos <= C_MAX and C_MIN <= c_neg <= C_MAX):
            raise InputError(
                f"threshold estimation: the start thresholds must lie in [{C_MIN}, {C_MAX}] "
                f"(scene.json has {c_pos}, {c_neg})"
            )
        self.start = (float(c_pos), float(c_neg))
        self.register_buffer(
            "log_start", torch.tensor([math.log(c_pos), math.log(c_neg)], device=device)
        )
        if ratio is not None and not (math.isfinite(ratio) and ratio > 0):
            raise InputError(f"threshold estimation: a measured ratio must be > 0, got {ratio}")
        r0 = 0.0 if ratio is None else math.log(ratio) - math.log(c_pos / c_neg)
        r0 = min(max(r0, -RATIO_MAX), RATIO_MAX)
        self.measured_ratio = ratio
        # not saved: a constant (and checkpoints made before it load as they are)
        sign = torch.tensor([0.5, -0.5], device=device)
        self.register_buffer("sign", sign, persistent=False)
        self.log_ratio = nn.Parameter(
            torch.full((), r0, device=device), requires_grad=ratio is None
        )
        self.log_scale = nn.Parameter(torch.zeros((), device=device), requires_grad=free_scale)
        self.pixel = None
        if per_pixel:
            self.pixel = nn.Parameter(torch.zeros(n_pix, 2, device=device))
        self.pixel_weight = float(pixel_weight)

    def _log_global(self) -> torch.Tensor:
        """(2,) log C₊, log C₋ before clamping."""
        # a buffer, not a tensor made per call: a captured step may not copy from the host
        return self.log_start + self.log_scale + self.sign * self.log_ratio

    def thresholds(self, pix: torch.Tensor | None = None) -> torch.Tensor:
        """C₊, C₋: (2,) global, or (B, 2) at flat pixels `pix` (B,) with per-pixel factors."""
        lg = self._log_global()
        if pix is not None and self.pixel is not None:
            lg = lg + self.pixel[pix]
        return lg.clamp(math.log(C_MIN), math.log(C_MAX)).exp()

    def target(self, parts: torch.Tensor, pix: torch.Tensor) -> torch.Tensor:
        """E(u) = a·C₊ + b·C₋, (B,) float32; parts: (B, 2) [a, b]; pix: (B,) flat pixels."""
        c = self.thresholds(pix)
        return (parts.float() * c).sum(-1)

    def regulariser(self, pix: torch.Tensor) -> torch.Tensor | None:
        """pixel_weight · mean over the batch's pixels of p±(u)², or None (no factors)."""
        if self.pixel is None or self.pixel_weight == 0:
            return None
        return self.pixel_weight * self.pixel[pix].square().mean()

    @torch.no_grad()
    def project(self) -> None:
        """Put every parameter back into its bounds (after an optimiser step)."""
        self.log_ratio.clamp_(-RATIO_MAX, RATIO_MAX)
        self.log_scale.clamp_(-SCALE_MAX, SCALE_MAX)
        if self.pixel is not None:
            self.pixel.clamp_(-PIXEL_MAX, PIXEL_MAX)

    @torch.no_grad()
    def stats(self, on_device: bool = False) -> dict[str, float | torch.Tensor]:
        """threshold_pos, threshold_neg (global), threshold_ratio, and the per-pixel factors'
        RMS log deviation when learnt; on_device: 0-dim device tensors (no host read)."""
        c = self.thresholds()
        vals = [c[0], c[1], c[0] / c[1]]
        keys = ["threshold_pos", "threshold_neg", "threshold_ratio"]
        if self.pixel is not None:
            vals.append(self.pixel.square().mean().sqrt())
            keys.append("threshold_pixel_rms")
        row = torch.stack(vals)
        return dict(zip(keys, row.unbind() if on_device else row.tolist(), strict=True))
