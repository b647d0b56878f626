"""Rays through refined poses (issue #20) in a handful of launches, with a hand-written backward.

`pose_refine.PoseRefiner.rays` in torch is ~30 small ops forward (the so3 exponential of every
grid row, the gauge, index_select, einsum, normalize) and as many autograd nodes backward: on
a GPU the refined step is paced by their launches, not by their arithmetic. Here:

forward   `_gauge_sums`       one thread per row: the used rows' world-frame corrections
                              summed by atomics ("mean" gauge only)
          `_corrected_rows`   one thread per row: δ = [w, v] less the mean, R' = Exp(w) R,
                              o' = t + v; clears the row's `seen` flag
          `_gather_rays`      one thread per ray: o'[p], normalize(R'[p] · dir); marks `seen`
backward  `_ray_grads`        one thread per chunk of consecutive rays: the chunk's gradient
                              summed in registers while the row stays the same, added to the
                              row once per change (the sampler lays rays out in long runs of
                              one row, so a few atomics per row instead of one per ray; any
                              order is still summed right, only with more atomics)
          `_row_grads`        one thread per row: back through Exp(w) R (Rodrigues'
                              derivative, series near 0) and o' = t + v; gauge sums by atomics
          `_delta_grads`      one thread per row: back through the gauge and the base rotation

A row whose rotation correction is exactly zero has R' = R, so its rays are the uncorrected
rays `base_d` as given (the sampler's `render.generate_rays`): at δ = 0 the result is the
sampler's rays bit for bit on every device, whatever the kernel's rounding of R'·d.

`row_adam` is `pose_refine.RowAdam`'s lazy row-wise Adam step, with its decoupled decay of the
rows stepped and its significance gate, in one launch.
"""

from __future__ import annotations

import torch
import warp as wp

from .common import fast_view, init, launch

init()

# Below this |ω|² (rad²) Exp's coefficients and their derivatives come from their Taylor
# series (`se3.so3_exp`'s, to more terms): in float32 the closed forms cancel, 1 − cos θ and
# θ cos θ − sin θ lose most digits at small θ (a relative error ~1e-5 of the pose gradient
# near θ = 1e-3 rad); six terms are exact to ~1e-10 up to here.
_SERIES = wp.constant(1.0)
_NORM_EPS = wp.constant(1e-12)  # torch.nn.functional.normalize's eps
CHUNK = 32  # rays per thread in the backward's gather-sum


# ---------------------------------------------------------------------------------- so(3)


@wp.func
def _rotation(m: wp.mat44) -> wp.mat33:
    return wp.mat33(m[0, 0], m[0, 1], m[0, 2], m[1, 0], m[1, 1], m[1, 2], m[2, 0], m[2, 1], m[2, 2])


@wp.func
def _skew(w: wp.vec3) -> wp.mat33:
    """[ω]×: [ω]× v = ω × v."""
    return wp.mat33(0.0, -w[2], w[1], w[2], 0.0, -w[0], -w[1], w[0], 0.0)


@wp.func
def _vee(m: wp.mat33) -> wp.vec3:
    """(⟨M, [e_x]×⟩, ⟨M, [e_y]×⟩, ⟨M, [e_z]×⟩): the gradient w.r.t. ω of ⟨M, [ω]×⟩."""
    return wp.vec3(m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1])


@wp.func
def _series(x: float, c0: float, c1: float, c2: float, c3: float, c4: float, c5: float):
    """c0 + c1 x + ... + c5 x⁵ (Horner)."""
    return c0 + x * (c1 + x * (c2 + x * (c3 + x * (c4 + x * c5))))


