"""Real spherical-harmonics direction encoding, degree 4 (16 coefficients), as Warp kernels.

Same basis, order and signs as tiny-cuda-nn / torch-ngp's ``sh_encoder`` with the direction
given in [-1, 1]^3 (a unit vector; torch-ngp's convention, not tcnn's [0, 1] input). No
normalisation happens here: the backward is the plain Jacobian of the polynomials.
"""

import torch
import warp as wp

from .common import fast_view, init, launch

init()

N_COEFFS = 16


@wp.kernel(enable_backward=False)
def _sh_forward(d: wp.array(dtype=wp.vec3), out: wp.array2d(dtype=float)):
    i = wp.tid()
    v = d[i]
    x, y, z = v[0], v[1], v[2]
    xy, xz, yz = x * y, x * z, y * z
    x2, y2, z2 = x * x, y * y, z * z
    out[0, i] = 0.28209479177387814  # 1/(2 sqrt(pi))
    out[1, i] = -0.48860251190291987 * y  # sqrt(3)/(2 sqrt(pi))
    out[2, i] = 0.48860251190291987 * z
    out[3, i] = -0.48860251190291987 * x
    out[4, i] = 1.0925484305920792 * xy  # sqrt(15)/(2 sqrt(pi))
    out[5, i] = -1.0925484305920792 * yz
    out[6, i] = 0.94617469575755997 * z2 - 0.31539156525251999  # sqrt(5)(3z^2-1)/(4 sqrt(pi))
    out[7, i] = -1.0925484305920792 * xz
    out[8, i] = 0.54627421529603959 * (x2 - y2)  # sqrt(15)/(4 sqrt(pi))
    out[9, i] = 0.59004358992664352 * y * (y2 - 3.0 * x2)  # sqrt(70)/(8 sqrt(pi))
    out[10, i] = 2.8906114426405538 * xy * z  # sqrt(105)/(2 sqrt(pi))
    out[11, i] = 0.45704579946446572 * y * (1.0 - 5.0 * z2)  # sqrt(42)/(8 sqrt(pi))
    out[12, i] = 0.3731763325901154 * z * (5.0 * z2 - 3.0)  # sqrt(7)/(4 sqrt(pi))
    out[13, i] = 0.45704579946446572 * x * (1.0 - 5.0 * z2)
    out[14, i] = 1.4453057213202769 * z * (x2 - y2)  # sqrt(105)/(4 sqrt(pi))
    out[15, i] = 0.59004358992664352 * x * (3.0 * y2 - x2)


@wp.kernel(enable_backward=False)
def _sh_backward(
    d: wp.array(dtype=wp.vec3), g: wp.array2d(dtype=float), grad_d: wp.array(dtype=wp.vec3)
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
    g1, g2, g3, g4, g5 = g[i, 1], g[i, 2], g[i, 3], g[i, 4], g[i, 5]
    g6, g7, g8, g9, g10 = g[i, 6], g[i, 7], g[i, 8], g[i, 9], g[i, 10]
    g11, g12, g13, g14, g15 = g[i, 11], g[i, 12], g[i, 13], g[i, 14], g[i, 15]
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


class _SHEncode(torch.autograd.Function):
    @staticmethod
    def forward(ctx, d):
        # Coefficient-major storage: adjacent threads write adjacent words (a (N, 16) row per
        # thread would scatter 4-byte stores 64 bytes apart); returned as its (N, 16) view.
        storage = torch.empty(N_COEFFS, d.shape[0], dtype=torch.float32, device=d.device)
        if d.shape[0]:
            launch(_sh_forward, d.shape[0], d, [fast_view(d, wp.vec3), fast_view(storage)])
        ctx.save_for_backward(d)
        return storage.t()

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_out):
        (d,) = ctx.saved_tensors
        grad_d = torch.empty_like(d)
        if d.shape[0]:
            g = grad_out.contiguous() if 0 in grad_out.stride() else grad_out  # any strides
            launch(
                _sh_backward,
                d.shape[0],
                d,
                [fast_view(d, wp.vec3), fast_view(g), fast_view(grad_d, wp.vec3)],
            )
        return grad_d


def sh_encode(d: torch.Tensor) -> torch.Tensor:
    """SH basis of unit directions d: (N, 3) float32 -> (N, 16) float32, differentiable in d.

    The result is the transposed view of (16, N) storage (use ``.contiguous()`` before ``.view``).
    """
    if d.ndim != 2 or d.shape[1] != 3 or d.dtype != torch.float32:
        raise ValueError(f"sh_encode: d must be (N, 3) float32, got {tuple(d.shape)} {d.dtype}")
    return _SHEncode.apply(d.contiguous())
