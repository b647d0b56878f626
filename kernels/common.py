"""Shared Warp plumbing: initialisation, device mapping, zero-copy tensor views, and THE way a
kernel is launched (`launch`, or `launch_tiled` for blocks of cooperating threads): every op in
this package goes through them."""

from __future__ import annotations

import functools
from collections import OrderedDict

import torch
import warp as wp


@functools.cache
def init() -> None:
    """Initialise Warp once, quietly."""
    wp.config.log_level = wp.LOG_WARNING  # no banner, no per-module load lines
    wp.init()


def device_of(t: torch.Tensor) -> str:
    """The Warp device string for a torch tensor ("cpu" or "cuda:N")."""
    init()
    if t.device.type == "cuda":
        return f"cuda:{t.device.index or 0}"
    return "cpu"


def stream_of(t: torch.Tensor):
    """Warp stream matching torch's current CUDA stream (None on CPU)."""
    if t.device.type != "cuda":
        return None
    return wp.stream_from_torch(torch.cuda.current_stream(t.device))


# ---------------------------------------------------------------------------------------------
# Low-overhead launching (the hot path calls these once per op; wp.from_torch, wp.launch and
# wp.stream_from_torch cost tens of microseconds of Python each).

_VIEWS: OrderedDict = OrderedDict()
_STREAMS: dict = {}


def fast_view(t: torch.Tensor, dtype=None) -> wp.array:
    """Warp view of tensor t (any strides; dtype a scalar or vector type over its last dim).

    Views are plain (pointer, shape, strides) descriptors, so one cached per key is safe to
    reuse for any tensor with the same storage address and geometry.
    """
    key = (t.data_ptr(), t.shape, t.stride(), t.dtype, dtype, t.device)
    a = _VIEWS.get(key)
    if a is None:
        init()
        a = wp.from_torch(t, dtype=dtype, requires_grad=False)
        a = wp.array(
            ptr=a.ptr, dtype=a.dtype, shape=a.shape, strides=a.strides, device=a.device, copy=False
        )  # drops from_torch's reference to t
        _VIEWS[key] = a
        if len(_VIEWS) > 256:
            _VIEWS.popitem(last=False)
    return a


def as_float32(t: torch.Tensor, device: torch.device | None = None) -> torch.Tensor:
    """t as a contiguous float32 tensor on `device` (None: t's): t itself where it is one.

    For a kernel's inputs: a `.float()`, `.to()` or `.detach()` that changes nothing still
    dispatches an op (a few µs of host time a call, every step); a Warp view needs no detaching.
    """
    if device is not None and t.device != torch.device(device):
        t = t.to(device)
    if t.dtype == torch.float32 and t.is_contiguous():
        return t
    return t.float().contiguous()


FEATURE_DTYPES = (torch.float32, torch.bfloat16)
"""What an encoding (hash grid, SH) can write its features in: float32, or bf16 for an MLP
that runs in it."""


def features_dtype(bf16: bool):
    """The Warp scalar type an encoding's features and their gradient are stored in."""
    return wp.bfloat16 if bf16 else wp.float32


def fast_stream(t: torch.Tensor):
    """Warp stream for torch's current stream on t's device (None on CPU), cached."""
    if t.device.type != "cuda":
        return None
    ts = torch.cuda.current_stream(t.device)
    key = (t.device.index, ts.cuda_stream)
    s = _STREAMS.get(key)
    if s is None:
        s = _STREAMS[key] = stream_of(t)
    return s


@functools.cache
def launcher(kernel) -> Launcher:
    """The process-wide Launcher of a kernel."""
    return Launcher(kernel)


class Launcher:
    """Replays one kernel through a recorded `wp.Launch` (about half of wp.launch's cost)."""

    def __init__(self, kernel):
        self.kernel = kernel
        self._cmds = {}

    def __call__(self, dim: int, t: torch.Tensor, args: list):
        """Launch over dim threads on t's device and current stream with args (Warp values)."""
        device = device_of(t)
        cmd = self._cmds.get(device)
        if cmd is None:
            cmd = wp.launch(self.kernel, dim=dim, inputs=args, device=device, record_cmd=True)
            self._cmds[device] = cmd
        else:
            for i, a in enumerate(args):
                cmd.set_param_at_index(i, a)
            cmd.set_dim(dim)
        cmd.launch(fast_stream(t))


def launch(kernel, dim: int, like: torch.Tensor, args: list) -> None:
    """Launch `kernel` over `dim` threads on `like`'s device and current stream.

    args: the kernel's parameters in order (inputs, then outputs); a torch tensor becomes a
    cached zero-copy view with its scalar dtype, so pass `fast_view(t, wp.vec3)` where the
    kernel wants a vector type. dim 0 launches nothing.
    """
    if dim <= 0:
        return
    launcher(kernel)(dim, like, [fast_view(a) if isinstance(a, torch.Tensor) else a for a in args])


class TiledLauncher:
    """As `Launcher`, for a kernel run by blocks of `block_dim` cooperating threads
    (`wp.launch_tiled`: launched over (blocks, block_dim), `wp.tid()` gives (block, lane)).

    On the CPU the blocks run as cooperative fibers of `block_dim` lanes, the GPU's schedule,
    so a CPU test exercises the same lanes and tile ops. Warp makes that opt-in
    (`wp.config.enable_cpu_blocks`, otherwise a CPU block has one lane); it is switched on only
    while this launch is recorded, which fixes the block width of the recorded command and
    leaves every other kernel's CPU launches as they were. cpu_blocks=False records one lane
    per CPU block instead (for kernels that loop over their tiles themselves, as the MLP's).
    """

    def __init__(self, kernel, block_dim: int, cpu_blocks: bool = True):
        self.kernel, self.block_dim, self._cmds = kernel, block_dim, {}
        self.cpu_blocks = cpu_blocks

    def _record(self, blocks: int, device: str, args: list):
        cpu_blocks = wp.config.enable_cpu_blocks
        wp.config.enable_cpu_blocks = self.cpu_blocks
        try:
            return wp.launch_tiled(
                self.kernel,
                dim=(blocks,),
                inputs=args,
                device=device,
                block_dim=self.block_dim,
                record_cmd=True,
            )
        finally:
            wp.config.enable_cpu_blocks = cpu_blocks

    def __call__(self, blocks: int, t: torch.Tensor, args: list) -> None:
        """Launch `blocks` blocks on t's device and current stream with args (Warp values)."""
        device = device_of(t)
        cmd = self._cmds.get(device)
        if cmd is None:
            cmd = self._cmds[device] = self._record(blocks, device, args)
        else:
            for i, a in enumerate(args):
                cmd.set_param_at_index(i, a)
            cmd.set_dim((blocks, cmd.block_dim))
        cmd.launch(fast_stream(t))


@functools.cache
def tiled_launcher(kernel, block_dim: int, cpu_blocks: bool = True) -> TiledLauncher:
    """The process-wide TiledLauncher of a kernel at one block width."""
    return TiledLauncher(kernel, block_dim, cpu_blocks)


def launch_tiled(kernel, blocks: int, block_dim: int, like: torch.Tensor, args: list) -> None:
    """Launch `kernel` over `blocks` blocks of `block_dim` threads on `like`'s device and
    current stream (no host sync, no allocation once recorded; args as for `launch`).
    blocks 0 launches nothing."""
    if blocks <= 0:
        return
    tiled_launcher(kernel, block_dim)(
        blocks, like, [fast_view(a) if isinstance(a, torch.Tensor) else a for a in args]
    )
