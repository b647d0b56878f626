"""The optimiser: Adam, row-sparse for large hash tables on a CPU (`make_adam` picks).

A hash-grid step reads a fraction of the table's rows; dense Adam still updates every row (a
handful of passes over weight, gradient and both moments), which on a CPU costs more than the
step's real work once the table is large. `RowSparseAdam` updates only the rows the step's
backward wrote (the hash grid's backward marks them: `fastenerf.kernels.rows`), with dense
Adam's arithmetic on those rows. Its cost grows with the rows touched, dense Adam's with the
rows held: it wins where a step touches a small share of a large table (the GPU's 16 x 2^19
table on a CPU), loses where it touches most of a small one (the CPU preset's), so `make_adam`
uses it above ROW_SPARSE_MIN_ROWS rows (measured: benchmarks/RESULTS.md).

Lazy semantics (as torch.optim.SparseAdam and TensorFlow's LazyAdam): a row the step did not
touch keeps its weight and its moments (m, v) unchanged; dense Adam would decay its moments and
keep moving it along m / √v with a zero gradient. So:
- a row touched at every step, and a row never touched, end exactly as under torch.optim.Adam;
- a row touched now and then skips the moment decay of the steps between (its next update uses
  the moments it had when last touched) and the coasting updates dense Adam would have made;
- the bias corrections use the parameter's global step count (every step counts, touched or not).
A step pre-hook (data-parallel gradient averaging brings other ranks' rows) or a backward that
marked no rows makes that step dense for the table: exactly torch.optim.Adam's update.

On CUDA `make_adam` returns torch.optim.Adam(fused=True) (one kernel for every parameter; the
trainer may set its `grad_scale` / `found_inf`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

import torch

from .kernels.rows import RowTracker, track_rows

# Tables with more rows than this get RowSparseAdam on a CPU (see the module docstring).
ROW_SPARSE_MIN_ROWS = 1 << 22


def make_adam(
    groups: list[dict],
    device: torch.device,
    *,
    lr: float,
    betas: tuple[float, float],
    eps: float,
    row_sparse: Iterable[torch.nn.Parameter] = (),
    min_rows: int = ROW_SPARSE_MIN_ROWS,
    fused: bool = False,
) -> torch.optim.Optimizer:
    """The run's Adam: fused torch Adam on CUDA (or anywhere with `fused`: the device-paced
    step needs it); on a CPU, `RowSparseAdam` when a parameter given in `row_sparse` (hash
    tables, rows = dim 0) has over `min_rows` rows, else torch's Adam."""
    row_sparse = [p for p in row_sparse if p.shape[0] > min_rows]
    if device.type == "cuda" or fused:
        return torch.optim.Adam(groups, lr=lr, betas=betas, eps=eps, fused=True)
    if not row_sparse:
        return torch.optim.Adam(groups, lr=lr, betas=betas, eps=eps)
    return RowSparseAdam(groups, lr=lr, betas=betas, eps=eps, row_sparse=row_sparse)


def field_adam(field: torch.nn.Module, cfg, device: torch.device) -> torch.optim.Optimizer:
    """The training run's Adam over `field.param_groups()` (`make_adam`): cfg a TrainConfig
    (lr, adam_betas, adam_eps, step_mode: the device-paced steps need the fused Adam, whose
    found_inf skips on the device). Each group keeps its lr_scale (its lr / cfg.lr)."""
    groups = field.param_groups()
    for g in groups:
        g.setdefault("lr", cfg.lr)
        g["lr_scale"] = g["lr"] / cfg.lr
    table = getattr(field, "table", None)  # the ngp field's hash table
    return make_adam(
        groups,
        device,
        lr=cfg.lr,
        betas=tuple(cfg.adam_betas),
        eps=cfg.adam_eps,
        row_sparse=[table] if isinstance(table, torch.nn.Parameter) else [],
        fused=cfg.step_mode in ("device", "graph"),
    )


def set_lr(optimizer: torch.optim.Optimizer, lr: float) -> None:
    """Each group's learning rate = lr × its "lr_scale" (default 1); a tensor learning rate (one
    a captured step reads, `lr_as_tensors`) is filled in place, without a host wait."""
    for g in optimizer.param_groups:
        set_group_lr(g, lr * g.get("lr_scale", 1.0))


def set_group_lr(group: dict, value: float) -> None:
    """One group's learning rate; a tensor one (`lr_as_tensors`) is filled in place."""
    if torch.is_tensor(group["lr"]):
        group["lr"].fill_(value)
    else:
        group["lr"] = value


def lr_as_tensors(optimizer: torch.optim.Optimizer, device: torch.device) -> None:
    """Make a fused Adam capturable: its learning rates 0-dim tensors on `device` (a graph
    reads them when replayed; a float would be baked in at capture). float32 on CUDA, as the
    fused CUDA kernel takes it; float64 on a CPU, whose kernel takes a float lr as a double."""
    dtype = torch.float64 if torch.device(device).type == "cpu" else torch.float32
    for g in optimizer.param_groups:
        g["lr"] = torch.tensor(float(g["lr"]), dtype=dtype, device=device)
        g["capturable"] = True


def lr_as_floats(optimizer: torch.optim.Optimizer) -> None:
    """Undo `lr_as_tensors` (also after loading a state saved with tensor learning rates)."""
    for g in optimizer.param_groups:
        if torch.is_tensor(g["lr"]):
            g["lr"] = float(g["lr"])
        if "capturable" in g:
            g["capturable"] = False


