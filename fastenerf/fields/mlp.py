"""The ngp field's tiny MLPs, the colour one with widths that suit the GPU's tensor cores.

cuBLAS runs a bf16 GEMM whose rows are not a multiple of 8 elements (16 bytes) long on its
slow `align1` kernels. The colour MLP over [geometry features (15), SH (16)] has a 31-wide
input and a 3-wide output, so six of its GEMMs (forward and backward) ran on them: 1.8 of the
3.0 ms its MLPs took in a 7.9 ms-device step of the mesh scene on an H200
(benchmarks/RESULTS.md, the thirty-first session). `ColorMLP` computes the same function
with aligned widths, as tiny-cuda-nn pads its networks:

- its input is the density MLP's whole output (σ logit first, then the geometry features)
  beside SH: 16 + 16 = 32 for the default widths (zero columns pad other widths to a
  multiple of 8); the first layer's weights on the σ logit are masked to 0 (a (hidden, 32)
  product a call, not one over the (N, 16) input), and the two halves are concatenated as
  integer words (`concat_rows`);
- its output layer has 8 rows; the first 3 are the colour.

The weights on the masked and the zero inputs and of the unused outputs start at 0 and get no
gradient (a mask, a zero input, an output nothing reads), so the padded MLP computes what the
unpadded one of the same initial weights does; a checkpoint of the unpadded MLP loads into it,
padded with zeros.

With `fused_relu` each hidden layer is one GEMM whose epilogue applies the ReLU (cuBLASLt's
RELU_BIAS, reached through `torch._addmm_activation` with a zero bias) instead of a GEMM and
a separate ReLU kernel that reads and writes every sample's activations again (what that
pass costs a training step: benchmarks/RESULTS.md, the thirty-eighth session). The backward
is the same three kernels either way (cuBLASLt's DRELU epilogue, which would fold the
backward's threshold pass into a GEMM, ran as a separate kernel on an H200 and lost:
benchmarks/RESULTS.md, the forty-second session).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

ALIGN = 8  # elements: 16 bytes of bf16, what cuBLAS's vectorised kernels need of a row
N_SH = 16  # the degree-4 SH encoding's width
N_RGB = 3


def aligned(n: int) -> int:
    """n rounded up to a multiple of ALIGN."""
    return -(-n // ALIGN) * ALIGN


_ZERO_BIAS: dict[tuple, torch.Tensor] = {}


def _zero_bias(n: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """A zero (n,) vector, made once per (n, dtype, device): a captured step reuses it rather
    than filling a new one each replay."""
    key = (n, dtype, device)
    if key not in _ZERO_BIAS:
        _ZERO_BIAS[key] = torch.zeros(n, dtype=dtype, device=device)
    return _ZERO_BIAS[key]


class _LinearReLU(torch.autograd.Function):
    """relu(x @ wᵀ) as one `_addmm_activation` (no autograd formula of its own)."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        y = torch._addmm_activation(_zero_bias(w.shape[0], x.dtype, x.device), x, w.t())
        ctx.save_for_backward(x, w, y)
        return y

    @staticmethod
    def backward(ctx, g: torch.Tensor):
        x, w, y = ctx.saved_tensors
        gy = torch.ops.aten.threshold_backward(g, y, 0)  # what nn.ReLU's backward runs
        gx = gy.mm(w) if ctx.needs_input_grad[0] else None
        gw = gy.t().mm(x) if ctx.needs_input_grad[1] else None
        return gx, gw


