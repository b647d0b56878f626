"""kernels/event_loss.py on Warp's CPU backend against a float64 reference, values and
gradients; the clamp and the eps guard at black and negative colours; total_loss's fused path
against its torch path."""

import pytest
import torch

from fastenerf.losses import LUMA_709, total_loss
from kernels.event_loss import event_loss


def reference(rgb, target, channel, gamma, eps, weight):
    """The loss in float64, written out from DESIGN §3 (no shared code with either path)."""
    b = target.shape[0]
    lin = rgb.clamp_min(0.0) ** gamma
    if channel is None:
        inten = lin @ torch.tensor(LUMA_709, dtype=rgb.dtype)
    else:
        inten = lin[torch.arange(2 * b), channel.repeat(2)]
    log_i = torch.log(inten + eps)
    err = (log_i[b:] - log_i[:b] - target) ** 2
    if weight is None:
        return err.mean()
    return (err * weight).sum() / weight.sum().clamp_min(1.0)


def problem(b, mono, weighted, seed=0):
    g = torch.Generator().manual_seed(seed)
    rgb = torch.rand(2 * b, 3, generator=g, dtype=torch.float64) * 1.2 - 0.1  # some < 0
    rgb[:3] = 0.0  # black pixels: the eps guard
    target = torch.randn(b, generator=g, dtype=torch.float64) * 0.3
    channel = None if mono else torch.randint(0, 3, (b,), generator=g)
    weight = (torch.rand(b, generator=g) < 0.7).double() if weighted else None
    return rgb, target, channel, weight


@pytest.mark.parametrize("mono", [False, True])
@pytest.mark.parametrize("weighted", [False, True])
def test_event_loss_matches_float64_values_and_gradients(mono, weighted):
    rgb, target, channel, weight = problem(301, mono, weighted)
    r64, t64 = rgb.clone().requires_grad_(), target.clone().requires_grad_()
    want = reference(r64, t64, channel, 2.2, 0.1, weight)
    (want * 1.7).backward()
    r32, t32 = rgb.float().requires_grad_(), target.float().requires_grad_()
    w32 = None if weight is None else weight.float()
    got = event_loss(r32, t32, channel, 2.2, 0.1, w32)
    (got * 1.7).backward()
    assert got.dtype == torch.float32 and got.shape == ()
    assert float(got.detach()) == pytest.approx(float(want.detach()), rel=1e-5)
    torch.testing.assert_close(r32.grad.double(), r64.grad, rtol=1e-4, atol=1e-8)
    torch.testing.assert_close(t32.grad.double(), t64.grad, rtol=1e-4, atol=1e-8)
    # an unseen Bayer channel, a clamped (negative) value: exactly no gradient
    if not mono:
        seen = torch.zeros(2 * len(target), 3, dtype=torch.bool)
        seen[torch.arange(2 * len(target)), channel.repeat(2)] = True
        assert torch.all(r32.grad[~seen] == 0)
    assert torch.all(r32.grad[rgb < 0] == 0)


def test_black_pixels_and_a_tiny_eps_stay_finite():
    """c = 0 everywhere (a field that renders black) with eps 1e-6: log(eps) is finite and so
    is every gradient; without the eps (1e-45 underflows to 0 in float32 here) the loss
    would be inf."""
    b = 64
    rgb = torch.zeros(2 * b, 3, requires_grad=True)
    target = torch.full((b,), 0.5)
    loss = event_loss(rgb, target, torch.randint(0, 3, (b,)), 2.2, 1e-6)
    loss.backward()
    assert torch.isfinite(loss) and float(loss.detach()) == pytest.approx(0.25)
    assert torch.isfinite(rgb.grad).all()
    bad = event_loss(rgb.detach(), target, torch.randint(0, 3, (b,)), 2.2, 0.0)
    assert not torch.isfinite(bad)  # what the guard prevents (the config refuses eps <= 0)


def test_a_nan_colour_makes_the_loss_nan():
    """The trainer skips a step on a non-finite loss (its guard reads no rays on the host): a
    NaN pixel must reach the loss, as the torch clamp lets it, not be clamped to black."""
    rgb, target, channel, _ = problem(16, False, False)
    rgb = rgb.float()
    rgb[7 + 16, channel[7]] = float("nan")
    assert torch.isnan(event_loss(rgb, target.float(), channel, 2.2, 0.1))
    rgb[7 + 16] = float("nan")
    assert torch.isnan(event_loss(rgb, target.float(), None, 2.2, 0.1))


def test_all_pixels_weighted_out_is_zero_not_nan():
    rgb, target, channel, _ = problem(16, False, False)
    r = rgb.float().requires_grad_()
    loss = event_loss(r, target.float(), channel, 2.2, 0.1, torch.zeros(16))
    loss.backward()
    assert float(loss.detach()) == 0.0 and torch.all(r.grad == 0)


def test_wrong_shapes_are_refused():
    with pytest.raises(ValueError, match=r"rgb must be \(2B, 3\)"):
        event_loss(torch.zeros(10, 3), torch.zeros(4), None, 2.2, 0.1)


@pytest.mark.parametrize("mono", [False, True])
def test_total_loss_fused_is_the_torch_loss(mono):
    """The trainer's path (fused) and the torch expression: same loss and parts, same
    gradients, coarse level and dropped pixels included."""
    rgb, target, channel, _ = problem(200, mono, False, seed=4)
    coarse = (rgb * 0.9).float()
    valid = torch.rand(400, generator=torch.Generator().manual_seed(1)) < 0.95
    results = []
    for fused in (False, True):
        r, c = rgb.float().requires_grad_(), coarse.clone().requires_grad_()
        out = {"rgb": r, "rgb_coarse": c, "valid": valid}
        loss, parts = total_loss(out, target.float(), channel, gamma=2.2, eps=0.1, fused=fused)
        loss.backward()
        results.append((loss, parts, r.grad, c.grad))
    (la, pa, ra, ca), (lb, pb, rb, cb) = results
    torch.testing.assert_close(lb, la, rtol=1e-6, atol=0)
    assert pa.keys() == pb.keys() and float(pb["dropped"]) > 0
    for k in pa:
        torch.testing.assert_close(pb[k], pa[k], rtol=1e-6, atol=0)
    torch.testing.assert_close(rb, ra, rtol=1e-4, atol=1e-8)
    torch.testing.assert_close(cb, ca, rtol=1e-4, atol=1e-8)