@wp.func
def _exp_coeffs(x: float) -> wp.vec2:
    """(A, B) = (sin θ / θ, (1 − cos θ) / θ²) at x = θ² = |ω|²."""
    if x < _SERIES:  # Σ (−x)^k / (2k + 1)!, Σ (−x)^k / (2k + 2)!
        a = _series(
            x, 1.0, -1.0 / 6.0, 1.0 / 120.0, -1.0 / 5040.0, 1.0 / 362880.0, -1.0 / 39916800.0
        )
        b = _series(
            x, 0.5, -1.0 / 24.0, 1.0 / 720.0, -1.0 / 40320.0, 1.0 / 3628800.0, -1.0 / 479001600.0
        )
        return wp.vec2(a, b)
    th = wp.sqrt(x)
    return wp.vec2(wp.sin(th) / th, (1.0 - wp.cos(th)) / x)


@wp.func
def _exp_coeffs_grad(x: float) -> wp.vec2:
    """(dA/dθ², dB/dθ²) at x = θ² = |ω|²."""
    if x < _SERIES:  # the series above, differentiated term by term
        da = _series(x, -1.0 / 6.0, 1.0 / 60.0, -1.0 / 1680.0, 1.0 / 90720.0, -1.0 / 7983360.0, 0.0)
        db = _series(
            x, -1.0 / 24.0, 1.0 / 360.0, -1.0 / 13440.0, 1.0 / 907200.0, -1.0 / 95800320.0, 0.0
        )
        return wp.vec2(da, db)
    th = wp.sqrt(x)
    s = wp.sin(th)
    c = wp.cos(th)
    return wp.vec2((th * c - s) / (2.0 * x * th), (th * s - 2.0 * (1.0 - c)) / (2.0 * x * x))


@wp.func
def _so3_exp(w: wp.vec3) -> wp.mat33:
    """Exp(ω) = I + A [ω]× + B [ω]×² (Rodrigues), finite with finite gradients at ω = 0."""
    ab = _exp_coeffs(wp.dot(w, w))
    k = _skew(w)
    return wp.identity(n=3, dtype=float) + ab[0] * k + ab[1] * (k * k)


@wp.func
def _so3_exp_grad(w: wp.vec3, g: wp.mat33) -> wp.vec3:
    """∂L/∂ω of L through E = Exp(ω), given g = ∂L/∂E (3, 3).

    E = I + A K + B K², K = [ω]×: ∂E/∂ω_j = A [e_j]× + B ([e_j]× K + K [e_j]×) + 2 ω_j (A' K
    + B' K²) with A', B' the derivatives w.r.t. θ²; ⟨g, [e_j]× K⟩ = ⟨g Kᵀ, [e_j]×⟩ and
    ⟨g, K [e_j]×⟩ = ⟨Kᵀ g, [e_j]×⟩.
    """
    th2 = wp.dot(w, w)
    ab = _exp_coeffs(th2)
    dab = _exp_coeffs_grad(th2)
    k = _skew(w)
    kt = wp.transpose(k)
    radial = 2.0 * (dab[0] * wp.ddot(g, k) + dab[1] * wp.ddot(g, k * k))
    return ab[0] * _vee(g) + ab[1] * _vee(g * kt + kt * g) + radial * w


# ---------------------------------------------------------------------------------- rows


@wp.func
def _world(
    delta: wp.array2d(dtype=float), mask: wp.array2d(dtype=float), r: wp.mat33, g: int, j: int
):
    """World-frame half j (0: rotation, 1: shift) of row g's masked camera-frame correction."""
    c = 3 * j
    u = wp.vec3(
        delta[g, c] * mask[g, c], delta[g, c + 1] * mask[g, c + 1], delta[g, c + 2] * mask[g, c + 2]
    )
    return r * u


@wp.kernel(enable_backward=False)
def _gauge_sums(
    delta: wp.array2d(dtype=float),
    mask: wp.array2d(dtype=float),
    base: wp.array(dtype=wp.mat44),
    sums: wp.array(dtype=float),
):
    """sums[0:6] += the row's world-frame correction, sums[6] += its gauge weight (0 or 1);
    `sums` arrives zeroed."""
    g = wp.tid()
    rows = mask[g, 0]
    if rows == 0.0:
        return  # its correction is masked to zero: nothing to add
    r = _rotation(base[g])
    w = _world(delta, mask, r, g, 0)
    v = _world(delta, mask, r, g, 1)
    for j in range(3):
        wp.atomic_add(sums, j, w[j])
        wp.atomic_add(sums, 3 + j, v[j])
    wp.atomic_add(sums, 6, rows)