def fit_state(optimizer: torch.optim.Optimizer, fit: Callable[[torch.Tensor], torch.Tensor]):
    """Per-parameter state (Adam's moments) saved for a parameter of another shape made to its
    parameter's shape by `fit` (a checkpoint of an older layout: `ColorMLP.pad_legacy`).
    Raises ValueError where `fit` does not give the parameter's shape."""
    for group in optimizer.param_groups:
        for p in group["params"]:
            state = optimizer.state.get(p, {})
            for key, v in state.items():
                if torch.is_tensor(v) and v.dim() == p.dim() and v.shape != p.shape:
                    state[key] = fit(v)
                    if state[key].shape != p.shape:
                        raise ValueError(
                            f"optimiser state {key} {tuple(v.shape)} does not fit a parameter "
                            f"{tuple(p.shape)}"
                        )


class RowSparseAdam(torch.optim.Optimizer):
    """Adam whose `row_sparse` parameters (tables, rows = dim 0) update only the rows their
    backward passes recorded (see the module docstring for the lazy semantics); every other
    parameter gets torch.optim.Adam's update (no weight decay, no amsgrad).

    The state per parameter is torch Adam's (step, exp_avg, exp_avg_sq), so checkpoints move
    between the two.
    """

    def __init__(
        self,
        params,
        lr: float = 1e-3,
        betas: tuple[float, float] = (0.9, 0.999),
        eps: float = 1e-8,
        row_sparse: Iterable[torch.nn.Parameter] = (),
    ):
        if not (0.0 <= betas[0] < 1.0 and 0.0 <= betas[1] < 1.0) or lr < 0 or eps < 0:
            raise ValueError(f"RowSparseAdam: bad lr {lr}, betas {betas} or eps {eps}")
        super().__init__(params, {"lr": lr, "betas": tuple(betas), "eps": eps})
        self.trackers: dict[torch.nn.Parameter, RowTracker] = {p: track_rows(p) for p in row_sparse}
        self.dense_steps = 0  # steps a tracked table took densely (see the module docstring)

    def zero_grad(self, set_to_none: bool = True) -> None:
        super().zero_grad(set_to_none)
        for t in self.trackers.values():
            if t.passes:  # a backward whose step was not taken: its rows go with its gradient
                t.clear()

    def _state(self, p: torch.Tensor) -> dict:
        st = self.state[p]
        if not st:
            st["step"] = torch.tensor(0.0, dtype=torch.float32)
            st["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
            st["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)
        return st

    @torch.no_grad()
    def step(self, closure=None):
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()
        hooked = bool(self._optimizer_step_pre_hooks)
        for group in self.param_groups:
            for p in group["params"]:
                tracker = self.trackers.get(p)
                if p.grad is None:
                    if tracker is not None and tracker.passes:
                        tracker.clear()
                    continue
                st = self._state(p)
                st["step"] += 1
                rows = None
                if tracker is not None:
                    recorded = tracker.passes > 0
                    rows = tracker.take()
                    if hooked or not recorded:
                        rows = None
                        self.dense_steps += 1
                _adam_update(p, p.grad, st, group, rows)
        return loss


def _adam_update(p, grad, st: dict, group: dict, rows: torch.Tensor | None) -> None:
    """torch.optim.Adam's single-tensor update of p (all rows, or only `rows` (K,) int64)."""
    beta1, beta2 = group["betas"]
    lr, eps = group["lr"], group["eps"]
    step = float(st["step"])
    step_size = lr / (1 - beta1**step)
    bias_correction2_sqrt = (1 - beta2**step) ** 0.5
    m, v = st["exp_avg"], st["exp_avg_sq"]
    if rows is None:
        m.lerp_(grad, 1 - beta1)
        v.mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
        denom = (v.sqrt() / bias_correction2_sqrt).add_(eps)
        p.addcdiv_(m, denom, value=-step_size)
        return
    if rows.numel() == 0:
        return
    # Rows as single elements (8 bytes for 2 float32 features): a gather or scatter of whole
    # rows then costs a fraction of one over (K, F) slices.
    p1, g1, m1, v1 = (_rows_as_elements(t) for t in (p, grad, m, v))
    shape = (rows.shape[0], *p.shape[1:])
    g = g1.index_select(0, rows).view(p.dtype).view(shape)
    m_r = m1.index_select(0, rows).view(p.dtype).view(shape).lerp_(g, 1 - beta1)
    v_r = v1.index_select(0, rows).view(p.dtype).view(shape).mul_(beta2)
    v_r.addcmul_(g, g, value=1 - beta2)
    denom = (v_r.sqrt() / bias_correction2_sqrt).add_(eps)
    p_r = p1.index_select(0, rows).view(p.dtype).view(shape).addcdiv_(m_r, denom, value=-step_size)
    for dst, src in ((m1, m_r), (v1, v_r), (p1, p_r)):
        dst.index_copy_(
            0, rows, src.reshape(rows.shape[0], -1).view(dst.dtype).view(-1, *dst.shape[1:])
        )


# Element types by size in bytes: a table row of that many bytes is one element of the view.
_ROW_TYPES = {1: torch.uint8, 2: torch.int16, 4: torch.int32, 8: torch.int64, 16: torch.complex128}


def _rows_as_elements(t: torch.Tensor) -> torch.Tensor:
    """A contiguous (n, ...) tensor as (n,) elements of one row each, or (n, -1) if no dtype
    has the row's size."""
    row_bytes = t[0].numel() * t.element_size() if t.shape[0] else 0
    if row_bytes in _ROW_TYPES and t.is_contiguous():
        return t.view(t.shape[0], -1).view(_ROW_TYPES[row_bytes]).view(-1)
    return t.view(t.shape[0], -1)
