"""Which windows and which pixels a training step sees (DESIGN §3, supplement G).

WindowSampler: windows (t0, t1] on the stream's pose grid t_j = t_start + j·(t_end − t_start)/n
(j = 0..n): a window ends at a grid time t_j (j uniform in 1..n, so every view is used) and
spans w ~ U{win_min..win_max} views, t0 = t_{j−w}. On a loop t0 may precede t_start: the event
index wraps it to the stream's end and its pose is that of grid index (j − w) mod n; without a
loop t0 is clamped to t_start. w is re-drawn every step ("step") or drawn once per end view
when the sampler is built ("load", as the reference does).

RaySampler: for each window, (1 − neg_ratio) of its pixels are the pixels of random events
inside the window (drawn from the time-sorted stream, so busy pixels are drawn more often),
the rest uniform over the sensor (negative samples: mostly E = 0, keeping static regions and
background stable). A window without events falls back to uniform pixels. Rays are made on
the training device from a per-pixel direction table and the grid's camera-to-world table,
both computed once. Targets E come from the Warp kernel `fastenerf.kernels.events.window_sum`
when it imports and agrees with the numpy `EventIndex.query`, otherwise from the latter.
Batches are drawn `prefetch` steps at a time: building one costs a few dozen small host-side
ops whatever its size, which on a GPU cost more than the whole step's device work (see
benchmarks/RESULTS.md, the step profile), so a block of k batches costs about what one did.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import torch

from .data.events import EventIndex
from .data.rig import Rig
from .errors import InputError
from .render import camera_directions, generate_rays


class WindowSampler:
    """Random windows on the pose grid; all randomness from one seeded numpy Generator.

    n_views: grid intervals n (n + 1 grid times); t_start, t_end: µs; win_min, win_max: views.
    """

    def __init__(
        self,
        n_views: int,
        t_start: int,
        t_end: int,
        win_min: int,
        win_max: int,
        redraw: str = "step",
        loop: bool = True,
        seed: int = 0,
    ):
        if n_views < 1 or t_end <= t_start:
            raise InputError(
                f"window grid: need n_views >= 1 and t_end > t_start "
                f"(got {n_views}, {t_start}..{t_end})"
            )
        if not 1 <= win_min <= win_max:
            raise InputError(
                f"window lengths: need 1 <= win_min <= win_max (got {win_min}, {win_max})"
            )
        if redraw not in ("step", "load"):
            raise InputError(f"win_redraw must be 'step' or 'load', got {redraw!r}")
        self.n_views, self.t_start, self.t_end = int(n_views), int(t_start), int(t_end)
        # A window never spans more than the whole stream (a loop would count events twice).
        self.win_min, self.win_max = int(min(win_min, n_views)), int(min(win_max, n_views))
        self.redraw, self.loop = redraw, bool(loop)
        self.rng = np.random.default_rng(seed)
        self.lengths = None
        if redraw == "load":
            self.lengths = self.rng.integers(self.win_min, self.win_max + 1, size=n_views + 1)

    def grid_times(self, j: np.ndarray) -> np.ndarray:
        """µs (int64) of grid indices j (any integers; negative ones lie before t_start)."""
        j = np.asarray(j, dtype=np.int64)
        return self.t_start + (j * (self.t_end - self.t_start)) // self.n_views

    def pose_index(self, j: np.ndarray) -> np.ndarray:
        """Row of the (n + 1)-pose table for grid indices j: wrapped on loops, else clamped."""
        j = np.asarray(j, dtype=np.int64)
        return np.mod(j, self.n_views) if self.loop else np.clip(j, 0, self.n_views)

    def sample(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """n windows as grid indices (j0, j1), (n,) int64 each, j0 < j1."""
        j1 = self.rng.integers(1, self.n_views + 1, size=n)
        if self.lengths is not None:
            w = self.lengths[j1]
        else:
            w = self.rng.integers(self.win_min, self.win_max + 1, size=n)
        j0 = j1 - w
        if not self.loop:
            j0 = np.maximum(j0, 0)
        return j0.astype(np.int64), j1.astype(np.int64)

    def set_win_max(self, win_max: int) -> None:
        """Draw windows up to `win_max` views from now on (capped at the stream, as at
        construction); lengths drawn once at load are drawn again."""
        if win_max < self.win_min:
            raise InputError(f"window lengths: need win_max >= win_min ({self.win_min})")
        self.win_max = int(min(win_max, self.n_views))
        if self.lengths is not None:
            self.lengths = self.rng.integers(self.win_min, self.win_max + 1, self.n_views + 1)

    def state_dict(self) -> dict:
        return {
            "rng": self.rng.bit_generator.state,
            "lengths": self.lengths,
            "win_max": self.win_max,
        }

    def load_state_dict(self, state: dict) -> None:
        self.rng.bit_generator.state = state["rng"]
        self.lengths = state["lengths"]
        self.win_max = int(state.get("win_max", self.win_max))  # set_win_max may have moved it


def to_device(a, device: torch.device) -> torch.Tensor:
    """A host array on `device` without waiting for the device: a copy from pageable memory is
    ordered after every queued kernel and holds the host until they have run (the device-paced
    and graphed steps keep steps queued while the next batch is drawn); one from pinned memory
    does not. a: numpy array or CPU tensor; on a CPU it is shared, not copied."""
    t = torch.as_tensor(a)
    if torch.device(device).type != "cuda":
        return t
    return t.pin_memory().to(device, non_blocking=True)


@dataclass
class RayBatch:
    """One step's rays: B pixels, each rendered at t0 (rows :B) and t1 (rows B:).

    rays_o, rays_d: (2B, 3) world units / unit; pix: (B,) flat pixel ids; channel: (B,) Bayer
    channel or None (mono); target: (B,) E(u; t0, t1] in log units; positive: (B,) bool,
    True for event pixels; n_windows: windows in the batch.
    Only when the sampler is asked for them (self-calibration, issue #20): dirs (B, 3)
    camera-frame directions of the pixels; pose_idx (2B,) int64 grid row of each ray's pose
    (rays_o[i] is row pose_idx[i]'s centre); parts (B, 2) the target's polarity parts [a, b]
    with E = a·C_pos + b·C_neg (`threshold.py`).
    positive_share: () float32 mean of `positive`, made for the sampler's whole block at once
    (None: not made; the reader takes the mean).
    """

    rays_o: torch.Tensor
    rays_d: torch.Tensor
    pix: torch.Tensor
    channel: torch.Tensor | None
    target: torch.Tensor
    positive: torch.Tensor
    n_windows: int
    dirs: torch.Tensor | None = None
    pose_idx: torch.Tensor | None = None
    parts: torch.Tensor | None = None
    positive_share: torch.Tensor | None = None


def _load_window_sum():
    try:
        from .kernels.events import window_sum  # type: ignore[import-not-found]
    except Exception:  # noqa: BLE001 - any import problem means: use numpy
        return None
    return window_sum


class RaySampler:
    """Pixels, rays and event targets for a batch of windows (see module docstring).

    index: the scene's EventIndex; rig: its Rig; windows: the WindowSampler; device: where rays
    are made and rendered; use_kernel: None tries the Warp kernel, False forces numpy;
    with_poses / with_parts: batches also carry dirs + pose_idx / parts (see RayBatch).
    """

    def __init__(
        self,
        index: EventIndex,
        rig: Rig,
        windows: WindowSampler,
        *,
        rays_per_step: int,
        windows_per_step: int,
        neg_ratio: float,
        device: str | torch.device = "cpu",
        seed: int = 0,
        use_kernel: bool | None = None,
        prefetch: int = 1,
        with_poses: bool = False,
        with_parts: bool = False,
    ):
        if prefetch < 1:
            raise InputError(f"sampler prefetch must be >= 1 (got {prefetch})")
        self.index, self.rig, self.windows = index, rig, windows
        self.prefetch = int(prefetch)
        self.with_poses, self.with_parts = bool(with_poses), bool(with_parts)
        self._block: list[RayBatch] = []  # drawn batches not handed out yet
        self._block_state: dict | None = None  # RNG states the current block was drawn from
        self.device = torch.device(device)
        self.n_windows, self.neg_ratio = int(windows_per_step), float(neg_ratio)
        self._resize(max(1, int(rays_per_step) // self.n_windows))
        self._next_per_window: int | None = None  # set_pixels: from the next block on
        self.n_pix = rig.intrinsics.width * rig.intrinsics.height
        self.dirs = camera_directions(rig.intrinsics, self.device)
        grid_t = windows.grid_times(np.arange(windows.n_views + 1))
        self.grid_c2w = torch.as_tensor(rig.pose(grid_t), dtype=torch.float32, device=self.device)
        self.times_sorted = torch.as_tensor(index.times_sorted, device=self.device)
        self.pixels_by_time = torch.as_tensor(index.pixels_by_time, device=self.device)
        self.gen = torch.Generator(device=self.device)
        self.gen.manual_seed(int(seed) + 1)
        self.mono = rig.bayer is None
        self._kernel = None
        if use_kernel is not False:
            self._kernel = self._check_kernel(_load_window_sum())
        self._kernel_arrays = index.to_torch(self.device) if self._kernel else None

    def _resize(self, per_window: int) -> None:
        self.per_window = int(per_window)
        self.n_neg = min(self.per_window, int(round(self.neg_ratio * self.per_window)))

    @property
    def pixels(self) -> int:
        """Pixels per step of the next block drawn (each rendered at t0 and at t1)."""
        return self.n_windows * (self._next_per_window or self.per_window)

    def set_pixels(self, n: int) -> None:
        """Draw about `n` pixels per step (split evenly over the windows) from the next block
        on; the block being handed out keeps its size."""
        self._next_per_window = max(1, int(n) // self.n_windows)

    def block_done(self) -> bool:
        """Whether the next `sample` draws a new block (where `set_pixels` takes effect)."""
        return not self._block

    @property
    def target_backend(self) -> str:
        return "warp" if self._kernel is not None else "numpy"

    # -- targets -----------------------------------------------------------------------------

    def _check_kernel(self, kernel):
        """Use the Warp kernel only if it reproduces the numpy query on a few windows."""
        if kernel is None:
            return None
        rng = np.random.default_rng(0)
        pix = rng.integers(0, self.n_pix, 64)
        if len(self.index.pixels_by_time):
            pix[:32] = rng.choice(self.index.pixels_by_time, 32)
        ws = self.windows
        j1 = rng.integers(1, ws.n_views + 1, 64)
        j0 = j1 - rng.integers(ws.win_min, ws.win_max + 1, 64)
        if not ws.loop:
            j0 = np.maximum(j0, 0)
        t0, t1 = ws.grid_times(j0), ws.grid_times(j1)
        want = self.index.query(pix, t0, t1)
        try:
            arrays = self.index.to_torch(self.device)
            got = self._kernel_query(
                kernel,
                arrays,
                to_device(pix, self.device),
                to_device(t0, self.device),
                to_device(t1, self.device),
            )
            ok = np.allclose(got.cpu().numpy(), want, atol=1e-5)
        except Exception as e:  # noqa: BLE001 - a broken kernel must not stop training
            warnings.warn(
                f"Warp window_sum unusable ({e}); using the numpy event index", stacklevel=2
            )
            return None
        if not ok:
            warnings.warn(
                "Warp window_sum disagrees with EventIndex.query; using numpy", stacklevel=2
            )
            return None
        return kernel

    def _kernel_query(
        self, kernel, arrays, pix, t0, t1, any_wraps=None, thresholds=None
    ) -> torch.Tensor:
        """any_wraps: whether some window wraps, when the caller knows it on the host (saves
        reading it back from the device: a sync every step); thresholds: (C_pos, C_neg)
        instead of the index's."""
        idx = self.index
        c_pos, c_neg = thresholds or (idx.pos_threshold, idx.neg_threshold)
        wraps = (t0 < idx.t_start) & idx.loop
        t0a = torch.where(wraps, torch.full_like(t0, idx.t_start - 1), t0)
        e = kernel(
            arrays["offsets"],
            arrays["times"],
            arrays["cum_pos"],
            pix,
            t0a,
            t1,
            c_pos,
            c_neg,
            idx.polarity_offset,
        )
        if any_wraps if any_wraps is not None else bool(wraps.any()):
            t0b = torch.where(wraps, t0 + idx.period, torch.full_like(t0, idx.t_end))
            e = e + kernel(
                arrays["offsets"],
                arrays["times"],
                arrays["cum_pos"],
                pix,
                t0b,
                torch.full_like(t1, idx.t_end),
                c_pos,
                c_neg,
                idx.polarity_offset,
            )
        return e.float()

    def targets(self, pix: torch.Tensor, t0: np.ndarray, t1: np.ndarray) -> torch.Tensor:
        """E(u; t0, t1] (B,) float32 on the device; pix (B,), t0/t1 (B,) int64 µs."""
        if self._kernel is not None:
            return self._kernel_query(
                self._kernel,
                self._kernel_arrays,
                pix,
                to_device(t0, self.device),
                to_device(t1, self.device),
                any_wraps=bool(self.index.loop and np.any(np.asarray(t0) < self.index.t_start)),
            )
        e = self.index.query(pix.cpu().numpy(), t0, t1)
        return to_device(e, self.device)

    def parts(self, pix: torch.Tensor, t0: np.ndarray, t1: np.ndarray) -> torch.Tensor:
        """The target's polarity parts [a, b] (B, 2) float32: E = a·C_pos + b·C_neg, so
        a = (1 + offset)·n_pos and b = (offset − 1)·n_neg of each window (t0, t1] (B,)."""
        if self._kernel is not None:
            args = (
                pix,
                to_device(t0, self.device),
                to_device(t1, self.device),
                bool(self.index.loop and np.any(np.asarray(t0) < self.index.t_start)),
            )
            k, arrays = self._kernel, self._kernel_arrays
            a = self._kernel_query(k, arrays, *args, thresholds=(1.0, 0.0))
            b = self._kernel_query(k, arrays, *args, thresholds=(0.0, 1.0))
            return torch.stack([a, b], 1)
        idx = self.index
        t0a, t1a, t0b, t1b = idx.split_wrapped(t0, t1)
        p = pix.cpu().numpy()
        n, n_pos = idx.counts(p, t0a, t1a)
        if idx.loop:
            n2, n_pos2 = idx.counts(p, t0b, t1b)
            n, n_pos = n + n2, n_pos + n_pos2
        off = idx.polarity_offset
        ab = np.stack([(1.0 + off) * n_pos, (off - 1.0) * (n - n_pos)], 1).astype(np.float32)
        return to_device(ab, self.device)

    # -- pixels ------------------------------------------------------------------------------

    def event_pixels(self, t0: np.ndarray, t1: np.ndarray, n: int) -> torch.Tensor:
        """(W, n) pixels of random events in each window (t0, t1] (W,); -1 where none."""
        t0a, t1a, t0b, t1b = self.index.split_wrapped(t0, t1)
        q = to_device(np.stack([t0a, t1a, t0b, t1b], 1), self.device)
        # Both parts as (t0, t1]: index ranges [i0, i1) of the time-sorted stream.
        i = torch.searchsorted(self.times_sorted, q.contiguous(), right=True)
        ca = (i[:, 1] - i[:, 0]).clamp_min(0)
        cb = (i[:, 3] - i[:, 2]).clamp_min(0)
        total = ca + cb
        u = torch.rand(len(t0), n, generator=self.gen, device=self.device, dtype=torch.float64)
        r = (u * total[:, None]).long().clamp_max((total - 1).clamp_min(0)[:, None])
        idx = torch.where(r < ca[:, None], i[:, :1] + r, i[:, 2:3] + r - ca[:, None])
        if len(self.pixels_by_time) == 0:
            return torch.full_like(idx, -1)
        pix = self.pixels_by_time[idx.clamp(0, len(self.pixels_by_time) - 1)]
        return torch.where(total[:, None] > 0, pix, torch.full_like(pix, -1))

    def sample(self) -> RayBatch:
        """One step's windows, pixels, rays and targets (from the current prefetched block)."""
        if not self._block:
            if self._next_per_window is not None:
                self._resize(self._next_per_window)
                self._next_per_window = None
            self._block_state = self._rng_state()
            self._block = self._draw_block(self.prefetch)
        return self._block.pop(0)

    def _draw_block(self, k: int) -> list[RayBatch]:
        """k steps' batches drawn together: every op below runs once for all k·W windows."""
        w, n = self.n_windows * k, self.per_window
        j0, j1 = self.windows.sample(w)
        t0, t1 = self.windows.grid_times(j0), self.windows.grid_times(j1)
        n_pos = n - self.n_neg
        uniform = torch.randint(0, self.n_pix, (w, n), generator=self.gen, device=self.device)
        if n_pos > 0:
            ev = self.event_pixels(t0, t1, n_pos)
            positive = torch.cat(
                [ev >= 0, torch.zeros(w, self.n_neg, dtype=torch.bool, device=self.device)], 1
            )
            pix = torch.where(positive, torch.cat([ev, uniform[:, n_pos:]], 1), uniform)
        else:
            positive = torch.zeros(w, n, dtype=torch.bool, device=self.device)
            pix = uniform
        win = torch.arange(w, device=self.device).repeat_interleave(n)
        pix = pix.reshape(-1)
        p0 = to_device(self.windows.pose_index(j0), self.device)
        p1 = to_device(self.windows.pose_index(j1), self.device)
        dirs = self.dirs[pix]
        o0, d0 = generate_rays(dirs, self.grid_c2w[p0][win])
        o1, d1 = generate_rays(dirs, self.grid_c2w[p1][win])
        win_np = np.repeat(np.arange(w), n)
        target = self.targets(pix, t0[win_np], t1[win_np])
        channel = None if self.mono else self.rig.channel(pix)
        # step i's rays are its B pixels at t0, then the same pixels at t1: (k, 2, B, 3)
        b = self.n_windows * n
        rays_o = torch.stack([o0.reshape(k, b, 3), o1.reshape(k, b, 3)], 1)
        rays_d = torch.stack([d0.reshape(k, b, 3), d1.reshape(k, b, 3)], 1)
        # every step's share of event pixels (a stat): four ops for the block, not two a step
        extras = [{"positive_share": s} for s in positive.reshape(k, b).float().mean(1).unbind(0)]
        if self.with_poses:
            rows = torch.stack([p0[win].reshape(k, b), p1[win].reshape(k, b)], 1)
            pose_idx = rows.reshape(k, 2 * b).unbind(0)
            for e, d, r in zip(extras, dirs.reshape(k, b, 3).unbind(0), pose_idx, strict=True):
                e.update(dirs=d, pose_idx=r)
        if self.with_parts:
            ab = self.parts(pix, t0[win_np], t1[win_np]).reshape(k, b, 2)
            for e, p in zip(extras, ab, strict=True):
                e["parts"] = p
        # each step's views of the block's tensors: one unbind for all k, not k indexings
        views = zip(
            rays_o.reshape(k, 2 * b, 3).unbind(0),
            rays_d.reshape(k, 2 * b, 3).unbind(0),
            pix.reshape(k, b).unbind(0),
            [None] * k if channel is None else channel.reshape(k, b).unbind(0),
            target.reshape(k, b).unbind(0),
            positive.reshape(k, b).unbind(0),
            strict=True,
        )
        return [RayBatch(*v, self.n_windows, **e) for v, e in zip(views, extras, strict=True)]

    def _rng_state(self) -> dict:
        return {"windows": self.windows.state_dict(), "gen": self.gen.get_state()}

    def state_dict(self) -> dict:
        """The RNG states the current block was drawn from and how many of it were used, so a
        resume redraws the same block and goes on where it stopped."""
        # windows_now: the lengths as they are now (`WindowSampler.set_win_max` may have moved
        # them since the block was drawn), restored once the block is drawn again
        now = {"windows_now": self.windows.state_dict(), "per_window": self.per_window}
        now["per_window_next"] = self._next_per_window
        if not self._block:
            return {**self._rng_state(), "position": 0, **now}
        return {**self._block_state, "position": self.prefetch - len(self._block), **now}

    def load_state_dict(self, state: dict) -> None:
        self.windows.load_state_dict(state["windows"])
        self.gen.set_state(state["gen"].cpu() if hasattr(state["gen"], "cpu") else state["gen"])
        if state.get("per_window") is not None:  # the block's size (`set_pixels`)
            self._resize(int(state["per_window"]))
        self._next_per_window = state.get("per_window_next")
        self._block = []
        position = int(state.get("position", 0))
        if position > 0:
            self._block_state = self._rng_state()
            self._block = self._draw_block(self.prefetch)[position:]
        if "windows_now" in state:
            self.windows.load_state_dict(state["windows_now"])