@wp.kernel(enable_backward=False)
def _corrected_rows(
    delta: wp.array2d(dtype=float),
    mask: wp.array2d(dtype=float),
    base: wp.array(dtype=wp.mat44),
    sums: wp.array(dtype=float),
    centre: int,
    corr: wp.array2d(dtype=float),
    rot: wp.array(dtype=wp.mat33),
    origin: wp.array(dtype=wp.vec3),
    seen: wp.array(dtype=wp.uint8),
):
    """corr = gauge-fixed world-frame [w, v] (G, 6); rot = Exp(w) R; origin = t + v; the row's
    `seen` flag cleared for `_gather_rays` to mark."""
    g = wp.tid()
    m = base[g]
    r = _rotation(m)
    w = _world(delta, mask, r, g, 0)
    v = _world(delta, mask, r, g, 1)
    if centre != 0:
        n = sums[6]
        rows = mask[g, 0]
        w = w - rows * (wp.vec3(sums[0], sums[1], sums[2]) / n)
        v = v - rows * (wp.vec3(sums[3], sums[4], sums[5]) / n)
    for j in range(3):
        corr[g, j] = w[j]
        corr[g, 3 + j] = v[j]
    rot[g] = _so3_exp(w) * r
    origin[g] = wp.vec3(m[0, 3], m[1, 3], m[2, 3]) + v
    seen[g] = wp.uint8(0)


@wp.kernel(enable_backward=False)
def _gather_rays(
    pose_idx: wp.array(dtype=wp.int64),
    dirs: wp.array(dtype=wp.vec3),
    corr: wp.array2d(dtype=float),
    rot: wp.array(dtype=wp.mat33),
    origin: wp.array(dtype=wp.vec3),
    base_d: wp.array(dtype=wp.vec3),
    rays_o: wp.array(dtype=wp.vec3),
    rays_d: wp.array(dtype=wp.vec3),
    seen: wp.array(dtype=wp.uint8),
):
    """Ray i: origin[p] and normalize(rot[p] · dirs[i mod B]), p = pose_idx[i]; a row without
    a rotation correction keeps the given uncorrected direction (bit for bit)."""
    i = wp.tid()
    p = pose_idx[i]
    rays_o[i] = origin[p]
    if corr[p, 0] == 0.0 and corr[p, 1] == 0.0 and corr[p, 2] == 0.0:
        rays_d[i] = base_d[i]
    else:
        y = rot[p] * dirs[i % dirs.shape[0]]
        rays_d[i] = y / wp.max(wp.length(y), _NORM_EPS)
    seen[p] = wp.uint8(1)  # every writer stores the same value: no atomic needed


# ---------------------------------------------------------------------------------- backward


@wp.func
def _add_row(g_rows: wp.array2d(dtype=float), p: wp.int64, g_rot: wp.mat33, g_o: wp.vec3):
    for a in range(3):
        for b in range(3):
            wp.atomic_add(g_rows, p, 3 * a + b, g_rot[a, b])
        wp.atomic_add(g_rows, p, 9 + a, g_o[a])