def linear_relu(x: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """relu(F.linear(x, w)), x (N, in), w (out, in) -> (N, out), with the ReLU in the GEMM;
    computed in autocast's dtype where autocast is on (as F.linear would), else in w's."""
    kind = x.device.type
    dt = torch.get_autocast_dtype(kind) if torch.is_autocast_enabled(kind) else w.dtype
    x = x if x.dtype == dt else x.to(dt)
    w = w if w.dtype == dt else w.to(dt)
    with torch.autocast(kind, enabled=False):
        return _LinearReLU.apply(x, w)


class MLP(nn.Sequential):
    """Linear (no bias) + ReLU layers and a linear output, run with each hidden layer's ReLU
    fused into its GEMM when `fused_relu` (module docstring); the same parameters and state
    dict either way."""

    def __init__(self, *layers: nn.Module, fused_relu: bool = False):
        super().__init__(*layers)
        self.fused_relu = fused_relu

    def run(self, x: torch.Tensor, first_weight: torch.Tensor | None = None) -> torch.Tensor:
        """The layers on x (N, in) -> (N, out); first_weight: the first layer's weight to use
        in its place (ColorMLP's masked one)."""
        layers = list(self)
        i = 0
        while i < len(layers):
            layer, w = layers[i], first_weight if i == 0 else None
            if self.fused_relu and i + 1 < len(layers) and isinstance(layers[i + 1], nn.ReLU):
                x = linear_relu(x, layer.weight if w is None else w)
                i += 2
                continue
            # unfused, each module is called (its hooks run), as nn.Sequential would
            x = layer(x) if w is None else F.linear(x, w)
            i += 1
        return x

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.run(x)


def mlp(
    n_in: int,
    hidden: int,
    n_out: int,
    n_hidden_layers: int,
    fused_relu: bool = False,
) -> MLP:
    """Linear (no bias) + ReLU per hidden layer, then a linear output: (N, n_in) -> (N, n_out)."""
    # No biases, like tiny-cuda-nn's fully fused MLPs: the hash features carry the offsets.
    layers: list[nn.Module] = []
    d = n_in
    for _ in range(n_hidden_layers):
        layers += [nn.Linear(d, hidden, bias=False), nn.ReLU(inplace=True)]
        d = hidden
    layers.append(nn.Linear(d, n_out, bias=False))
    return MLP(*layers, fused_relu=fused_relu)


_WORDS = ((torch.int64, 8), (torch.int32, 4), (torch.int16, 2))  # (dtype, bytes), widest first


def _word_for(parts: list[torch.Tensor]) -> torch.dtype | None:
    """The widest integer word that tiles every part's rows (one dtype for all, so that the
    words concatenate without promotion), or None."""
    size = parts[0].element_size()
    if any(p.dim() != 2 or p.dtype != parts[0].dtype for p in parts):
        return None
    for word, w in _WORDS:
        if w >= size and all(p.shape[1] * size % w == 0 for p in parts):
            return word
    return None


def _as_words(t: torch.Tensor, word: torch.dtype) -> torch.Tensor | None:
    """A row-major 2-D tensor viewed as `word`s (its rows tiled by them), or None where it
    cannot be (strides, an unaligned storage offset)."""
    if not t.is_contiguous():
        return None
    try:
        return t.view(word)
    except RuntimeError:
        return None


class _ConcatRows(torch.autograd.Function):
    """torch.cat(parts, 1) whose copy moves whole words: torch's cat copies a 2-byte element
    per thread, and the colour MLP's bf16 input took it 0.19 ms of a 6.5 ms H200 step."""

    @staticmethod
    def forward(ctx, *parts: torch.Tensor) -> torch.Tensor:
        ctx.widths = [p.shape[1] for p in parts]
        word = _word_for(list(parts))
        words = [None if word is None else _as_words(p, word) for p in parts]
        if any(w is None for w in words):
            return torch.cat(parts, 1)
        return torch.cat(words, 1).view(parts[0].dtype)

    @staticmethod
    def backward(ctx, g: torch.Tensor):
        return tuple(g.split(ctx.widths, 1))


def concat_rows(parts: list[torch.Tensor]) -> torch.Tensor:
    """torch.cat(parts, 1) of (N, C_i) tensors of one dtype, the same values and gradients,
    copied as integer words where every part allows it (else torch.cat itself)."""
    return _ConcatRows.apply(*parts)


class _DensityLogit(torch.autograd.Function):
    """(σ logit (N,) float32, h) from the density MLP's output h (N, 1 + geo): h's single
    consumer, so that its gradient is the colour MLP's with the logit's added into column 0,
    where the colour MLP's masked first weights leave zeros (ColorMLP), rather than a
    zero-filled select's gradient added to the whole of it: one pass over every sample's h
    gradient, and a fill, fewer."""

    @staticmethod
    def forward(ctx, h: torch.Tensor):
        ctx.set_materialize_grads(False)
        ctx.meta = (h.shape, h.dtype, h.device)
        return h[:, 0].float(), h.view_as(h)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_logit, g_h):
        shape, dtype, device = ctx.meta
        if g_h is None:
            g_h = torch.zeros(shape, dtype=dtype, device=device)
        elif not _owned_rows(g_h):
            g_h = g_h.clone()
        if g_logit is not None:
            g_h[:, 0] += g_logit.to(dtype)
        return g_h


def _owned_rows(g: torch.Tensor) -> bool:
    """Whether g is a slice of rows written by the backward that made it (the colour MLP's
    input gradient, split by _ConcatRows), so adding into its first column touches nothing
    another gradient reads: a view of a dense buffer, rows apart by at least their width."""
    return g._base is not None and g.stride(1) == 1 and g.stride(0) >= g.shape[1]


