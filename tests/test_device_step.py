"""The device-paced step (issue #17) takes the same steps as the plain one, on the CPU.

Both paths run the same fused torch Adam here, so they must agree to the last bit where every
loss is finite; where one is not, the device path must skip the update exactly as the plain path
does, although the host only learns of it later.
"""

import json
import math

import numpy as np
import pytest
import torch

from fastenerf.data.formats.native import load_scene
from fastenerf.hooks import Checkpointer, DivergenceGuard, MetricsLog
from fastenerf.run import load_checkpoint
from fastenerf.train import STATS_FLUSH_EVERY, Trainer
from tests.test_train import tiny_cfg


@pytest.fixture(scope="module")
def scene(tiny_scene):
    return load_scene(tiny_scene)


def make(scene, path, mode: str, backend: str = "ngp", **kw) -> Trainer:
    trainer = Trainer(scene, tiny_cfg(backend, step_mode="device", **kw), path)
    assert trainer.set_step_mode(mode) == mode
    return trainer


def weights(trainer: Trainer) -> dict[str, torch.Tensor]:
    return {k: p.detach().clone() for k, p in trainer.field.named_parameters()}


@pytest.mark.parametrize("backend", ["ngp", "vanilla"])
def test_device_path_takes_the_plain_paths_steps(scene, tmp_path, backend):
    # one after the other: each trainer seeds the global generator (ray jitter) when built
    plain = make(scene, tmp_path / "plain", "plain", backend, steps=5)
    a = [plain.step()["loss"] for _ in range(5)]
    device = make(scene, tmp_path / "device", "device", backend, steps=5)
    b = [device.step()["loss"] for _ in range(5)]
    assert torch.is_tensor(b[-1])  # still on the device until flushed
    device.flush_stats()
    b = [s["loss"] for s in device.history]
    assert a == b
    wa, wb = weights(plain), weights(device)
    for k in wa:
        assert torch.equal(wa[k], wb[k]), k


def test_device_path_skips_a_non_finite_loss(scene, tmp_path):
    trainer = make(scene, tmp_path / "run", "device", steps=3)
    before = weights(trainer)
    sample = trainer.sampler.sample

    def poisoned():
        batch = sample()
        batch.target[0] = float("nan")
        return batch

    trainer.sampler.sample = poisoned
    stats = trainer.step()
    trainer.flush_stats()
    assert math.isnan(stats["loss"]) and stats["skipped_steps"] == 1
    assert trainer.nonfinite_run == 1
    after = weights(trainer)
    for k in before:
        assert torch.equal(before[k], after[k]), k
    # Adam's step count did not advance either: the next good step is the first update
    state = trainer.optimizer.state[trainer.field.table]
    assert float(state["step"]) == 0.0


def test_device_path_skips_a_non_finite_gradient_of_a_finite_loss(scene, tmp_path):
    trainer = make(scene, tmp_path / "run", "device", steps=3)
    forward = trainer._forward

    def nan_grad(batch):
        out, loss, parts = forward(batch)
        # finite value, NaN gradient (sqrt at 0), as a stiff density can give
        return out, loss + torch.sqrt(trainer.field.table.sum() * 0.0), parts

    trainer._forward = nan_grad
    before = weights(trainer)
    stats = trainer.step()
    trainer.flush_stats()
    assert math.isfinite(stats["loss"]) and trainer.skipped_steps == 1
    after = weights(trainer)
    assert all(torch.equal(before[k], after[k]) for k in before)


def test_divergence_guard_stops_a_device_paced_run(scene, tmp_path):
    trainer = make(scene, tmp_path / "run", "device", steps=300)
    forward = trainer._forward

    def nan_forward(batch):
        out, loss, parts = forward(batch)
        return out, (loss * float("nan") if trainer.step_count >= 3 else loss), parts

    trainer._forward = nan_forward
    patience = 5
    hooks = [DivergenceGuard(patience), Checkpointer(every_s=0, every_steps=1)]
    summary = trainer.run(hooks)
    assert summary["failure"] and "diverged" in summary["failure"]
    # the host learns of the run at a flush: at most STATS_FLUSH_EVERY steps late
    assert 3 + patience <= summary["steps"] <= 3 + patience + STATS_FLUSH_EVERY
    ck = load_checkpoint(tmp_path / "run" / "checkpoint.pt")
    now = weights(trainer)
    for k, v in now.items():  # the weights never saw a NaN step
        assert torch.isfinite(v).all() and torch.equal(ck["field"][k], v), k


def test_metrics_log_writes_every_step_it_should(scene, tmp_path):
    trainer = make(scene, tmp_path / "run", "device", steps=40, log_every=4)
    trainer.run([MetricsLog(4)])
    lines = (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()
    rows = [json.loads(x) for x in lines]
    steps = [r["step"] for r in rows]
    assert steps == sorted(steps) and steps[-1] == 40
    expected = {s for s in range(1, 41) if s % 4 == 0 or s <= 10}
    assert expected == set(steps)
    assert all(isinstance(r["loss"], float) and np.isfinite(r["loss"]) for r in rows)
