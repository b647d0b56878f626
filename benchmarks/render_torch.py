"""Plain-PyTorch versions of the rendering kernels, the baselines `benchmarks.kernels_render`
times Warp against (what a user of this field would write without custom kernels):

- `torch_composite`: packed samples scattered into a dense (rays x max samples) array,
  exclusive transmittance from a cumulative sum of optical depths, early-stop mask, segment
  sums with index_add; autograd gives the backward;
- `torch_march`: dense uniform steps over every ray's box interval, an occupancy lookup of each
  midpoint in the dense bool grid, compaction with boolean masks (the same intervals as the
  Warp marcher with cone_angle = 0 and no jitter, so sample counts must agree).
"""

from __future__ import annotations

import torch

from fastenerf.kernels.composite import T_MIN


def torch_composite(sigmas, rgbs, t_starts, t_ends, packed_info, background=None, n_max=None):
    """Compositing over packed samples with a dense cumulative sum and segment sums (autograd).
    `n_max`: the largest sample count of a ray, if known (else read from the device: a host
    sync, which a CUDA graph cannot capture)."""
    R = packed_info.shape[0]
    counts = packed_info[:, 1].long()
    S = sigmas.shape[0]
    ray = torch.repeat_interleave(torch.arange(R, device=sigmas.device), counts, output_size=S)
    pos = torch.arange(S, device=sigmas.device) - packed_info[:, 0].long()[ray]
    N = n_max if n_max is not None else (int(counts.max()) if R else 0)
    tau = sigmas * (t_ends - t_starts).clamp_min(0)
    # exclusive sum of the optical depths, as nerfacc's plain-PyTorch path (a cumprod's backward
    # reads its input on the host, so no CUDA graph could capture it)
    dense = torch.zeros(R, N + 1, dtype=sigmas.dtype, device=sigmas.device)
    dense = dense.index_put((ray, pos + 1), tau)
    T = torch.exp(-torch.cumsum(dense, 1)[ray, pos])
    w = torch.where(T >= T_MIN, T * -torch.expm1(-tau), torch.zeros_like(T))
    z = torch.zeros(R, dtype=sigmas.dtype, device=sigmas.device)
    opacity = z.index_add(0, ray, w)
    depth = z.index_add(0, ray, w * 0.5 * (t_starts + t_ends))
    rgb = torch.zeros(R, 3, dtype=sigmas.dtype, device=sigmas.device)
    rgb = rgb.index_add(0, ray, w[:, None] * rgbs)
    if background is not None:
        rgb = rgb + (1 - opacity)[:, None] * background
    return {"rgb": rgb, "depth": depth, "opacity": opacity, "weights": w}


def torch_march(rays_o, rays_d, aabb, binary, dt, max_samples, chunk_elems=2**26):
    """Dense constant steps + occupancy lookup + boolean-mask compaction (one cascade)."""
    dev, dtype = rays_o.device, rays_o.dtype
    lo = torch.tensor(aabb[:3], dtype=dtype, device=dev)
    hi = torch.tensor(aabb[3:], dtype=dtype, device=dev)
    res = binary.shape[-1]
    safe = torch.where(rays_d.abs() < 1e-12, torch.full_like(rays_d, 1e-12), rays_d)
    ta, tb = (lo - rays_o) / safe, (hi - rays_o) / safe
    t0 = torch.minimum(ta, tb).amax(1).clamp_min(0)
    t1 = torch.maximum(ta, tb).amin(1)
    hit = t1 > t0
    n_steps = int(((t1 - t0)[hit].max() / dt).ceil()) + 1 if hit.any() else 0
    occ = binary.reshape(-1)
    outs = []
    rows = max(1, chunk_elems // max(n_steps, 1))
    for s in range(0, rays_o.shape[0], rows):
        o, d = rays_o[s : s + rows], rays_d[s : s + rows]
        a0, a1 = t0[s : s + rows, None], t1[s : s + rows, None]
        k = torch.arange(n_steps, dtype=dtype, device=dev)
        start = a0 + k * dt
        end = torch.minimum(start + dt, a1)
        mid = 0.5 * (start + end)
        p = o[:, None] + mid[..., None] * d[:, None]
        ijk = ((p - lo) / (hi - lo) * res).floor().long().clamp_(0, res - 1)
        keep = (start < a1) & occ[(ijk[..., 0] * res + ijk[..., 1]) * res + ijk[..., 2]]
        keep &= torch.cumsum(keep, 1) <= max_samples
        r, _ = torch.nonzero(keep, as_tuple=True)
        outs.append((keep.sum(1), start[keep], end[keep], r + s))
    counts = torch.cat([x[0] for x in outs]).int()
    csum = torch.cumsum(counts, 0, dtype=torch.int32)
    packed = torch.stack([csum - counts, counts], 1)
    cat = lambda i: torch.cat([x[i] for x in outs])  # noqa: E731
    return packed, cat(1), cat(2), cat(3).int()


def torch_distortion(w, t_s, t_e, packed):
    """The distortion loss per ray (R,) in plain PyTorch, O(S) by segmented prefix sums (the
    speed baseline and, in float64, the reference):
    L_r = 2 sum_i w_i (m_i W_<i - WM_<i) + 1/3 sum_i w_i^2 delta_i."""
    R = packed.shape[0]
    ray = torch.repeat_interleave(torch.arange(R, device=w.device), packed[:, 1].long())
    m, first = 0.5 * (t_s + t_e), packed[ray, 0].long()

    def before(x):  # sum of x over the samples of the same ray before each one
        c = torch.cumsum(x, 0) - x
        return c - c[first] if x.numel() else c

    per = 2 * w * (m * before(w) - before(w * m)) + w * w * (t_e - t_s) / 3
    return torch.zeros(R, dtype=w.dtype, device=w.device).index_add(0, ray, per)
