"""Real spherical-harmonics direction encoding, degree 4 (16 coefficients), as Warp kernels.

Same basis, order and signs as tiny-cuda-nn / torch-ngp's ``sh_encoder`` with the direction
given in [-1, 1]^3 (a unit vector; torch-ngp's convention, not tcnn's [0, 1] input). No
normalisation happens here: the backward is the plain Jacobian of the polynomials.
"""

import functools

import torch
import warp as wp

from .common import FEATURE_DTYPES, fast_view, features_dtype, init, launch

init()

N_COEFFS = 16
BF16_GROUP = 4  # bf16 forward: consecutive coefficients a thread writes


VEC16 = wp.types.vector(length=N_COEFFS, dtype=wp.float32)


@wp.func
def sh_basis(v: wp.vec3) -> VEC16:
    """The 16 coefficients of unit direction v, float32."""
    x, y, z = v[0], v[1], v[2]
    xy, xz, yz = x * y, x * z, y * z
    x2, y2, z2 = x * x, y * y, z * z
    return VEC16(
        0.28209479177387814,  # 1/(2 sqrt(pi))
        -0.48860251190291987 * y,  # sqrt(3)/(2 sqrt(pi))
        0.48860251190291987 * z,
        -0.48860251190291987 * x,
        1.0925484305920792 * xy,  # sqrt(15)/(2 sqrt(pi))
        -1.0925484305920792 * yz,
        0.94617469575755997 * z2 - 0.31539156525251999,  # sqrt(5)(3z^2-1)/(4 sqrt(pi))
        -1.0925484305920792 * xz,
        0.54627421529603959 * (x2 - y2),  # sqrt(15)/(4 sqrt(pi))
        0.59004358992664352 * y * (y2 - 3.0 * x2),  # sqrt(70)/(8 sqrt(pi))
        2.8906114426405538 * xy * z,  # sqrt(105)/(2 sqrt(pi))
        0.45704579946446572 * y * (1.0 - 5.0 * z2),  # sqrt(42)/(8 sqrt(pi))
        0.3731763325901154 * z * (5.0 * z2 - 3.0),  # sqrt(7)/(4 sqrt(pi))
        0.45704579946446572 * x * (1.0 - 5.0 * z2),
        1.4453057213202769 * z * (x2 - y2),  # sqrt(105)/(4 sqrt(pi))
        0.59004358992664352 * x * (3.0 * y2 - x2),
    )


