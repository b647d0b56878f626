"""kernels/pose_rays: rays through refined poses and their gradient w.r.t. the corrections, and
the lazy row Adam step, on Warp's CPU backend against the torch reference in float64 (the
reference `PoseRefiner.rays` path of the same module, converted with `.double()`). Where CUDA
is available the comparisons run on it too."""

import pytest
import torch

from fastenerf.kernels.pose_rays import pose_rays
from fastenerf.optim import set_group_lr
from fastenerf.pose_refine import PoseRefiner, RowAdam
from fastenerf.render import generate_rays
from fastenerf.se3 import so3_exp

G = 9  # grid rows; the last is unused (a loop's twin of the first), row 4 too
USED = torch.tensor([True] * 4 + [False] + [True] * 3 + [False])
B = 3 * 40  # pixels: 3 windows of 40 rays, runs longer than a chunk and across chunks
DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


def grid(gen: torch.Generator) -> torch.Tensor:
    """(G, 4, 4) float32 camera-to-world poses: random rotations and centres."""
    c2w = torch.eye(4, dtype=torch.float64).repeat(G, 1, 1)
    c2w[:, :3, :3] = so3_exp(torch.randn(G, 3, generator=gen, dtype=torch.float64))
    c2w[:, :3, 3] = 2.0 * torch.randn(G, 3, generator=gen, dtype=torch.float64)
    return c2w.float()