def density_logit(h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The density MLP's output h (N, 1 + geo) -> (its column 0 as float32 (N,), h for the
    colour MLP), the gradients those of `h[:, 0].float()` and h."""
    return _DensityLogit.apply(h)


class ColorMLP(MLP):
    """Colour logits (N, 3) from the density MLP's output h (N, 1 + geo_features), σ logit
    first, and the view directions' SH (N, 16); two hidden layers of `hidden`, no biases.

    Its layers are `mlp(geo_features + 16, hidden, 3, 2)`'s, drawn from torch's generator in
    the same order (the same initial function), with the first layer's input and the last
    layer's output padded with zero weights (module docstring). The output is in the
    layers' dtype (bf16 under autocast), a view of the padded one's first 3 columns.
    """

    def __init__(self, geo_features: int, hidden: int, fused_relu: bool = False):
        plain = mlp(geo_features + N_SH, hidden, N_RGB, 2)
        super().__init__(*plain, fused_relu=fused_relu)
        self.n_h = 1 + geo_features
        self.n_pad = aligned(self.n_h + N_SH) - (self.n_h + N_SH)
        with torch.no_grad():
            first, last = self[0], self[len(self) - 1]
            self[0] = nn.Linear(first.in_features + 1 + self.n_pad, hidden, bias=False)
            self[0].weight.copy_(self._pad_in(first.weight))
            self[len(self) - 1] = nn.Linear(hidden, aligned(N_RGB), bias=False)
            self[len(self) - 1].weight.copy_(self._pad_out(last.weight))
        # the σ logit's input column stays out of the function and gets no gradient: its
        # weights are masked (a (hidden, 32) product) rather than the (N, 16) input
        mask = torch.ones(1, self[0].in_features)
        mask[0, 0] = 0.0
        self.register_buffer("w_mask", mask, persistent=False)

    @torch.no_grad()
    def hold_view(self, on: bool) -> None:
        """Mask (on) or unmask the first layer's weights on the SH inputs past degree 0 (a
        constant): a colour that ignores the view direction, those weights getting no
        gradient meanwhile. In place: a captured step reads the mask as it is."""
        self.w_mask[0, self.n_h + 1 : self.n_h + N_SH] = 0.0 if on else 1.0

    def _pad_in(self, w: torch.Tensor) -> torch.Tensor:
        """(hidden, geo + 16) first-layer weights -> (hidden, aligned): a zero column for the
        σ logit in front, zero columns for the padding behind."""
        rows = w.shape[0]
        return torch.cat([w.new_zeros(rows, 1), w, w.new_zeros(rows, self.n_pad)], 1)

    @staticmethod
    def _pad_out(w: torch.Tensor) -> torch.Tensor:
        """(3, hidden) output weights -> (aligned(3), hidden), zero rows behind."""
        return torch.cat([w, w.new_zeros(aligned(N_RGB) - N_RGB, w.shape[1])], 0)

    def pad_legacy(self, t: torch.Tensor) -> torch.Tensor:
        """`t` shaped as the unpadded MLP's first or last weight (a checkpoint's weight, or its
        Adam moments) padded as this MLP's is; any other tensor as it is."""
        if (
            t.dim() == 2
            and t.shape[1] == self.n_h - 1 + N_SH
            and t.shape[0] == self[0].out_features
        ):
            return self._pad_in(t)
        last = self[len(self) - 1]
        if t.dim() == 2 and t.shape[0] == N_RGB and t.shape[1] == last.in_features:
            return self._pad_out(t)
        return t

    def forward(self, h: torch.Tensor, sh: torch.Tensor) -> torch.Tensor:
        # sh_encode hands over a transposed (16, N) float32 storage, which the cast writes as
        # rows, so that the concatenation below can move them as words (its bf16 output is
        # rows already: no copy)
        parts = [h, sh.to(h.dtype, memory_format=torch.contiguous_format)]
        if self.n_pad:
            parts.append(h.new_zeros(()).expand(h.shape[0], self.n_pad))
        y = self.run(concat_rows(parts), first_weight=self[0].weight * self.w_mask)
        return y[:, :N_RGB]

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        # a checkpoint of the unpadded MLP (written before the thirty-first session)
        for key in (f"{prefix}0.weight", f"{prefix}{len(self) - 1}.weight"):
            if key in state_dict:
                state_dict[key] = self.pad_legacy(state_dict[key])
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)