@wp.kernel(enable_backward=False)
def _ray_grads(
    pose_idx: wp.array(dtype=wp.int64),
    dirs: wp.array(dtype=wp.vec3),
    rot: wp.array(dtype=wp.mat33),
    grad_o: wp.array(dtype=wp.vec3),
    grad_d: wp.array(dtype=wp.vec3),
    chunk: int,
    g_rows: wp.array2d(dtype=float),
):
    """g_rows[p] += [∂L/∂R'_p (row-major 9), ∂L/∂o'_p (3)] of rays chunk·c ... chunk·(c+1)−1;
    `g_rows` arrives zeroed. Through normalize: ∂n/∂y = (I − n nᵀ) / |y| (y / eps below eps)."""
    c = wp.tid()
    n_rays = pose_idx.shape[0]
    start = c * chunk
    end = wp.min(start + chunk, n_rays)
    row = pose_idx[start]
    r = rot[row]
    g_rot = wp.mat33()
    g_o = wp.vec3()
    for i in range(start, end):
        p = pose_idx[i]
        if p != row:
            _add_row(g_rows, row, g_rot, g_o)
            row = p
            r = rot[p]
            g_rot = wp.mat33()
            g_o = wp.vec3()
        x = dirs[i % dirs.shape[0]]
        y = r * x
        s = wp.length(y)
        gd = grad_d[i]
        gy = gd / _NORM_EPS
        if s > _NORM_EPS:
            n = y / s
            gy = (gd - n * wp.dot(n, gd)) / s
        g_rot += wp.outer(gy, x)
        g_o += grad_o[i]
    _add_row(g_rows, row, g_rot, g_o)


@wp.kernel(enable_backward=False)
def _row_grads(
    base: wp.array(dtype=wp.mat44),
    mask: wp.array2d(dtype=float),
    corr: wp.array2d(dtype=float),
    g_rows: wp.array2d(dtype=float),
    centre: int,
    g_world: wp.array2d(dtype=float),
    g_sums: wp.array(dtype=float),
):
    """g_world = ∂L/∂[w, v] (G, 6) through R' = Exp(w) R and o' = t + v; with the "mean" gauge
    g_sums[0:6] += the used rows' g_world (`g_sums` arrives zeroed)."""
    g = wp.tid()
    g_rot = wp.mat33(
        g_rows[g, 0], g_rows[g, 1], g_rows[g, 2],
        g_rows[g, 3], g_rows[g, 4], g_rows[g, 5],
        g_rows[g, 6], g_rows[g, 7], g_rows[g, 8],
    )  # fmt: skip
    r = _rotation(base[g])
    w = wp.vec3(corr[g, 0], corr[g, 1], corr[g, 2])
    gw = _so3_exp_grad(w, g_rot * wp.transpose(r))
    gv = wp.vec3(g_rows[g, 9], g_rows[g, 10], g_rows[g, 11])
    for j in range(3):
        g_world[g, j] = gw[j]
        g_world[g, 3 + j] = gv[j]
    rows = mask[g, 0]
    if centre != 0 and rows != 0.0:
        for j in range(3):
            wp.atomic_add(g_sums, j, rows * gw[j])
            wp.atomic_add(g_sums, 3 + j, rows * gv[j])


@wp.kernel(enable_backward=False)
def _delta_grads(
    base: wp.array(dtype=wp.mat44),
    mask: wp.array2d(dtype=float),
    g_world: wp.array2d(dtype=float),
    g_sums: wp.array(dtype=float),
    sums: wp.array(dtype=float),
    centre: int,
    g_delta: wp.array2d(dtype=float),
):
    """∂L/∂δ (G, 6): back through the gauge (w_g = d_g − rows_g Σ_h d_h / n, so every d_h also
    gets −Σ_g rows_g ∂L/∂w_g / n), the base rotation (d = R (δ ∘ mask)) and the mask."""
    g = wp.tid()
    r = wp.transpose(_rotation(base[g]))
    gw = wp.vec3(g_world[g, 0], g_world[g, 1], g_world[g, 2])
    gv = wp.vec3(g_world[g, 3], g_world[g, 4], g_world[g, 5])
    if centre != 0:
        n = sums[6]
        gw = gw - wp.vec3(g_sums[0], g_sums[1], g_sums[2]) / n
        gv = gv - wp.vec3(g_sums[3], g_sums[4], g_sums[5]) / n
    gw = r * gw
    gv = r * gv
    for j in range(3):
        g_delta[g, j] = gw[j] * mask[g, j]
        g_delta[g, 3 + j] = gv[j] * mask[g, 3 + j]


