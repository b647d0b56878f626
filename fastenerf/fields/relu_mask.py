"""GEMMs whose epilogue writes or applies a ReLU bit mask (cuBLASLt, through ctypes).

torch reaches cuBLASLt's RELU_BIAS epilogue (`torch._addmm_activation`, `fused_relu`) but not
RELU_AUX, which also stores one bit an output (pre-activation > 0), nor DRELU, which
multiplies a GEMM's result by such a mask as it stores it. With both, an MLP's backward
applies each hidden layer's ReLU gradient inside the GEMM that makes that gradient, instead
of a threshold pass that reads the gradient and the activations and writes the gradient
again (three (N, hidden) passes a hidden layer).

The mask is cuBLASLt's layout: torch's row-major (N, C) output is cuBLAS's column-major
(C, N), so sample n's C bits start at bit n · ld (ld = C rounded up to 128), bit c of byte
b is output 8 b + c, least significant first. `pack_mask` / `unpack_mask` write and read that
layout with torch ops: the reference the CPU runs (and tests), and the fallback of a shape
cuBLASLt has no algorithm for.
"""

from __future__ import annotations

import ctypes
import functools
from collections import OrderedDict
from pathlib import Path

import torch

MASK_ALIGN = 128  # bits: what cuBLASLt asks of a ReLU bit mask's leading dimension
WORKSPACE_BYTES = 32 << 20
BIAS_SCRATCH = 4096  # float32s: a DRELU_BGRAD bias gradient of up to this many outputs

# cuBLASLt's enums (cublasLt.h, library_types.h)
_R_32F, _R_16F, _R_16BF = 0, 2, 14
_COMPUTE_32F = 68
_OP_N, _OP_T = 0, 1
_DESC_TRANSA, _DESC_TRANSB, _DESC_EPILOGUE, _DESC_BIAS_POINTER = 3, 4, 7, 8
_DESC_AUX_POINTER, _DESC_AUX_LD = 11, 12
_PREF_MAX_WORKSPACE = 1
_PREF_MIN_ALIGN = (5, 6, 7, 8)  # A, B, C, D bytes
_EPI_RELU_AUX, _EPI_DRELU, _EPI_DRELU_BGRAD = 130, 136, 152
_DTYPES = {torch.bfloat16: _R_16BF, torch.float16: _R_16F}
_POINTER_ALIGN = 16  # bytes: what the plans are asked to work with (TMA's)


