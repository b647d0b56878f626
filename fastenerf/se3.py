"""Small rotations in torch, differentiable everywhere (pose refinement, issue #20).

`so3_exp` is Rodrigues' formula with Taylor series near zero: the textbook form divides by
|ω| and has a NaN gradient at ω = 0, which is exactly where every pose correction starts.
`rotation_angle` measures a rotation's angle from its matrix with atan2, which keeps full
precision at small angles where arccos((tr − 1) / 2) loses half the digits.
"""

from __future__ import annotations

import functools
import math

import torch

# Below this |ω|² (rad²) the Taylor series are exact to float64 rounding (next terms ~θ⁶).
_SMALL = 1e-6


def hat(w: torch.Tensor) -> torch.Tensor:
    """Skew matrices [ω]× (..., 3, 3) of vectors ω (..., 3): [ω]× v = ω × v."""
    x, y, z = w.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], -1).reshape(*w.shape[:-1], 3, 3)


def so3_exp(w: torch.Tensor) -> torch.Tensor:
    """Rotation matrices (..., 3, 3) of axis-angle vectors ω (..., 3) radians (Rodrigues).

    R = I + A [ω]× + B [ω]×², A = sin θ / θ, B = (1 − cos θ) / θ², θ = |ω|; values and
    gradients finite at ω = 0 (A, B from their series there).
    """
    th2 = (w * w).sum(-1, keepdim=True)[..., None]  # (..., 1, 1)
    small = th2 < _SMALL
    th2_safe = torch.where(small, torch.ones_like(th2), th2)
    th = th2_safe.sqrt()
    a = torch.where(small, 1 - th2 / 6 + th2 * th2 / 120, torch.sin(th) / th)
    b = torch.where(small, 0.5 - th2 / 24 + th2 * th2 / 720, (1 - torch.cos(th)) / th2_safe)
    k = hat(w)
    eye = torch.eye(3, dtype=w.dtype, device=w.device).expand_as(k)
    return eye + a * k + b * (k @ k)


def rotation_angle(R: torch.Tensor) -> torch.Tensor:
    """Angle of rotation matrices R (..., 3, 3), radians in [0, π], (...)."""
    s = 0.5 * torch.stack(
        [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]],
        -1,
    ).norm(dim=-1)
    c = 0.5 * (R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2] - 1)
    return torch.atan2(s, c)


def so3_log(R: torch.Tensor) -> torch.Tensor:
    """Rotation vectors w (..., 3), radians, of rotation matrices R (..., 3, 3) with angles
    below π: so3_exp(so3_log(R)) = R. The axis comes from R's skew part, whose size is
    sin(angle), so near π (sin → 0) it is ill-conditioned."""
    v = 0.5 * torch.stack(
        [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]],
        -1,
    )
    s = v.norm(dim=-1, keepdim=True)
    angle = rotation_angle(R).unsqueeze(-1)
    # angle / sin(angle) -> 1 at 0: its series below 1e-4 rad, where s carries no digits
    small = angle < 1e-4
    scale = torch.where(small, 1.0 + angle * angle / 6.0, angle / torch.where(small, 1.0, s))
    return v * scale


def relative_angle_deg(R_a: torch.Tensor, R_b: torch.Tensor) -> torch.Tensor:
    """Geodesic angle between rotations R_a, R_b (..., 3, 3), degrees (...)."""
    return rotation_angle(R_a.transpose(-1, -2) @ R_b) * (180.0 / math.pi)


def mean_world_rotation(R_a: torch.Tensor, R_b: torch.Tensor, weights: torch.Tensor | None = None):
    """The rotation W (3, 3) that best turns R_b (N, 3, 3) into R_a in the world frame,
    R_a ≈ W · R_b: argmin Σ w_i ‖W R_b,i − R_a,i‖², i.e. argmax tr(Wᵀ M) over rotations with
    M = Σ w_i R_a,i R_b,iᵀ; weights: optional (N,) >= 0, not all 0. Same dtype as R_a.

    Why: it is the part of a refinement's pose error that every camera shares about its
    own centre, the part a mean gauge holds (`PoseRefiner.stats` reports its angle).
    Solved as Horn's quaternion form: tr(R(q)ᵀ M) = qᵀ K q, W from K's top eigenvector, found
    by repeated squaring of K shifted positive. No SVD or eigen-solver: on CUDA those wait
    for the device (their error checks), and a device-paced step reads these stats without
    waiting (`PoseRefiner.stats(on_device=True)`); the answer is a rotation even where M's
    determinant is negative.
    """
    w = torch.ones(R_a.shape[0], dtype=R_a.dtype, device=R_a.device) if weights is None else weights
    M = torch.einsum("n,nij,nkj->ik", w.to(R_a.dtype), R_a, R_b.to(R_a.dtype))
    K = torch.einsum("ij,ijab->ab", M, _quat_forms(R_a.dtype, R_a.device))
    # |eigenvalues of K| <= Σ singular values of M <= √3 ‖M‖_F: the shift makes K PSD, and
    # 2^40 powers leave only the top eigenvector for any gap above a ratio of 1 + 1e-10
    P = K + torch.eye(4, dtype=K.dtype, device=K.device) * (3**0.5 * M.norm() + 1e-300)
    for _ in range(40):
        P = P / P.abs().amax().clamp_min(1e-300)
        P = P @ P
    col = P.norm(dim=0).argmax()
    q = P.index_select(1, col[None])[:, 0]
    return quat_to_matrix(q / q.norm())


def quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrix (..., 3, 3) of unit quaternions q (..., 4) = (w, x, y, z)."""
    w, x, y, z = q.unbind(-1)
    rows = [
        [w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z],
    ]
    return torch.stack([torch.stack(r, -1) for r in rows], -2)


@functools.lru_cache(maxsize=8)
def _quat_forms(dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """(3, 3, 4, 4) symmetric B_ij with qᵀ B_ij q = R(q)_ij (`quat_to_matrix`'s entries)."""
    B = torch.zeros(3, 3, 4, 4, dtype=torch.float64)
    eye = torch.eye(4, dtype=torch.float64)
    for a in range(4):
        for b in range(4):
            e = (eye[a] + eye[b]) if a != b else eye[a]
            # polarisation: the bilinear form's (a, b) entry from the quadratic form
            qa, qb, qab = quat_to_matrix(eye[a]), quat_to_matrix(eye[b]), quat_to_matrix(e)
            B[:, :, a, b] = qab if a == b else (qab - qa - qb) / 2
    return B.to(dtype=dtype, device=device)
