"""The ngp colour MLP's tensor-core widths (fastenerf/fields/mlp.py): the padded MLP computes
the unpadded one's function, values and gradients, its padding never trains, and a
checkpoint of the unpadded MLP loads into it."""

from __future__ import annotations

import shutil

import pytest
import torch

from fastenerf.data.formats.native import load_scene
from fastenerf.fields.mlp import (
    ALIGN,
    ColorMLP,
    _as_words,
    _word_for,
    concat_rows,
    density_logit,
    linear_relu,
    mlp,
)
from fastenerf.run import CHECKPOINT
from fastenerf.train import Trainer
from tests.test_train import tiny_cfg


def _pair(geo: int, hidden: int = 64):
    """(padded, unpadded) colour MLPs drawn from the same generator state, in float64."""
    torch.manual_seed(7)
    padded = ColorMLP(geo, hidden).double()
    torch.manual_seed(7)
    plain = mlp(geo + 16, hidden, 3, 2).double()
    return padded, plain


def _inputs(n: int, geo: int, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    h = torch.randn(n, 1 + geo, generator=g, dtype=torch.float64, requires_grad=True)
    sh = torch.randn(n, 16, generator=g, dtype=torch.float64, requires_grad=True)
    return h, sh


@pytest.mark.parametrize("geo", [15, 10, 7])  # 32 wide; 27 -> 32 with zero columns; 24
def test_padded_colour_mlp_is_the_unpadded_function_and_gradient(geo):
    padded, plain = _pair(geo)
    assert padded[0].in_features % ALIGN == 0 and padded[4].out_features % ALIGN == 0
    # the same initial weights where they act, zeros elsewhere
    w0 = padded[0].weight
    assert torch.equal(w0[:, 1 : 1 + geo + 16], plain[0].weight)
    assert not w0[:, 0].any() and not w0[:, 1 + geo + 16 :].any()
    assert torch.equal(padded[4].weight[:3], plain[4].weight) and not padded[4].weight[3:].any()

    h, sh = _inputs(33, geo)
    y = padded(h, sh)
    ref = plain(torch.cat([h[:, 1:], sh], 1))
    assert y.shape == (33, 3)
    torch.testing.assert_close(y, ref, rtol=1e-12, atol=1e-12)
    g = torch.randn_like(ref)
    gp = torch.autograd.grad(y, [h, sh, *padded.parameters()], g)
    gr = torch.autograd.grad(ref, [h, sh, *plain.parameters()], g)
    assert not gp[0][:, 0].any()  # the σ logit gets nothing from the colour
    torch.testing.assert_close(gp[0][:, 1:], gr[0][:, 1:], rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(gp[1], gr[1], rtol=1e-12, atol=1e-12)
    dw0, dw2, dw4 = gp[2:]
    torch.testing.assert_close(dw0[:, 1 : 1 + geo + 16], gr[2], rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(dw2, gr[3], rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(dw4[:3], gr[4], rtol=1e-12, atol=1e-12)
    # the padding's gradients are exact zeros: Adam leaves those weights where they are
    assert not dw0[:, 0].any() and not dw0[:, 1 + geo + 16 :].any() and not dw4[3:].any()


@pytest.mark.parametrize("amp", [False, True])
def test_adam_never_moves_the_padding(amp):
    torch.manual_seed(0)
    net = ColorMLP(10, 32)
    opt = torch.optim.Adam(net.parameters(), lr=1e-2, eps=1e-15)
    for step in range(5):
        h, sh = (t.float().detach() for t in _inputs(64, 10, seed=step))
        with torch.autocast("cpu", torch.bfloat16, enabled=amp):
            y = net(h, sh)
        loss = (torch.sigmoid(y.float()) - 0.5).square().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert net[0].weight[:, 1:27].abs().sum() > 0  # it trained
    assert not net[0].weight[:, 0].any() and not net[0].weight[:, 27:].any()
    assert not net[4].weight[3:].any()


def test_unpadded_checkpoint_loads_padded_through_a_parent_module():
    padded, plain = _pair(15)
    with torch.no_grad():
        for p in plain.parameters():
            p.add_(0.1 * torch.randn_like(p))  # not the weights `padded` starts with
    old = torch.nn.ModuleDict({"color_net": plain}).state_dict()
    assert old["color_net.0.weight"].shape == (64, 31)
    assert old["color_net.4.weight"].shape == (3, 64)
    holder = torch.nn.ModuleDict({"color_net": padded})
    holder.load_state_dict(old)  # strict: every key taken, every shape made to fit
    h, sh = _inputs(9, 15, seed=4)
    ref = plain(torch.cat([h[:, 1:], sh], 1))
    torch.testing.assert_close(padded(h, sh), ref, rtol=1e-12, atol=1e-12)
    # and a padded checkpoint round-trips as it is
    again = torch.nn.ModuleDict({"color_net": _pair(15)[0]})
    again.load_state_dict(holder.state_dict())
    assert torch.equal(again["color_net"](h, sh), padded(h, sh))


def test_a_run_checkpointed_with_the_unpadded_mlp_resumes_as_if_padded(tiny_scene, tmp_path):
    """A checkpoint whose colour MLP weights and Adam moments have the unpadded layout (a run
    interrupted before the thirty-first session) resumes to the same steps as the padded one."""
    scene = load_scene(tiny_scene)
    first = Trainer(scene, tiny_cfg("ngp", steps=3), tmp_path / "new")
    first.run(hooks=[], progress=False)
    first.save_checkpoint(finished=True)
    shutil.copytree(tmp_path / "new", tmp_path / "old")
    path = tmp_path / "old" / CHECKPOINT
    ck = torch.load(path, weights_only=False)
    net = first.field.color_net
    index = {id(p): i for i, p in enumerate(first.optimizer.param_groups[0]["params"])}
    for layer, cut in ((net[0], lambda t: t[:, 1:32]), (net[4], lambda t: t[:3])):
        key = "color_net.0.weight" if layer is net[0] else "color_net.4.weight"
        ck["field"][key] = cut(ck["field"][key]).clone()
        for name, v in ck["optimizer"]["state"][index[id(layer.weight)]].items():
            if torch.is_tensor(v) and v.dim() == 2:
                ck["optimizer"]["state"][index[id(layer.weight)]][name] = cut(v).clone()
    assert ck["field"]["color_net.0.weight"].shape == (net[0].out_features, 31)
    torch.save(ck, path)
    runs = []
    for name in ("new", "old"):
        tr = Trainer(scene, tiny_cfg("ngp", steps=5), tmp_path / name, True)
        tr.run(hooks=[], progress=False)
        runs.append(dict(tr.field.named_parameters()))
    for k, v in runs[0].items():
        torch.testing.assert_close(runs[1][k], v, rtol=0, atol=0, msg=k)


@pytest.mark.parametrize(
    "dtype,widths,word",
    [
        (torch.bfloat16, (16, 16), torch.int64),  # the colour MLP's input under autocast
        (torch.float32, (16, 16), torch.int64),  # ... and on a CPU
        (torch.float64, (3, 5), torch.int64),
        (torch.bfloat16, (3, 1), torch.int16),  # odd widths: 2-byte words
        (torch.float32, (3, 2), torch.int32),  # one word for all parts: no promotion
    ],
)
def test_concat_rows_is_torch_cat_copied_as_words(dtype, widths, word):
    g = torch.Generator().manual_seed(3)
    parts = [torch.randn(37, w, generator=g).to(dtype).requires_grad_(True) for w in widths]
    assert _word_for(parts) == word  # the word path is taken
    assert all(_as_words(p.detach(), word) is not None for p in parts)
    out, ref = concat_rows(parts), torch.cat(parts, 1)
    assert out.dtype == dtype and torch.equal(out, ref)
    cot = torch.randn(ref.shape, generator=g).to(dtype)
    got = torch.autograd.grad(out, parts, cot)
    want = torch.autograd.grad(ref, parts, cot)
    assert all(torch.equal(a, b) for a, b in zip(got, want, strict=True))


def test_concat_rows_falls_back_to_torch_cat_where_words_do_not_fit():
    base = torch.randn(8, 6)
    strided = base[:, ::2]  # not contiguous
    zeros = base.new_zeros(()).expand(8, 3)  # the colour MLP's padding columns
    offset = torch.randn(8 * 6 + 1)[1:].view(8, 6)  # rows of 24 bytes starting 4 bytes in
    for parts in ([strided, base], [base, zeros], [offset, offset], [base, base.double()]):
        parts = [p.clone() if p.dtype == torch.float64 else p for p in parts]
        if len({p.dtype for p in parts}) == 1:
            assert torch.equal(concat_rows(parts), torch.cat(parts, 1))
        else:  # mixed dtypes: torch.cat's own promotion
            assert torch.equal(concat_rows(parts), torch.cat(parts, 1))
    assert _as_words(strided, torch.int32) is None and _as_words(zeros, torch.int32) is None
    assert _word_for([offset, offset]) == torch.int64 and _as_words(offset, torch.int64) is None
    assert _word_for([base, base.double()]) is None


def _cat_dtypes(fn) -> list[torch.dtype]:
    """The dtypes of every aten.cat `fn` dispatches (its forward and backward)."""
    from torch.utils._python_dispatch import TorchDispatchMode

    seen = []

    class Spy(TorchDispatchMode):
        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            if func is torch.ops.aten.cat.default:
                seen.append(args[0][0].dtype)
            return func(*args, **(kwargs or {}))

    with Spy():
        fn()
    return seen


def test_the_colour_mlp_concatenates_the_fields_own_sh_as_words():
    """The field's SH come as a transposed view (kernels/sh.py); the bf16 input the colour MLP
    builds from them must still take the word copy (torch's 2-byte cat is the slow one)."""
    from kernels.sh import sh_encode

    torch.manual_seed(0)
    net = ColorMLP(15, 64).to(torch.bfloat16)
    d = torch.nn.functional.normalize(torch.randn(300, 3), dim=1)
    sh = sh_encode(d)
    assert not sh.is_contiguous()  # the layout this test is about
    h = torch.randn(300, 16).to(torch.bfloat16).requires_grad_(True)

    def step():
        net(h, sh).float().square().sum().backward()

    assert _cat_dtypes(step) == [torch.int64]
    want = net(h, sh.contiguous())
    assert torch.equal(net(h, sh), want)
    # the gradient reaches the directions through the kernel's layout as through rows
    d.requires_grad_(True)
    grads = []
    for layout in (lambda t: t, torch.Tensor.contiguous):
        (g,) = torch.autograd.grad(net(h, layout(sh_encode(d))).float().sum(), d)
        grads.append(g)
    assert torch.isfinite(grads[0]).all() and grads[0].abs().sum() > 0
    assert torch.equal(grads[0], grads[1])


def _heads_grads(split, dtype, colour: bool, logit: bool):
    """h's gradient through the σ logit and the colour MLP, the logit split from h by `split`."""
    torch.manual_seed(3)
    net = ColorMLP(15, 64).to(dtype)
    h = torch.randn(200, 16, dtype=torch.float64).to(dtype).requires_grad_(True)
    sh = torch.randn(200, 16, dtype=torch.float64).to(dtype)
    lg, hc = split(h)
    loss = (lg * torch.linspace(-2, 2, 200, dtype=lg.dtype)).sum() if logit else 0.0
    if colour:
        loss = loss + net(hc, sh).float().square().sum()
    (g,) = torch.autograd.grad(loss, h)
    return g


@pytest.mark.parametrize("dtype", [torch.float64, torch.bfloat16])
@pytest.mark.parametrize("colour, logit", [(True, True), (False, True), (True, False)])
def test_density_logit_gradient_is_the_selects_bit_for_bit(dtype, colour, logit):
    """density_logit adds the logit's gradient into the colour MLP's column 0 in place: the
    same bits as h[:, 0].float() beside h (a zero-filled select added to the colour's)."""

    def select(h):
        return h[:, 0].float(), h

    got = _heads_grads(density_logit, dtype, colour, logit)
    want = _heads_grads(select, dtype, colour, logit)
    assert got.dtype == dtype and torch.equal(got, want)
    assert (got[:, 0] != 0).any() == logit and (got[:, 1:] != 0).any() == colour


def test_density_logit_adds_into_a_gradient_it_does_not_own_out_of_place():
    """A gradient that another branch also reads (a pass-through's, or a broadcast) is not
    written: the logit's is added into a copy. Fails if the guard is dropped."""
    h = torch.randn(50, 16, dtype=torch.float64, requires_grad=True)
    lg, hc = density_logit(h)
    other = torch.zeros(50, 16, dtype=torch.float64, requires_grad=True)
    s = hc + other  # add's backward hands the same dense gradient tensor to both inputs
    w = torch.ones(50, 16, dtype=torch.float64)
    (gh, go) = torch.autograd.grad(lg.sum() + (s * w).sum(), (h, other))
    assert torch.equal(go, torch.ones(50, 16, dtype=torch.float64))
    assert torch.equal(gh[:, 0], torch.full((50,), 2.0, dtype=torch.float64))
    (gh,) = torch.autograd.grad(lg.sum() + hc.sum(), h)  # an expanded ones tensor
    assert torch.equal(gh[:, 1:], torch.ones(50, 15, dtype=torch.float64))


def test_linear_relu_is_relu_of_linear_values_and_gradients():
    """The fused layer (fields/mlp.py: one `_addmm_activation`, its own backward) against
    relu(F.linear) in float64: values and both gradients, a gradient of zero where the
    pre-activation is negative. Fails if the backward's mask or either GEMM is wrong."""
    g = torch.Generator().manual_seed(3)
    x = torch.randn(40, 12, generator=g, dtype=torch.float64, requires_grad=True)
    w = torch.randn(9, 12, generator=g, dtype=torch.float64, requires_grad=True)
    y = linear_relu(x, w)
    ref = torch.relu(torch.nn.functional.linear(x, w))
    assert (ref == 0).any() and (ref > 0).any()  # both sides of the kink are exercised
    torch.testing.assert_close(y, ref, rtol=1e-12, atol=1e-12)
    up = torch.randn(y.shape, generator=g, dtype=torch.float64)
    for a, b in zip(
        torch.autograd.grad(y, [x, w], up), torch.autograd.grad(ref, [x, w], up), strict=True
    ):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    assert torch.autograd.gradcheck(linear_relu, (x[:5].detach().requires_grad_(), w))


@pytest.mark.parametrize("geo", [15, 10])
def test_fused_relu_mlps_are_the_same_networks(geo):
    """`fused_relu` changes how the layers run, not the network: the same state dict, the same
    outputs and gradients (float64) for the density MLP's shape and the padded colour MLP,
    and under bf16 autocast the same output dtype and float32 weight gradients."""
    torch.manual_seed(5)
    plain = ColorMLP(geo, 32).double()
    torch.manual_seed(5)
    fused = ColorMLP(geo, 32, fused_relu=True).double()
    assert plain.state_dict().keys() == fused.state_dict().keys()
    h, sh = _inputs(29, geo)
    ya, yb = plain(h, sh), fused(h, sh)
    torch.testing.assert_close(ya, yb, rtol=1e-12, atol=1e-12)
    ga = torch.autograd.grad(ya.sum(), [h, *plain.parameters()])
    gb = torch.autograd.grad(yb.sum(), [h, *fused.parameters()])
    for a, b in zip(ga, gb, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    dens = mlp(32, 16, 1 + geo, 1, fused_relu=True)
    dens.load_state_dict(mlp(32, 16, 1 + geo, 1).state_dict())  # a plain checkpoint loads
    x = torch.randn(64, 32)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        y = dens(x)
        dens.fused_relu = False
        y_plain = dens(x)
    assert y.dtype == y_plain.dtype == torch.bfloat16
    torch.testing.assert_close(y.float(), y_plain.float(), rtol=2e-2, atol=2e-2)
    y.float().sum().backward()
    assert all(p.grad is not None and p.grad.dtype == torch.float32 for p in dens.parameters())