# ---------------------------------------------------------------------------------- autograd


def _v3(t: torch.Tensor) -> wp.array:
    return fast_view(t, wp.vec3)


class _PoseRays(torch.autograd.Function):
    @staticmethod
    def forward(ctx, delta, base, mask, dirs, pose_idx, base_d, centre):
        g, n = len(delta), len(pose_idx)
        dev = delta.device
        sums = torch.zeros(8, device=dev) if centre else delta.new_empty(8)  # unread if not
        if centre:
            launch(_gauge_sums, g, delta, [delta, mask, fast_view(base, wp.mat44), sums])
        corr = torch.empty(g, 6, device=dev)
        rot = torch.empty(g, 3, 3, device=dev)
        origin = torch.empty(g, 3, device=dev)
        seen = torch.empty(g, dtype=torch.bool, device=dev)
        seen_u8 = seen.view(torch.uint8)
        args = [delta, mask, fast_view(base, wp.mat44), sums, int(centre)]
        outs = [corr, fast_view(rot, wp.mat33), _v3(origin), seen_u8]
        launch(_corrected_rows, g, delta, args + outs)
        rays_o = torch.empty(n, 3, device=dev)
        rays_d = torch.empty(n, 3, device=dev)
        args = [pose_idx, _v3(dirs), corr, fast_view(rot, wp.mat33), _v3(origin), _v3(base_d)]
        launch(_gather_rays, n, delta, args + [_v3(rays_o), _v3(rays_d), seen_u8])
        ctx.save_for_backward(base, mask, dirs, pose_idx, corr, rot, sums)
        ctx.centre = centre
        ctx.mark_non_differentiable(seen)
        return rays_o, rays_d, seen

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_o, grad_d, _grad_seen):
        base, mask, dirs, pose_idx, corr, rot, sums = ctx.saved_tensors
        g, n, dev = len(base), len(pose_idx), base.device
        zero = None
        if grad_o is None or grad_d is None:
            zero = torch.zeros(n, 3, device=dev)
        grad_o = zero if grad_o is None else grad_o.float().contiguous()
        grad_d = zero if grad_d is None else grad_d.float().contiguous()
        buf = torch.zeros(g * 12 + 8, device=dev)  # one fill: the rows' sums, the gauge's
        g_rows, g_sums = buf[: g * 12].view(g, 12), buf[g * 12 :]
        args = [pose_idx, _v3(dirs), fast_view(rot, wp.mat33), _v3(grad_o), _v3(grad_d)]
        launch(_ray_grads, (n + CHUNK - 1) // CHUNK, base, args + [CHUNK, g_rows])
        base44 = fast_view(base, wp.mat44)
        g_world = torch.empty(g, 6, device=dev)
        launch(_row_grads, g, base, [base44, mask, corr, g_rows, int(ctx.centre), g_world, g_sums])
        g_delta = torch.empty(g, 6, device=dev)
        args = [base44, mask, g_world, g_sums, sums, int(ctx.centre), g_delta]
        launch(_delta_grads, g, base, args)
        return g_delta, None, None, None, None, None, None


def pose_rays(
    delta: torch.Tensor,
    base: torch.Tensor,
    mask: torch.Tensor,
    dirs: torch.Tensor,
    pose_idx: torch.Tensor,
    base_d: torch.Tensor,
    centre: bool,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Rays through corrected poses, differentiable w.r.t. delta (`PoseRefiner.rays`' maths).

    delta: (G, 6) float32 camera-frame corrections [ω (rad), u (world units)]; base: (G, 4, 4)
    float32 camera-to-world poses; mask: (G, 6) float32 (0: the entry is not learnt, and a row
    with mask[:, 0] = 0 is out of the gauge); dirs: (B, 3) camera-frame directions; pose_idx:
    (kB,) int64 grid row of each ray, in [0, G) (not checked: no host read), ray i seeing
    dirs[i mod B]; base_d: (kB, 3) float32 the rays' uncorrected directions, normalize(R·d)
    (returned as they are on rows without a rotation correction); centre: the "mean" gauge
    (subtract the used rows' mean world-frame correction).
    Returns rays_o (kB, 3) world units, rays_d (kB, 3) unit, float32, and seen (G,) bool: the
    rows pose_idx holds (no gradient).
    """
    g, n = delta.shape[0], pose_idx.shape[0]
    if delta.dtype != torch.float32 or delta.shape != (g, 6) or base.shape != (g, 4, 4):
        raise ValueError("pose_rays: delta (G, 6) and base (G, 4, 4) must be float32")
    if dirs.ndim != 2 or dirs.shape[1] != 3 or n % max(len(dirs), 1) or not len(dirs):
        raise ValueError(f"pose_rays: dirs must be (B, 3) with B dividing {n} rays")
    if base_d.shape != (n, 3):
        raise ValueError(f"pose_rays: base_d must be ({n}, 3)")
    return _PoseRays.apply(
        delta.contiguous(),
        base.float().contiguous(),
        mask.float().contiguous(),
        dirs.float().contiguous(),
        pose_idx.long().contiguous(),
        base_d.float().contiguous(),
        bool(centre),
    )


# ---------------------------------------------------------------------------------- Adam

_ZEROS: dict[torch.device, torch.Tensor] = {}


def _zero(device: torch.device) -> torch.Tensor:
    """A (1,) float32 zero on `device`, made once (the "no found_inf" flag)."""
    z = _ZEROS.get(device)
    if z is None:
        z = _ZEROS[device] = torch.zeros(1, device=device)
    return z


@wp.func
def _has_gradient(grad: wp.array2d(dtype=float), g: int) -> bool:
    for j in range(grad.shape[1]):
        if grad[g, j] != 0.0:
            return True
    return False


@wp.func
def _gate_factor(m_hat: float, s_hat: float, c: float, gate: float):
    """The significance gate's factor in [0, 1]: z = |m̂| / √(ŝ c), the mean gradient in
    standard errors of a zero-mean one; 0 up to z = gate, 1 from 2 gate, linear between."""
    var = s_hat * c
    if var <= 0.0:
        return 0.0
    z = wp.abs(m_hat) / wp.sqrt(var)
    return wp.clamp(z / gate - 1.0, 0.0, 1.0)


@wp.kernel(enable_backward=False)
def _row_adam(
    grad: wp.array2d(dtype=float),
    rows: wp.array(dtype=wp.uint8),
    use_rows: int,
    found_inf: wp.array(dtype=float),
    lr_now: wp.array(dtype=float),
    b1: float,
    b2: float,
    one_minus_b1: float,
    one_minus_b2: float,
    eps: float,
    decay: float,
    gate: float,
    gate_b: float,
    param: wp.array2d(dtype=float),
    exp_avg: wp.array2d(dtype=float),
    exp_avg_sq: wp.array2d(dtype=float),
    row_steps: wp.array2d(dtype=float),
    gate_m: wp.array2d(dtype=float),
    gate_sq: wp.array2d(dtype=float),
):
    """One row: Adam on it if it was seen (rows[g], or any nonzero gradient without `rows`)
    and found_inf[0] is 0, then the decoupled decay: the updated row times 1 − rate, rate =
    min(1, lr · decay) in float32; otherwise the row, its moments and its step count stay.
    lr_now[0]: the learning rate, read on the device (a captured step replays each step's).
    gate > 0: each component's Adam step times `_gate_factor` of the gate_b-averages of its
    gradient and squared gradient (gate_m, gate_sq); gate 0 leaves both untouched."""
    g = wp.tid()
    if found_inf[0] != 0.0:
        return
    if use_rows != 0:
        if rows[g] == wp.uint8(0):
            return
    elif not _has_gradient(grad, g):
        return
    t = row_steps[g, 0] + 1.0
    row_steps[g, 0] = t
    bc1 = 1.0 - wp.pow(b1, t)
    bc2 = 1.0 - wp.pow(b2, t)
    lr = lr_now[0]
    keep = 1.0 - wp.min(1.0, lr * decay)
    # the variance of a bias-corrected gate_b-average of t unit-variance draws: 1 at t = 1
    bcg = 1.0 - wp.pow(gate_b, t)
    c = (1.0 - gate_b) * (1.0 + wp.pow(gate_b, t)) / ((1.0 + gate_b) * bcg)
    for j in range(grad.shape[1]):
        gj = grad[g, j]
        m = exp_avg[g, j] * b1 + gj * one_minus_b1
        v = exp_avg_sq[g, j] * b2 + gj * gj * one_minus_b2
        exp_avg[g, j] = m
        exp_avg_sq[g, j] = v
        step = lr * (m / bc1) / (wp.sqrt(v / bc2) + eps)
        if gate > 0.0:
            gm = gate_m[g, j] * gate_b + gj * (1.0 - gate_b)
            s = gate_sq[g, j] * gate_b + gj * gj * (1.0 - gate_b)
            gate_m[g, j] = gm
            gate_sq[g, j] = s
            step = step * _gate_factor(gm / bcg, s / bcg, c, gate)
        param[g, j] = (param[g, j] - step) * keep  # Adam's step, then the decay (AdamW's)


def row_adam(
    param: torch.Tensor,
    grad: torch.Tensor,
    state: dict[str, torch.Tensor],
    rows: torch.Tensor | None,
    found_inf: torch.Tensor | None,
    lr: float | torch.Tensor,
    betas: tuple[float, float],
    eps: float,
    decay: float = 0.0,
    gate: float = 0.0,
    gate_beta: float = 0.9,
) -> None:
    """`RowAdam.step` on one (G, k) float32 parameter, in place, one launch.

    grad: (G, k) float32; state: exp_avg, exp_avg_sq (G, k) and row_steps (G, 1) float32,
    contiguous; rows: (G,) bool rows to step, or None (rows with a nonzero gradient);
    found_inf: optional 0-dim or (1,) flag on the device, non-zero: no row steps (and no
    decay); lr: a float, or a 1-element float32 tensor on the parameter's device that the
    kernel reads (what a captured step fills before each replay); decay: decoupled decay
    (AdamW's): each stepped row, after its Adam update, times 1 − min(1, lr · decay) (0: none,
    bit for bit); gate, gate_beta: the significance gate (`RowAdam`; 0: none, bit for bit),
    which needs state["gate_m"] and state["gate_sq"] (G, k) float32.
    """
    if decay < 0 or gate < 0:
        raise ValueError(f"row_adam: decay and gate must be >= 0, got {decay} and {gate}")
    b1, b2 = (float(b) for b in betas)
    dev = param.device
    flag = _zero(dev) if found_inf is None else found_inf.to(dev, torch.float32).reshape(1)
    use_rows = rows is not None
    rows_u8 = (rows.to(dev, torch.bool) if use_rows else flag).view(torch.uint8)
    args = [grad.contiguous(), rows_u8.contiguous(), int(use_rows), flag.contiguous()]
    if torch.is_tensor(lr):
        if lr.numel() != 1 or lr.dtype != torch.float32 or lr.device != dev:
            raise ValueError("row_adam: a tensor lr must be one float32 on the parameter's device")
        lr_now = lr.reshape(1)
    else:
        lr_now = torch.full((1,), float(lr), device=dev)
    args += [lr_now, b1, b2, 1.0 - b1, 1.0 - b2, float(eps), float(decay), float(gate)]
    args += [float(gate_beta), param, state["exp_avg"], state["exp_avg_sq"], state["row_steps"]]
    gated = gate > 0  # gate 0: the two are never touched
    args += [state["gate_m"] if gated else param, state["gate_sq"] if gated else param]
    launch(_row_adam, param.shape[0], param, args)
