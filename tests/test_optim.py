"""RowSparseAdam vs torch.optim.Adam (float64), and the hash grid's record of touched rows."""

import copy

import pytest
import torch

from fastenerf.kernels.hashgrid import HashGridConfig, hash_grid_encode, init_table
from fastenerf.optim import RowSparseAdam, make_adam

KW = {"lr": 1e-2, "betas": (0.9, 0.99), "eps": 1e-15}


def record(tracker, rows):
    """What the hash grid's backward does for each row it writes."""
    tracker.mask[list(rows)] = 1
    tracker.passes += 1


def twins(seed=0, features=2):
    """The same (table (40, features), weight (3, 4)) float64 parameters twice."""
    g = torch.Generator().manual_seed(seed)
    table = torch.randn(40, features, generator=g, dtype=torch.float64)
    w = torch.randn(3, 4, generator=g, dtype=torch.float64)
    a = [torch.nn.Parameter(table.clone()), torch.nn.Parameter(w.clone())]
    b = [torch.nn.Parameter(table.clone()), torch.nn.Parameter(w.clone())]
    return a, b


@pytest.mark.parametrize("features", [2, 3])  # rows of 16 bytes (one element) or 24
def test_rows_touched_every_step_and_never_match_dense_adam(features):
    (ta, wa), (tb, wb) = twins(features=features)
    dense = torch.optim.Adam([ta, wa], **KW)
    sparse = RowSparseAdam([tb, wb], **KW, row_sparse=[tb])
    touched = torch.tensor([3, 7, 8, 21, 39])
    g = torch.Generator().manual_seed(1)
    for _ in range(25):
        grad_t = torch.zeros(40, features, dtype=torch.float64)
        grad_t[touched] = torch.randn(len(touched), features, generator=g, dtype=torch.float64)
        grad_w = torch.randn(3, 4, generator=g, dtype=torch.float64)
        for opt, t, w in ((dense, ta, wa), (sparse, tb, wb)):
            opt.zero_grad()
            t.grad, w.grad = grad_t.clone(), grad_w.clone()
        record(sparse.trackers[tb], touched.tolist()[::-1])
        dense.step()
        sparse.step()
    torch.testing.assert_close(tb, ta, rtol=1e-13, atol=1e-15)  # every row: touched or never
    torch.testing.assert_close(wb, wa, rtol=1e-13, atol=1e-15)
    assert sparse.dense_steps == 0
    assert not torch.equal(ta[touched], twins(features=features)[0][0][touched])  # they moved


def test_lazy_rows_keep_weight_and_moments_between_touches():
    (t,), g = twins()[1][:1], torch.Generator().manual_seed(2)
    opt = RowSparseAdam([t], **KW, row_sparse=[t])
    for step in range(6):
        rows = [1, 2] if step % 2 == 0 else [1]  # row 2 every other step
        t.grad = torch.zeros_like(t)
        t.grad[rows] = torch.randn(len(rows), 2, generator=g, dtype=torch.float64)
        record(opt.trackers[t], rows)
        before = (t[2].clone(), opt.state[t]["exp_avg"][2].clone()) if step else None
        opt.step()
        if step % 2:  # not touched: nothing of row 2 changes (dense Adam would move it)
            assert torch.equal(t[2], before[0])
            assert torch.equal(opt.state[t]["exp_avg"][2], before[1])
    assert float(opt.state[t]["step"]) == 6  # bias correction counts every step


def test_step_pre_hook_makes_the_table_dense():
    """Data-parallel averaging adds other ranks' rows to the gradient: update them all."""
    (ta, wa), (tb, wb) = twins()
    dense = torch.optim.Adam([ta, wa], **KW)
    sparse = RowSparseAdam([tb, wb], **KW, row_sparse=[tb])
    sparse.register_step_pre_hook(lambda *a: None)
    g = torch.Generator().manual_seed(3)
    for _ in range(4):
        gt = torch.randn(40, 2, generator=g, dtype=torch.float64)
        ta.grad, tb.grad = gt.clone(), gt.clone()
        wa.grad = wb.grad = None
        record(sparse.trackers[tb], [0])
        dense.step()
        sparse.step()
    torch.testing.assert_close(tb, ta, rtol=1e-13, atol=1e-15)
    assert sparse.dense_steps == 4