def sampler_rows(gen: torch.Generator, layout: str) -> torch.Tensor:
    """(2B,) int64 grid rows: the sampler's layout (each window's rays in a run, all t0 rows
    then all t1 rows), or any order (shuffled, unused rows included)."""
    if layout == "runs":
        used = USED.nonzero()[:, 0]
        j = used[torch.randint(0, len(used) - 1, (3,), generator=gen)]
        t0 = j.repeat_interleave(B // 3)
        t1 = used[torch.searchsorted(used, j) + 1].repeat_interleave(B // 3)
        return torch.cat([t0, t1])
    return torch.randint(0, G, (2 * B,), generator=gen)


def refiner(gauge: str, translation: bool, scale: float, gen: torch.Generator) -> PoseRefiner:
    pr = PoseRefiner(grid(gen), USED, gauge, translation=translation)
    with torch.no_grad():
        pr.delta.copy_(scale * torch.randn(G, 6, generator=gen))
    return pr


def rays_and_grad(pr: PoseRefiner, dirs, idx, base_d, g_o, g_d, fused: bool):
    pr.delta.grad = None
    o, d, seen = pr.rays_and_rows(dirs.to(pr.delta.dtype), idx, base_d, fused=fused)
    ((o * g_o.to(o.dtype)).sum() + (d * g_d.to(d.dtype)).sum()).backward()
    return o.detach(), d.detach(), seen, pr.delta.grad.clone()


# per-component sizes (rad): exactly zero, tiny, small, moderate, large ones inside the
# kernel's series (|ω|² < 1) and outside it (closed forms)
@pytest.mark.parametrize("scale", [0.0, 1e-8, 1e-3, 0.05, 0.3, 1.0])
@pytest.mark.parametrize("layout", ["runs", "shuffled"])
@pytest.mark.parametrize("gauge", ["mean", "first", "none"])
@pytest.mark.parametrize("translation", [True, False])
@pytest.mark.parametrize("device", DEVICES)
def test_rays_and_gradients_match_float64(scale, layout, gauge, translation, device):
    gen = torch.Generator().manual_seed(7)
    pr = refiner(gauge, translation, scale, gen)
    idx = sampler_rows(gen, layout)
    dirs = torch.cat([torch.randn(B, 2, generator=gen) * 0.6, torch.ones(B, 1)], 1)
    base_d = generate_rays(dirs.repeat(2, 1), pr.base[idx])[1]  # the sampler's rays
    g_o, g_d = torch.randn(2 * B, 3, generator=gen), torch.randn(2 * B, 3, generator=gen)

    args = [t.to(device) for t in (dirs, idx, base_d, g_o, g_d)]
    o, d, seen, grad = (t.cpu() for t in rays_and_grad(pr.to(device), *args, fused=True))
    pr.cpu()
    ref = PoseRefiner(pr.base, USED, gauge, translation=translation).double()
    with torch.no_grad():
        ref.delta.copy_(pr.delta.double())
    o64, d64, seen64, grad64 = rays_and_grad(ref, dirs, idx, None, g_o, g_d, fused=False)

    assert o.dtype == d.dtype == grad.dtype == torch.float32
    torch.testing.assert_close(o.double(), o64, atol=1e-6, rtol=0)
    torch.testing.assert_close(d.double(), d64, atol=5e-7, rtol=0)
    assert torch.equal(seen, seen64) and torch.equal(seen, torch.isin(torch.arange(G), idx))
    assert torch.isfinite(grad).all() and grad.abs().sum() > 0
    torch.testing.assert_close(grad.double(), grad64, atol=1e-6 * grad64.abs().max(), rtol=1e-5)
    off = ~ref.mask.bool()
    assert (grad[off] == 0).all()  # unused rows, the fixed first row, shifts when rotations only
    if scale == 0.0:  # uncorrected rows keep the sampler's rays bit for bit
        assert torch.equal(d, base_d) and torch.equal(o, pr.base[idx, :3, 3])


def test_zero_corrections_give_generate_rays_without_the_samplers_rays():
    """Without base rays the fused path computes them (`render.generate_rays`), so δ = 0
    still gives exactly the uncorrected rays; its gradient there is finite."""
    gen = torch.Generator().manual_seed(1)
    pr = refiner("mean", True, 0.0, gen)
    idx = sampler_rows(gen, "runs")
    dirs = torch.randn(B, 3, generator=gen)
    o, d = pr.rays(dirs, idx)
    o_ref, d_ref = generate_rays(dirs.repeat(2, 1), pr.base[idx])
    assert torch.equal(o, o_ref) and torch.equal(d, d_ref)
    d.sum().backward()  # the origins unused: their gradient is None
    assert torch.isfinite(pr.delta.grad).all() and pr.delta.grad[:, :3].abs().sum() > 0
    assert (pr.delta.grad[:, 3:] == 0).all()


def test_fused_matches_the_torch_path_in_float32():
    gen = torch.Generator().manual_seed(2)
    pr = refiner("mean", True, 0.02, gen)
    idx = sampler_rows(gen, "runs")
    dirs = torch.randn(B, 3, generator=gen)
    g_o, g_d = torch.randn(2 * B, 3, generator=gen), torch.randn(2 * B, 3, generator=gen)
    got = rays_and_grad(pr, dirs, idx, None, g_o, g_d, fused=True)
    want = rays_and_grad(pr, dirs, idx, None, g_o, g_d, fused=False)
    for a, b in zip(got, want, strict=True):
        torch.testing.assert_close(a, b, atol=2e-6, rtol=1e-5)


def test_bad_inputs():
    gen = torch.Generator().manual_seed(0)
    pr = refiner("mean", True, 0.0, gen)
    idx = sampler_rows(gen, "runs")
    dirs = torch.randn(B, 3)
    args = (pr.delta, pr.base, pr.mask)
    with pytest.raises(ValueError, match="float32"):
        pose_rays(pr.delta.double(), pr.base, pr.mask, dirs, idx, torch.zeros(2 * B, 3), True)
    with pytest.raises(ValueError, match="dirs"):
        pose_rays(*args, dirs[:7], idx, torch.zeros(2 * B, 3), True)
    with pytest.raises(ValueError, match="base_d"):
        pose_rays(*args, dirs, idx, torch.zeros(B, 3), True)


# ------------------------------------------------------------------------------ row Adam


@pytest.mark.parametrize("with_rows", [True, False])
@pytest.mark.parametrize("device", DEVICES)
def test_row_adam_kernel_matches_the_torch_step(with_rows, device):
    gen = torch.Generator().manual_seed(4)
    p_k = torch.nn.Parameter(torch.randn(G, 6, generator=gen).to(device))
    p_t = torch.nn.Parameter(p_k.detach().clone())
    opt_k = RowAdam([p_k], lr=1e-2, eps=1e-12)
    opt_t = RowAdam([p_t], lr=1e-2, eps=1e-12, fused=False)
    for step in range(8):
        g = torch.randn(G, 6, generator=gen)
        seen = torch.rand(G, generator=gen) < 0.5
        if not with_rows:
            g[~seen] = 0.0  # rows None: the rows with a gradient step
        found_inf = torch.tensor(float(step == 3), device=device)  # one skipped step
        g, seen = g.to(device), seen.to(device)
        for p, opt in ((p_k, opt_k), (p_t, opt_t)):
            p.grad = g.clone()
            opt.param_groups[0]["lr"] = 1e-2 * 0.9**step
            opt.step(seen if with_rows else None, found_inf=found_inf)
    torch.testing.assert_close(p_k.detach(), p_t.detach(), atol=1e-7, rtol=1e-6)
    for key in ("exp_avg", "exp_avg_sq", "row_steps"):
        # float32 both; CUDA contracts multiply-adds differently in torch and Warp (1.7e-6
        # relative measured on an H200), the CPU build agrees to 1e-7
        torch.testing.assert_close(opt_k.state[p_k][key], opt_t.state[p_t][key], atol=0, rtol=1e-5)
    assert opt_k.state[p_k]["row_steps"].max() <= 7  # the skipped step counted for no row


def test_row_adam_kernel_without_found_inf_and_unseen_rows_kept():
    p = torch.nn.Parameter(torch.zeros(4, 6))
    opt = RowAdam([p], lr=1e-2)
    p.grad = torch.ones(4, 6)
    opt.step(torch.tensor([True, False, True, False]))
    assert (p[[1, 3]] == 0).all() and torch.allclose(p[[0, 2]], torch.full((2, 6), -1e-2))
    assert opt.state[p]["row_steps"][:, 0].tolist() == [1, 0, 1, 0]


def _row_adam_float64(
    p, grads, rows, flags, lrs, decay, b1=0.9, b2=0.999, eps=1e-12, gate=0.0, gate_beta=0.9
):
    """The lazy row Adam with its decoupled decay, row by row in float64: a row the batch saw
    (on a step without found_inf) takes Adam's step, then is multiplied by 1 − min(1, lr·decay).
    gate > 0: each component's step times clamp(z / gate − 1, 0, 1), z = |ḡ| / √(ŝ c), ḡ and ŝ
    the bias-corrected gate_beta-averages of g and g², c the variance of such an average of t
    unit draws, Σw² / (Σw)² with w_i = β^(t−i) summed term by term."""
    p = p.double().clone()
    m, v, t = torch.zeros_like(p), torch.zeros_like(p), [0] * len(p)
    gm, sq = torch.zeros_like(p), torch.zeros_like(p)
    for g_all, seen, skip, lr in zip(grads, rows, flags, lrs, strict=True):
        for r in range(len(p)) if not skip else ():
            if not seen[r]:
                continue
            g = g_all[r].double()
            t[r] += 1
            m[r] = b1 * m[r] + (1 - b1) * g
            v[r] = b2 * v[r] + (1 - b2) * g * g
            step = lr * (m[r] / (1 - b1 ** t[r])) / ((v[r] / (1 - b2 ** t[r])).sqrt() + eps)
            if gate > 0:
                bg = gate_beta
                gm[r] = bg * gm[r] + (1 - bg) * g
                sq[r] = bg * sq[r] + (1 - bg) * g * g
                w = [bg ** (t[r] - i) for i in range(1, t[r] + 1)]
                c = sum(x * x for x in w) / sum(w) ** 2
                z = (gm[r] / (1 - bg ** t[r])).abs() / (sq[r] / (1 - bg ** t[r]) * c).sqrt()
                step = step * (z / gate - 1).clamp(0.0, 1.0)
            p[r] = (p[r] - step) * (1 - min(1.0, lr * decay))
    return p


@pytest.mark.parametrize("gate,gate_beta", [(0.5, 0.9), (1.0, 0.9), (2.0, 0.9), (1.5, 0.99)])
@pytest.mark.parametrize("fused", [True, False])
@pytest.mark.parametrize("device", DEVICES)
def test_row_adam_gate_matches_float64(gate, gate_beta, fused, device):
    """The significance gate (kernel and torch step) against the float64 reference, with the
    decay and a skipped step: gradients with a common part and noise, so that some components
    open, some stay shut and some are in between. gate_sq changes only on the rows stepped."""
    gen = torch.Generator().manual_seed(6)
    start = torch.randn(G, 6, generator=gen)
    p = torch.nn.Parameter(start.clone().to(device))
    opt = RowAdam([p], lr=1e-2, eps=1e-12, fused=fused, gate=gate, gate_beta=gate_beta)
    bias = torch.randn(G, 6, generator=gen)
    grads, rows, flags, lrs = [], [], [], []
    for step in range(12):
        g = bias + torch.randn(G, 6, generator=gen)
        seen = torch.rand(G, generator=gen) < 0.7
        lr, skip = 1e-2 * 0.9**step, step == 5
        p.grad = g.to(device)
        opt.param_groups[0]["lr"] = lr
        sq_before = opt.state[p]["gate_sq"].clone() if opt.state[p] else None
        opt.step(seen.to(device), found_inf=torch.tensor(float(skip), device=device), decay=4.0)
        if sq_before is not None:
            keep = (torch.ones(G, dtype=torch.bool) if skip else ~seen).to(device)
            assert torch.equal(opt.state[p]["gate_sq"][keep], sq_before[keep])
        assert "gate_m" in opt.state[p]
        grads, rows, flags, lrs = grads + [g], rows + [seen], flags + [skip], lrs + [lr]
    want = _row_adam_float64(start, grads, rows, flags, lrs, 4.0, gate=gate, gate_beta=gate_beta)
    torch.testing.assert_close(p.detach().cpu().double(), want, atol=1e-7, rtol=1e-5)
    moved = (p.detach().cpu().double() - start.double()).abs()
    ungated = _row_adam_float64(start, grads, rows, flags, lrs, 4.0)
    assert (moved < (ungated - start.double()).abs() - 1e-6).any()  # the gate held some back


@pytest.mark.parametrize("decay", [0.0, 4.0, 150.0])  # lr·decay 0, up to 0.04, >= 1 at first
@pytest.mark.parametrize("fused", [True, False])
@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("lr_tensor", [False, True])
def test_row_adam_decay_matches_float64(decay, fused, device, lr_tensor):
    """The decay of `RowAdam.step(decay=...)` (kernel and torch step): only on the rows the
    batch saw, after their Adam step, none on a found_inf step; lr·decay >= 1 zeroes the row.
    lr_tensor: the lr a device tensor filled each step (`RowAdam.lr_as_tensors`, what a
    captured step reads), the same steps."""
    gen = torch.Generator().manual_seed(5)
    start = torch.randn(G, 6, generator=gen)
    p = torch.nn.Parameter(start.clone().to(device))
    opt = RowAdam([p], lr=1e-2, eps=1e-12, fused=fused)
    if lr_tensor:
        opt.lr_as_tensors(torch.device(device))
    grads, rows, flags, lrs = [], [], [], []
    for step in range(8):
        g = torch.randn(G, 6, generator=gen)
        seen = torch.rand(G, generator=gen) < 0.5
        seen[step % G] = True  # every step sees a row
        lr = 1e-2 * 0.7**step  # lr·decay = 1.5 on the first step with decay 150, 0.18 at last
        before = p.detach().clone()
        p.grad = g.to(device)
        set_group_lr(opt.param_groups[0], lr)
        skip = step == 3
        opt.step(seen.to(device), found_inf=torch.tensor(float(skip), device=device), decay=decay)
        after = p.detach()
        grads, rows, flags, lrs = grads + [g], rows + [seen], flags + [skip], lrs + [lr]
        if skip or not seen.all():  # rows not stepped keep every bit
            keep = torch.ones(G, dtype=torch.bool) if skip else ~seen
            assert torch.equal(after[keep.to(device)], before[keep.to(device)])
        if lr * decay >= 1 and not skip:  # the clamp: rows seen are zeroed, not flipped
            assert (after[seen.to(device)] == 0).all() and (before[seen.to(device)] != 0).any()
    want = _row_adam_float64(start, grads, rows, flags, lrs, decay)
    torch.testing.assert_close(p.detach().cpu().double(), want, atol=1e-7, rtol=1e-5)
    # decay 0 is no decay, bit for bit: the same steps without the argument (and a float
    # lr's steps are a tensor lr's, bit for bit)
    if decay == 0.0 or lr_tensor:
        q = torch.nn.Parameter(start.clone().to(device))
        opt_q = RowAdam([q], lr=1e-2, eps=1e-12, fused=fused)
        for g, seen, skip, lr in zip(grads, rows, flags, lrs, strict=True):
            q.grad, opt_q.param_groups[0]["lr"] = g.to(device), lr
            flag = torch.tensor(float(skip), device=device)
            opt_q.step(seen.to(device), found_inf=flag, **({"decay": decay} if decay else {}))
        assert torch.equal(q.detach(), p.detach())


@pytest.mark.parametrize("fused", [True, False])
@pytest.mark.parametrize("device", DEVICES)
def test_row_adam_gate_on_components_without_gradient_stays_finite(fused, device):
    """A seen row whose gradient is exactly zero in some components (the shift columns when
    only turns are learnt are masked to zero on every step) has ŝ = 0 there: the gate's z would
    be 0/0. Those components stay as they were (no NaN), the others step."""
    p = torch.nn.Parameter(torch.zeros(G, 6, device=device))
    opt = RowAdam([p], lr=1e-2, eps=1e-12, fused=fused, gate=0.5)
    for _ in range(5):
        g = torch.zeros(G, 6, device=device)
        g[:, :3] = 1.0  # turns: a steady pull; shifts: none
        p.grad = g
        opt.step(torch.ones(G, dtype=torch.bool, device=device))
    assert torch.isfinite(p).all() and (p[:, 3:] == 0).all() and (p[:, :3] < 0).all()


def test_row_adam_decay_rejects_a_negative_decay_and_gate():
    p = torch.nn.Parameter(torch.zeros(2, 6))
    p.grad = torch.ones(2, 6)
    with pytest.raises(ValueError, match="decay"):
        RowAdam([p], lr=1e-2).step(torch.tensor([True, False]), decay=-1.0)
    with pytest.raises(ValueError, match="gate"):
        RowAdam([p], lr=1e-2, gate=-1.0)


@pytest.mark.parametrize("layout", ["runs", "shuffled"])
@pytest.mark.parametrize("device", DEVICES)
def test_shared_row_rays_and_gradient(layout, device):
    """refine_shared: one (1, 6) row for every pose; a ray's direction is c2w_i · Exp(ω) d and
    its origin the centre (rotations only); the fused kernels (the row broadcast to the grid,
    its gradient summed back) match the float64 torch path, whose gradient matches finite
    differences; rays of several poses all reach the one row."""
    gen = torch.Generator().manual_seed(3)
    pr = PoseRefiner(grid(gen), USED, "none", translation=False, shared=True)
    assert pr.delta.shape == (1, 6)
    with pytest.raises(ValueError, match="no gauge"):
        PoseRefiner(pr.base, USED, "mean", shared=True)
    with torch.no_grad():
        pr.delta.copy_(torch.tensor([[0.02, -0.03, 0.01, 0.5, 0.5, 0.5]]))
    idx = sampler_rows(gen, layout)
    assert len(idx.unique()) > 2
    dirs = torch.cat([torch.randn(B, 2, generator=gen) * 0.6, torch.ones(B, 1)], 1)
    base_d = generate_rays(dirs.repeat(2, 1), pr.base[idx])[1]
    g_o, g_d = torch.randn(2 * B, 3, generator=gen), torch.randn(2 * B, 3, generator=gen)
    args = [t.to(device) for t in (dirs, idx, base_d, g_o, g_d)]
    o, d, seen, grad = (t.cpu() for t in rays_and_grad(pr.to(device), *args, fused=True))
    pr.cpu()
    ref = PoseRefiner(pr.base, USED, "none", translation=False, shared=True).double()
    with torch.no_grad():
        ref.delta.copy_(pr.delta.double())
    o64, d64, seen64, grad64 = rays_and_grad(ref, dirs, idx, None, g_o, g_d, fused=False)
    # the maths of a mis-mounted camera: every pose's own rotation, then the one turn
    R = pr.base[:, :3, :3].double() @ so3_exp(pr.delta[0, :3].double())
    want = torch.nn.functional.normalize(
        torch.einsum("nij,nj->ni", R[idx], dirs.double().repeat(2, 1)), dim=-1
    )
    torch.testing.assert_close(d64, want, atol=1e-7, rtol=0)  # a float32 base: R ω rotated
    torch.testing.assert_close(o64, pr.base[idx, :3, 3].double(), atol=0, rtol=0)
    torch.testing.assert_close(ref.c2w()[:, :3, :3].double(), R.float().double(), atol=1e-6, rtol=0)
    torch.testing.assert_close(o.double(), o64, atol=1e-6, rtol=0)
    torch.testing.assert_close(d.double(), d64, atol=5e-7, rtol=0)
    assert seen.tolist() == seen64.tolist() == [True]
    assert grad.shape == (1, 6) and (grad[0, 3:] == 0).all() and grad[0, :3].abs().min() > 0
    torch.testing.assert_close(grad.double(), grad64, atol=1e-6 * grad64.abs().max(), rtol=1e-5)

    def loss(delta):
        with torch.no_grad():
            ref.delta.copy_(delta)
            o, d = ref.rays(dirs.double(), idx, fused=False)
            return float((o * g_o.double()).sum() + (d * g_d.double()).sum())

    h, fd = 1e-6, torch.zeros(3, dtype=torch.float64)
    for j in range(3):
        e = torch.zeros(1, 6, dtype=torch.float64)
        e[0, j] = h
        fd[j] = (loss(pr.delta.double() + e) - loss(pr.delta.double() - e)) / (2 * h)
    torch.testing.assert_close(grad64[0, :3], fd, atol=1e-6 * fd.abs().max(), rtol=1e-6)
    with torch.no_grad():
        ref.delta.copy_(pr.delta.double())
    # each pose's rays alone give the row a gradient: the shared one is their sum
    parts = torch.zeros(1, 6, dtype=torch.float64)
    for row in idx.unique():
        keep = (idx == row)[:, None].double()
        _, _, _, gr = rays_and_grad(ref, dirs, idx, None, g_o * keep, g_d * keep, fused=False)
        assert gr[0, :3].abs().max() > 0
        parts += gr
    torch.testing.assert_close(parts, grad64, atol=1e-9 * grad64.abs().max(), rtol=1e-9)
