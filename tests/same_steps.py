"""Two training paths (plain, device-paced, graphed) take the same steps: checks that hold up to
float32 rounding.

The paths give the field the same samples in differently sized buffers (fixed-capacity, padded),
so a matrix product's reduction over samples may round differently: on some CPUs (AVX-512
oneDNN kernels) the MLP's weight gradients differ in the last bit, which Adam's first steps can
turn into a hash-table entry stepping ±lr the other way where its gradient is ~0. A wrong step
(a stale learning rate, a skipped or doubled update, a stale batch) moves the loss by orders of
magnitude more than LOSS_RTOL and most of a tensor's entries by more than TENSOR_RTOL.
"""

import os

import pytest
import torch

LOSS_RTOL = 1e-5
TENSOR_RTOL = 1e-3  # of an entry's size, plus as much of the tensor's mean size
TENSOR_SHARE = 0.99  # of entries within TENSOR_RTOL


def assert_same_losses(want: list[float], got: list[float]) -> None:
    """Per-step losses of two paths: equal up to LOSS_RTOL (relative)."""
    assert len(got) == len(want)
    assert got == pytest.approx(want, rel=LOSS_RTOL, abs=0)


def assert_same_tensor(want: torch.Tensor, got: torch.Tensor, name: str = "") -> None:
    """Two paths' parameters after the same steps: TENSOR_SHARE of the entries within rounding
    (TENSOR_RTOL of their size and of the tensor's mean size), and the mean difference under
    TENSOR_RTOL of the mean size. Relative throughout: pose corrections are ~1e-8 rad."""
    want, got = want.detach().double(), got.detach().double()
    assert want.shape == got.shape, name
    scale = want.abs().mean().item()
    err = (got - want).abs()
    share = (err <= TENSOR_RTOL * (want.abs() + scale)).double().mean().item()
    diff = err.mean().item()
    if os.environ.get("SAME_STEPS_DEBUG"):
        print(f"same_steps {name}: share {share:.5f} mean diff {diff:.3g} scale {scale:.3g}")
    assert share >= TENSOR_SHARE, f"{name}: {share:.4f} of entries within rounding"
    assert diff <= TENSOR_RTOL * scale, f"{name}: mean difference {diff:.3g} (size {scale:.3g})"