def mask_bytes(c: int) -> int:
    """Bytes a sample's mask of c outputs takes."""
    return -(-c // MASK_ALIGN) * MASK_ALIGN // 8


def pack_mask(y: torch.Tensor) -> torch.Tensor:
    """(N, C) activations -> (N, mask_bytes(C)) uint8, bit c set where y[:, c] > 0."""
    n, c = y.shape
    bits = torch.zeros(n, mask_bytes(c) * 8, dtype=torch.uint8, device=y.device)
    bits[:, :c] = y > 0
    weights = (2 ** torch.arange(8, device=y.device)).to(torch.uint8)
    return (bits.view(n, -1, 8) * weights).sum(-1, dtype=torch.uint8)


def unpack_mask(mask: torch.Tensor, c: int) -> torch.Tensor:
    """(N, mask_bytes(c)) uint8 -> (N, c) bool."""
    shifts = torch.arange(8, device=mask.device, dtype=torch.uint8)
    bits = (mask.unsqueeze(-1) >> shifts) & 1
    return bits.reshape(mask.shape[0], -1)[:, :c].bool()


# -- cuBLASLt ------------------------------------------------------------------------------


class _Heuristic(ctypes.Structure):
    _fields_ = [
        ("algo", ctypes.c_uint64 * 8),
        ("workspace_size", ctypes.c_size_t),
        ("state", ctypes.c_int),
        ("waves", ctypes.c_float),
        ("reserved", ctypes.c_int * 4),
    ]


@functools.cache
def _lib():
    """libcublasLt (torch's own, where it has loaded it), or None."""
    names = ["libcublasLt.so.13", "libcublasLt.so.12", "libcublasLt.so"]
    nvidia = Path(torch.__file__).resolve().parent.parent / "nvidia"
    names += [str(p) for p in sorted(nvidia.glob("**/libcublasLt.so*"))]
    for name in names:
        try:
            lib = ctypes.CDLL(name)
        except OSError:
            continue
        vp, sz = ctypes.c_void_p, ctypes.c_size_t
        lib.cublasLtCreate.argtypes = [ctypes.POINTER(vp)]
        lib.cublasLtMatmulDescCreate.argtypes = [ctypes.POINTER(vp), ctypes.c_int, ctypes.c_int]
        lib.cublasLtMatmulDescSetAttribute.argtypes = [vp, ctypes.c_int, vp, sz]
        lib.cublasLtMatmulDescDestroy.argtypes = [vp]
        lib.cublasLtMatrixLayoutCreate.argtypes = [
            ctypes.POINTER(vp),
            ctypes.c_int,
            ctypes.c_uint64,
            ctypes.c_uint64,
            ctypes.c_int64,
        ]
        lib.cublasLtMatrixLayoutDestroy.argtypes = [vp]
        lib.cublasLtMatmulPreferenceCreate.argtypes = [ctypes.POINTER(vp)]
        lib.cublasLtMatmulPreferenceSetAttribute.argtypes = [vp, ctypes.c_int, vp, sz]
        lib.cublasLtMatmulPreferenceDestroy.argtypes = [vp]
        lib.cublasLtMatmulAlgoGetHeuristic.argtypes = [vp] * 7 + [
            ctypes.c_int,
            ctypes.POINTER(_Heuristic),
            ctypes.POINTER(ctypes.c_int),
        ]
        lib.cublasLtMatmul.argtypes = [vp] * 14 + [sz, vp]
        return lib
    return None


def _check(status: int, what: str) -> None:
    if status != 0:
        raise RuntimeError(f"cuBLASLt {what} failed (status {status})")


def _set(fn, obj, attr: int, value) -> None:
    _check(fn(obj, attr, ctypes.byref(value), ctypes.sizeof(value)), f"attribute {attr}")


@functools.cache
def _device_state(index: int) -> tuple[ctypes.c_void_p, torch.Tensor, torch.Tensor]:
    """(cuBLASLt handle, workspace, bias-gradient scratch) of CUDA device `index`: kept for
    the process, since a captured graph's GEMMs write into them on every replay, whatever
    became of the plan that captured them."""
    lib = _lib()
    handle = ctypes.c_void_p()
    with torch.cuda.device(index):
        _check(lib.cublasLtCreate(ctypes.byref(handle)), "create")
        workspace = torch.empty(WORKSPACE_BYTES, dtype=torch.uint8, device=f"cuda:{index}")
        scratch = torch.empty(BIAS_SCRATCH, dtype=torch.float32, device=f"cuda:{index}")
    return handle, workspace, scratch


class _Plan:
    """One GEMM's descriptors and algorithm: D (m, n) = op(A) (m, k) · op(B) (k, n),
    column-major, with a ReLU-mask epilogue; the mask's pointer is set at each call. B is
    read transposed where `trans_b` (a feature-major input: torch's transposed view)."""

    def __init__(
        self, index: int, dtype: int, m: int, n: int, k: int, ldb: int, trans_b: bool, forward: bool
    ):
        self.desc = ctypes.c_void_p()
        self.layouts = [ctypes.c_void_p() for _ in range(3)]
        lib, (handle, workspace, scratch) = _lib(), _device_state(index)
        self.lib, self.handle, self.workspace = lib, handle, workspace
        _check(lib.cublasLtMatmulDescCreate(ctypes.byref(self.desc), _COMPUTE_32F, _R_32F), "desc")
        a_rows, a_cols = (k, m) if forward else (m, k)
        for layout, (rows, cols, ld) in zip(
            self.layouts,
            [(a_rows, a_cols, a_rows), (n, k, ldb) if trans_b else (k, n, ldb), (m, n, m)],
            strict=True,
        ):
            _check(
                lib.cublasLtMatrixLayoutCreate(ctypes.byref(layout), dtype, rows, cols, ld),
                "layout",
            )
        setd = lib.cublasLtMatmulDescSetAttribute
        _set(setd, self.desc, _DESC_TRANSA, ctypes.c_int32(_OP_T if forward else _OP_N))
        _set(setd, self.desc, _DESC_TRANSB, ctypes.c_int32(_OP_T if trans_b else _OP_N))
        _set(setd, self.desc, _DESC_AUX_LD, ctypes.c_int64(mask_bytes(m) * 8))
        # the heuristics read the pointers' alignment: the workspace stands in for them
        self.set_mask(workspace.data_ptr())
        epilogues = [_EPI_RELU_AUX] if forward else [_EPI_DRELU, _EPI_DRELU_BGRAD]
        self.algo = None
        for epi in epilogues:
            _set(setd, self.desc, _DESC_EPILOGUE, ctypes.c_uint32(epi))
            if epi == _EPI_DRELU_BGRAD:  # a bias gradient nobody reads, where DRELU needs one
                if m > BIAS_SCRATCH:
                    break
                _set(setd, self.desc, _DESC_BIAS_POINTER, ctypes.c_void_p(scratch.data_ptr()))
            self.algo = self._heuristic()
            if self.algo is not None:
                break

    def _heuristic(self) -> _Heuristic | None:
        lib = self.lib
        pref = ctypes.c_void_p()
        _check(lib.cublasLtMatmulPreferenceCreate(ctypes.byref(pref)), "preference")
        try:
            setp = lib.cublasLtMatmulPreferenceSetAttribute
            _set(setp, pref, _PREF_MAX_WORKSPACE, ctypes.c_uint64(WORKSPACE_BYTES))
            for attr in _PREF_MIN_ALIGN:
                _set(setp, pref, attr, ctypes.c_uint32(_POINTER_ALIGN))
            result, count = _Heuristic(), ctypes.c_int(0)
            a, b, d = self.layouts
            status = lib.cublasLtMatmulAlgoGetHeuristic(
                self.handle,
                self.desc,
                a,
                b,
                d,
                d,
                pref,
                1,
                ctypes.byref(result),
                ctypes.byref(count),
            )
        finally:
            lib.cublasLtMatmulPreferenceDestroy(pref)
        return result if status == 0 and count.value > 0 and result.state == 0 else None

    def set_mask(self, ptr: int) -> None:
        setd = self.lib.cublasLtMatmulDescSetAttribute
        _set(setd, self.desc, _DESC_AUX_POINTER, ctypes.c_void_p(ptr))

    def run(self, a: torch.Tensor, b: torch.Tensor, d: torch.Tensor, mask: torch.Tensor) -> None:
        self.set_mask(mask.data_ptr())
        la, lb, ld = self.layouts
        one, zero = ctypes.c_float(1.0), ctypes.c_float(0.0)
        stream = torch.cuda.current_stream(d.device).cuda_stream
        status = self.lib.cublasLtMatmul(
            self.handle,
            self.desc,
            ctypes.byref(one),
            a.data_ptr(),
            la,
            b.data_ptr(),
            lb,
            ctypes.byref(zero),
            d.data_ptr(),
            ld,
            d.data_ptr(),
            ld,
            ctypes.byref(self.algo),
            self.workspace.data_ptr(),
            WORKSPACE_BYTES,
            stream,
        )
        _check(status, "matmul")

    def __del__(self):
        try:  # a plan whose making failed part way, or one outliving the library at exit
            for layout in self.layouts:
                if layout.value:
                    self.lib.cublasLtMatrixLayoutDestroy(layout)
            if self.desc.value:
                self.lib.cublasLtMatmulDescDestroy(self.desc)
        except Exception:
            pass


_PLANS: OrderedDict[tuple, _Plan | None] = OrderedDict()
_MAX_PLANS = 64  # eager steps' sample counts vary; a captured step's stay fixed


def _plan(key: tuple) -> _Plan | None:
    """The cached plan of key (device, dtype, m, n, k, ldb, trans_b, forward), None where
    cuBLASLt has no algorithm for it."""
    if key not in _PLANS:
        try:
            plan = _Plan(*key)
        except RuntimeError:  # a status cuBLASLt refuses the descriptors with: the fallback
            plan = None
        _PLANS[key] = plan if plan is not None and plan.algo is not None else None
        while len(_PLANS) > _MAX_PLANS:
            _PLANS.popitem(last=False)
    _PLANS.move_to_end(key)
    return _PLANS[key]


def usable(device: torch.device) -> bool:
    """Whether `masked_relu_mlp` pays its way on device: off CUDA its torch ops always run (the
    reference); on CUDA only where cuBLASLt's library is found (else the fused GEMMs do)."""
    return device.type != "cuda" or _lib() is not None


def available(device: torch.device, dtype: torch.dtype) -> bool:
    """Whether cuBLASLt's mask epilogues can run on device in dtype (CUDA, bf16 or fp16)."""
    return device.type == "cuda" and dtype in _DTYPES and _lib() is not None


def _operand(t: torch.Tensor) -> tuple[torch.Tensor, int, bool]:
    """t (N, C) as cuBLAS reads it: (t, leading dimension, whether it is column-major), t
    row-major (unit column stride) or a transposed view of (C, N) storage (the hash grid's
    features), else copied into rows; so is a start or a leading dimension that is not 16
    bytes aligned (a sample count not a multiple of 8 in feature-major storage), which the
    plans' aligned kernels cannot read."""
    n, c = t.shape
    step = _POINTER_ALIGN // t.element_size()
    if t.data_ptr() % _POINTER_ALIGN == 0:
        ld = t.stride(0)
        if t.stride(1) == 1 and ld >= max(c, 1) and ld % step == 0:
            return t, ld, False
        ld = t.stride(1)
        if t.stride(0) == 1 and ld >= max(n, 1) and ld % step == 0:
            return t, ld, True
    return t.contiguous(), max(c, 1), False


def _lt_plan(
    x: torch.Tensor, m: int, k: int, ldb: int, trans_b: bool, forward: bool
) -> _Plan | None:
    if not available(x.device, x.dtype) or x.shape[0] == 0:  # `_operand` aligned ldb
        return None
    index = x.device.index if x.device.index is not None else torch.cuda.current_device()
    return _plan((index, _DTYPES[x.dtype], m, x.shape[0], k, ldb, trans_b, forward))


def linear_relu_mask(x: torch.Tensor, w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """relu(x @ wᵀ) and its bit mask: x (N, in), w (out, in) of one dtype -> ((N, out),
    (N, mask_bytes(out)) uint8), in one cuBLASLt GEMM where it can (RELU_AUX)."""
    x, ldx, trans = _operand(x)
    w = w.contiguous()
    out, k = w.shape
    plan = _lt_plan(x, out, k, ldx, trans, forward=True)
    if plan is None:
        y = torch.relu(x @ w.t())
        return y, pack_mask(y)
    y = torch.empty(x.shape[0], out, dtype=x.dtype, device=x.device)
    mask = torch.empty(x.shape[0], mask_bytes(out), dtype=torch.uint8, device=x.device)
    plan.run(w, x, y, mask)
    return y, mask


def masked_grad(g: torch.Tensor, w: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """(g @ w) ⊙ mask: g (N, out') the gradient of a layer's output, w (out', out) its weight,
    mask (N, mask_bytes(out)) the layer below's ReLU mask -> (N, out), the gradient of that
    layer's pre-activation, in one cuBLASLt GEMM where it can (DRELU)."""
    g, ldg, trans = _operand(g)
    w = w.contiguous()
    k, out = w.shape
    plan = _lt_plan(g, out, k, ldg, trans, forward=False)
    if plan is None:
        return (g @ w).masked_fill_(~unpack_mask(mask, out), 0)
    d = torch.empty(g.shape[0], out, dtype=g.dtype, device=g.device)
    plan.run(w, g, d, mask)
    return d


class _MaskedReluMLP(torch.autograd.Function):
    """x -> relu(· w_0ᵀ) -> … -> relu(· w_{L-2}ᵀ) -> · w_{L-1}ᵀ, the hidden layers' ReLU
    masks kept as bits and applied in the backward's GEMMs (module docstring)."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, *ws: torch.Tensor) -> torch.Tensor:
        inputs, masks = [x], []
        for w in ws[:-1]:
            h, m = linear_relu_mask(inputs[-1], w)
            inputs.append(h)
            masks.append(m)
        ctx.n = len(ws)
        ctx.save_for_backward(*inputs, *masks, *ws)
        return inputs[-1] @ ws[-1].t()

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g: torch.Tensor):
        n, saved = ctx.n, ctx.saved_tensors
        inputs, masks, ws = saved[:n], saved[n : 2 * n - 1], saved[2 * n - 1 :]
        grads: list[torch.Tensor | None] = [None] * (n + 1)
        for i in reversed(range(n)):
            if ctx.needs_input_grad[1 + i]:
                grads[1 + i] = g.t() @ inputs[i]
            if i > 0:
                g = masked_grad(g, ws[i], masks[i - 1])
            elif ctx.needs_input_grad[0]:
                grads[0] = g @ ws[0]
        return tuple(grads)


def masked_relu_mlp(x: torch.Tensor, weights: list[torch.Tensor]) -> torch.Tensor:
    """The no-bias ReLU MLP of `weights` (w_i (out_i, in_i), the last one linear) on x
    (N, in_0) -> (N, out_last), all of one dtype, its ReLU gradients applied through bit
    masks (cuBLASLt's epilogues on CUDA in bf16/fp16, torch ops elsewhere)."""
    return _MaskedReluMLP.apply(x, *weights)