def test_state_dict_moves_between_torch_adam_and_row_sparse_adam():
    (ta, wa), (tb, wb) = twins()
    a = torch.optim.Adam([ta, wa], **KW)
    ta.grad, wa.grad = torch.ones_like(ta), torch.ones_like(wa)
    a.step()
    b = RowSparseAdam([tb, wb], **KW, row_sparse=[tb])
    b.load_state_dict(copy.deepcopy(a.state_dict()))  # as through a checkpoint file
    tb.data.copy_(ta.data)
    wb.data.copy_(wa.data)
    for t, w in ((ta, wa), (tb, wb)):
        t.grad, w.grad = torch.full_like(t, 0.5), torch.full_like(w, -0.5)
    record(b.trackers[tb], range(40))
    a.step()
    b.step()
    torch.testing.assert_close(tb, ta, rtol=1e-13, atol=1e-15)
    torch.testing.assert_close(wb, wa, rtol=1e-13, atol=1e-15)


def test_hash_grid_backward_records_exactly_the_rows_it_writes():
    cfg = HashGridConfig(
        n_levels=4, n_features=2, log2_table_size=10, base_resolution=4, max_resolution=64
    )
    table = torch.nn.Parameter(init_table(cfg, generator=torch.Generator().manual_seed(0)))
    twin = torch.nn.Parameter(table.detach().clone())
    x = torch.rand(300, 3, generator=torch.Generator().manual_seed(1))
    cpu = torch.device("cpu")
    assert type(make_adam([twin], cpu, **KW, row_sparse=[twin])) is torch.optim.Adam  # small
    sparse = make_adam([{"params": [table]}], cpu, **KW, row_sparse=[table], min_rows=100)
    dense = torch.optim.Adam([twin], **KW)
    assert isinstance(sparse, RowSparseAdam)
    for t in (table, twin):
        (hash_grid_encode(x, t, cfg) ** 2).sum().backward()
    tracker = sparse.trackers[table]
    marked = torch.nonzero(tracker.mask)[:, 0]
    written = torch.nonzero(table.grad.abs().sum(1))[:, 0]
    assert torch.equal(marked, written)
    recorded = marked
    untouched = torch.ones(cfg.n_params, dtype=torch.bool)
    untouched[recorded] = False
    before = table.detach().clone()
    sparse.step()
    dense.step()
    torch.testing.assert_close(table[recorded], twin[recorded], rtol=1e-6, atol=1e-7)
    assert torch.equal(table[untouched], before[untouched])
    assert int(tracker.mask.sum()) == 0 and tracker.passes == 0  # ready for the next step


def test_untracked_backward_steps_densely():
    """A backward that did not record rows (e.g. a float64 copy of the table) still trains."""
    (ta,), (tb,) = twins()[0][:1], twins()[1][:1]
    dense = torch.optim.Adam([ta], **KW)
    sparse = RowSparseAdam([tb], **KW, row_sparse=[tb])
    ta.grad, tb.grad = torch.ones_like(ta), torch.ones_like(tb)
    dense.step()
    sparse.step()
    torch.testing.assert_close(tb, ta, rtol=1e-13, atol=1e-15)
    assert sparse.dense_steps == 1


@pytest.mark.parametrize("betas", [(1.0, 0.9), (0.9, -0.1)])
def test_rejects_bad_betas(betas):
    with pytest.raises(ValueError, match="betas"):
        RowSparseAdam([torch.nn.Parameter(torch.zeros(2))], betas=betas)