@functools.cache
def _sh_kernels(bf16: bool):
    """(forward, backward) kernels. float32: one thread a direction, the basis written
    feature-major, (16, N) storage handed on transposed; bf16 (`sh_encode`'s out_dtype):
    written row-major, (N, 16), one thread per four consecutive coefficients (a thread's four
    2-byte stores are contiguous, so a warp's stores cover 256 contiguous bytes, where a thread
    writing a whole 32-byte row would leave them 32 bytes apart; and the basis is computed 4x
    a direction rather than 16x as with one thread a coefficient), each value rounded to
    nearest even, and the gradient read as bf16. The arithmetic is float32."""
    ft = features_dtype(bf16)

    @wp.func
    def load_row(g: wp.array2d(dtype=ft), i: int) -> VEC16:
        """Row i of the (N, 16) gradient, as float32."""
        row = VEC16()
        for k in range(N_COEFFS):
            row[k] = wp.float32(g[i, k])
        return row

    @wp.kernel(enable_backward=False, module="unique")
    def sh_forward(d: wp.array(dtype=wp.vec3), out: wp.array2d(dtype=ft)):
        t = wp.tid()
        if wp.static(bf16):
            i = t // BF16_GROUP
            q = t - i * BF16_GROUP
            b = sh_basis(d[i])
            # constant indices only: the basis stays in registers
            v0, v1, v2, v3 = b[0], b[1], b[2], b[3]
            if q == 1:
                v0, v1, v2, v3 = b[4], b[5], b[6], b[7]
            if q == 2:
                v0, v1, v2, v3 = b[8], b[9], b[10], b[11]
            if q == 3:
                v0, v1, v2, v3 = b[12], b[13], b[14], b[15]
            k = q * BF16_GROUP
            out[i, k + 0] = ft(v0)
            out[i, k + 1] = ft(v1)
            out[i, k + 2] = ft(v2)
            out[i, k + 3] = ft(v3)
        else:
            b = sh_basis(d[t])
            for k in range(N_COEFFS):
                out[k, t] = b[k]

    @wp.kernel(enable_backward=False, module="unique")
    def sh_backward(
        d: wp.array(dtype=wp.vec3), g: wp.array2d(dtype=ft), grad_d: wp.array(dtype=wp.vec3)
    ):
        i = wp.tid()
        v = d[i]
        x, y, z = v[0], v[1], v[2]
        x2, y2, z2 = x * x, y * y, z * z
        c1 = 0.48860251190291987
        c2 = 1.0925484305920792
        c3 = 0.54627421529603959
        c4 = 0.59004358992664352
        c5 = 2.8906114426405538
        c6 = 0.45704579946446572
        c7 = 1.4453057213202769
        gv = load_row(g, i)
        g1, g2, g3, g4, g5 = gv[1], gv[2], gv[3], gv[4], gv[5]
        g6, g7, g8, g9, g10 = gv[6], gv[7], gv[8], gv[9], gv[10]
        g11, g12, g13, g14, g15 = gv[11], gv[12], gv[13], gv[14], gv[15]
        dx = (
            -c1 * g3
            + c2 * (y * g4 - z * g7)
            + 2.0 * c3 * x * g8
            - 6.0 * c4 * x * y * g9
            + c5 * y * z * g10
            + c6 * (1.0 - 5.0 * z2) * g13
            + 2.0 * c7 * x * z * g14
            + 3.0 * c4 * (y2 - x2) * g15
        )
        dy = (
            -c1 * g1
            + c2 * (x * g4 - z * g5)
            - 2.0 * c3 * y * g8
            + 3.0 * c4 * (y2 - x2) * g9
            + c5 * x * z * g10
            + c6 * (1.0 - 5.0 * z2) * g11
            - 2.0 * c7 * y * z * g14
            + 6.0 * c4 * x * y * g15
        )
        dz = (
            c1 * g2
            - c2 * (y * g5 + x * g7)
            + 2.0 * 0.94617469575755997 * z * g6
            + c5 * x * y * g10
            - 10.0 * c6 * z * (y * g11 + x * g13)
            + 0.3731763325901154 * (15.0 * z2 - 3.0) * g12
            + c7 * (x2 - y2) * g14
        )
        grad_d[i] = wp.vec3(dx, dy, dz)

    return sh_forward, sh_backward


class _SHEncode(torch.autograd.Function):
    @staticmethod
    def forward(ctx, d, out_dtype):
        bf16 = out_dtype == torch.bfloat16
        shape = (d.shape[0], N_COEFFS) if bf16 else (N_COEFFS, d.shape[0])
        storage = torch.empty(shape, dtype=out_dtype, device=d.device)
        if d.shape[0]:
            fwd, _ = _sh_kernels(bf16)
            launch(
                fwd,
                d.shape[0] * (N_COEFFS // BF16_GROUP if bf16 else 1),
                d,
                [fast_view(d, wp.vec3), fast_view(storage)],
            )
        ctx.save_for_backward(d)
        return storage if bf16 else storage.t()

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_out):
        (d,) = ctx.saved_tensors
        grad_d = torch.empty_like(d)
        if d.shape[0]:
            g = grad_out.contiguous() if 0 in grad_out.stride() else grad_out  # any strides
            _, bwd = _sh_kernels(grad_out.dtype == torch.bfloat16)
            launch(
                bwd,
                d.shape[0],
                d,
                [fast_view(d, wp.vec3), fast_view(g), fast_view(grad_d, wp.vec3)],
            )
        return grad_d, None


def sh_encode(d: torch.Tensor, out_dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """SH basis of unit directions d: (N, 3) float32 -> (N, 16), differentiable in d.

    float32 (out_dtype's default): the transposed view of (16, N) storage (use
    ``.contiguous()`` before ``.view``). bfloat16, for an MLP that runs in it: row-major
    (N, 16), the float32 basis rounded to nearest even (as `.to(torch.bfloat16)` makes it), and
    the gradient read as bf16, without a cast's pass either way.
    """
    if d.ndim != 2 or d.shape[1] != 3 or d.dtype != torch.float32:
        raise ValueError(f"sh_encode: d must be (N, 3) float32, got {tuple(d.shape)} {d.dtype}")
    if out_dtype not in FEATURE_DTYPES:
        raise ValueError(f"sh_encode: out_dtype must be one of {FEATURE_DTYPES}, got {out_dtype}")
    return _SHEncode.apply(d.contiguous(), out_dtype)
