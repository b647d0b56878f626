"""The device-paced step (issue #17) takes the same steps as the plain one, on the CPU.

Both paths run the same fused torch Adam here, so they must agree up to float32 rounding
(tests/same_steps.py) where every loss is finite; where one is not, the device path must skip
the update exactly as the plain path does, although the host only learns of it later.
"""

import json
import math

import numpy as np
import pytest
import torch

from fastenerf.data.formats.native import load_scene
from fastenerf.hooks import Checkpointer, DivergenceGuard, MetricsLog
from fastenerf.run import load_checkpoint
from fastenerf.step_stats import STATS_FLUSH_EVERY
from fastenerf.train import Trainer
from tests.same_steps import assert_same_losses, assert_same_tensor
from tests.test_train import NGP_TINY, tiny_cfg


@pytest.fixture(scope="module")
def scene(tiny_scene):
    return load_scene(tiny_scene)


def make(scene, path, mode: str, backend: str = "ngp", **kw) -> Trainer:
    trainer = Trainer(scene, tiny_cfg(backend, step_mode="device", **kw), path)
    assert trainer.set_step_mode(mode) == mode
    return trainer


def weights(trainer: Trainer) -> dict[str, torch.Tensor]:
    return {k: p.detach().clone() for k, p in trainer.field.named_parameters()}


# hidden cells carved from the third step on (an opaque start, so some samples are hidden)
CARVED = {"carve_hidden": True, "carve_min_hits": 1, "update_every": 2, "warmup_steps": 0}
CARVED["density_bias"] = 3.0


@pytest.mark.parametrize("backend", ["ngp", "vanilla", "ngp-compacted", "ngp-carved"])
def test_device_path_takes_the_plain_paths_steps(scene, tmp_path, backend):
    kw, carved = {}, backend == "ngp-carved"
    if backend.startswith("ngp-"):  # compacted samples (early_stop_eps) in their own buffer
        more = CARVED if carved else {}  # and hidden cells carved
        opts = {**NGP_TINY, "early_stop_eps": 1e-4, **more}
        backend, kw = "ngp", {"backend_options": opts}
    # one after the other: each trainer seeds the global generator (ray jitter) when built
    plain = make(scene, tmp_path / "plain", "plain", backend, steps=5, **kw)
    a = [plain.step()["loss"] for _ in range(5)]
    device = make(scene, tmp_path / "device", "device", backend, steps=5, **kw)
    b = [device.step()["loss"] for _ in range(5)]
    assert torch.is_tensor(b[-1])  # still on the device until flushed
    device.flush_stats()
    b = [s["loss"] for s in device.history]
    assert_same_losses(a, b)
    if kw:  # the field ran on fewer samples than were marched, and the stats say so
        for h in (plain.history[-1], device.history[-1]):
            assert 0 < h["samples_per_ray"] < h["marched_per_ray"]
        assert device.field.pruned_capacity is not None
        hidden = device.field.sampler.hidden
        assert (hidden is not None and bool(hidden.carved.any())) == carved
    wa, wb = weights(plain), weights(device)
    for k in wa:
        assert_same_tensor(wa[k], wb[k], k)


@pytest.mark.parametrize("mode", ["plain", "device"])
def test_the_single_pass_march_trains_the_two_passes_steps(scene, tmp_path, mode, monkeypatch):
    """`MarcherOptions.single_pass` marches once: the same samples, so the same steps, on the
    exactly sized buffers (plain) and the fixed-capacity ones (device); recorded in the run's
    config."""
    from fastenerf.kernels import march_scratch as ms

    strides, stride_of = [], ms.scratch_stride
    monkeypatch.setattr(
        ms, "scratch_stride", lambda *a: strides.append(stride_of(*a)) or strides[-1]
    )
    runs = []
    for single in (False, True):
        opts = {**NGP_TINY, "single_pass": single}
        t = make(scene, tmp_path / f"s{single}", mode, "ngp", steps=4, backend_options=opts)
        strides.clear()
        losses = [t.step()["loss"] for _ in range(4)]
        t.flush_stats()
        runs.append([float(s["loss"]) for s in t.history] if mode == "device" else losses)
        assert strides and all((x > 0) == single for x in strides)  # the march it asked for
    assert runs[0] == runs[1] and all(math.isfinite(x) for x in runs[0])
    config = json.loads((tmp_path / "sTrue" / "config.json").read_text())
    assert '"single_pass": true' in json.dumps(config)


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


def test_an_overflowing_sample_buffer_drops_whole_pixels_and_says_so(scene, tmp_path):
    """No silent truncation: rays that did not fit are flagged, their pixels leave the loss,
    the rest render exactly as with exactly sized buffers, and the share is reported."""
    from fastenerf.losses import total_loss

    trainer = make(scene, tmp_path / "run", "device", steps=3)
    for _ in range(2):
        trainer.step()
    field, batch = trainer.field, trainer.sampler.sample()
    kw = dict(near=scene.config.near, background=trainer.background, train=True)
    field.use_fixed_capacity(False)
    torch.manual_seed(5)
    exact = field.render(batch.rays_o, batch.rays_d, **kw)
    field.use_fixed_capacity(True)
    torch.manual_seed(5)
    field.render(batch.rays_o, batch.rays_d, **kw)  # sizes the buffers from this batch
    field.sample_capacity.capacity = exact["n_samples"] // 2
    torch.manual_seed(5)
    fixed = field.render(batch.rays_o, batch.rays_d, **kw)
    valid = fixed["valid"]
    assert 0 < int(valid.sum()) < len(valid)
    assert int(fixed["n_samples"]) <= exact["n_samples"] // 2
    assert torch.allclose(fixed["rgb"][valid], exact["rgb"][valid], atol=1e-6)
    b = batch.target.shape[0]
    loss, parts = total_loss(fixed, batch.target, batch.channel, gamma=2.2, eps=0.1)
    keep = valid[:b] & valid[b:]
    ref, _ = total_loss(
        {"rgb": torch.cat([exact["rgb"][:b][keep], exact["rgb"][b:][keep]])},
        batch.target[keep],
        None if batch.channel is None else batch.channel[keep],
        gamma=2.2,
        eps=0.1,
    )
    assert float(loss.detach()) == pytest.approx(float(ref.detach()), rel=1e-5)
    assert float(parts["dropped"]) == pytest.approx(1 - float(keep.float().mean()))
    # the trainer reports the share, and the capacity grows to what was wanted
    field.sample_capacity.capacity = exact["n_samples"] // 2
    field.sampler._capacity_cone = field.options.marcher.cone_angle
    stats = trainer.step()
    trainer.flush_stats()
    assert stats["dropped"] > 0
    for _ in range(2):  # the copy of the want started at one refresh is applied at the next
        field.sample_capacity.refresh()
    assert field.sample_capacity.capacity >= exact["n_samples"] // 2


def test_sample_capacity_follows_the_want_with_headroom():
    from fastenerf.fields.capacity import SampleCapacity

    cap = SampleCapacity(quantum=100, headroom=1.25, shrink_below=0.6)
    cap.reset(1000)
    assert cap.capacity == 1300  # 1250 rounded up to the quantum
    # a refresh applies the maximum observed before the previous refresh (its copy has
    # arrived by then) and starts copying the one since
    expected = [(2000, 1300), (1600, 2500), (100, 2500), (100, 200)]
    for want, capacity in expected:
        cap.observe(torch.tensor([want // 2], dtype=torch.int32))
        cap.observe(torch.tensor([want], dtype=torch.int32))
        cap.refresh()
        assert cap.capacity == capacity, (want, cap.capacity)


def test_sample_capacity_does_not_flap_on_a_want_at_a_quantums_edge():
    """A want that wobbles across the edge of a quantum (here 900 / 1.1 = 818 samples) keeps
    its capacity: a shrink must save two quanta, so growing back needs the want to rise a
    whole quantum (each change recaptures the training step's graph). A real fall of the
    want still shrinks it."""
    from fastenerf.fields.capacity import SampleCapacity

    cap = SampleCapacity(quantum=100, headroom=1.1, shrink_below=0.85)
    seen = []
    for want in [825, 810] * 10 + [500, 500, 500]:
        cap.observe(torch.tensor([want], dtype=torch.int32))
        cap.refresh()
        seen.append(cap.capacity)
    assert seen[1:20] == [1000] * 19  # without the two-quanta rule: 900, 1000, 900, ...
    assert seen[-1] == 600


def test_sample_capacity_with_patience_does_not_flap_on_one_low_reading_among_high_ones():
    """A reading is the maximum want of one occupancy update's steps; batches differ, so one
    reading in a few can be low. With `shrink_patience` k a shrink waits for k low readings
    in a row (then goes to the largest of them); at 1, each lone low one (900 -> 700 saves
    two quanta) shrinks the buffer and the next high one grows it back, a graph recapture
    each way. A want that stays low still shrinks it, k - 1 updates later."""
    from fastenerf.fields.capacity import SampleCapacity

    wants = [900, 900] + [700, 900, 900] * 10 + [500] * 5

    def capacities(patience: int) -> list[int]:
        cap = SampleCapacity(quantum=100, headroom=1.1, shrink_below=0.85, shrink_patience=patience)
        seen = []
        for want in wants:
            cap.observe(torch.tensor([want], dtype=torch.int32))
            cap.refresh()
            seen.append(cap.capacity)
        return seen

    flapping = capacities(1)
    assert flapping[1:32].count(800) == 10  # 1000, 800, 1000, 1000, 800, ...
    patient = capacities(3)
    assert patient[1:32] == [1000] * 31
    assert flapping[-4:] == [600] * 4  # the third 500 read shrinks it
    assert patient[-4:] == [1000, 1000, 600, 600]  # two reads later


@pytest.mark.parametrize("backend", ["ngp", "vanilla"])
def test_a_non_finite_ray_skips_the_step_without_a_host_check(scene, tmp_path, backend):
    """Training renders do not read the rays on the host (a sync per step): a NaN ray makes
    its pixel NaN instead, so the loss is NaN and the guard skips the update."""
    trainer = make(scene, tmp_path / "run", "device", backend, steps=3)
    before = weights(trainer)
    sample = trainer.sampler.sample

    def poisoned():
        batch = sample()
        batch.rays_o[3] = float("nan")
        batch.rays_d[5, 1] = float("inf")
        return batch

    trainer.sampler.sample = poisoned
    stats = trainer.step()
    trainer.flush_stats()
    assert math.isnan(stats["loss"]) and trainer.skipped_steps == 1
    after = weights(trainer)
    assert all(torch.equal(before[k], after[k]) for k in before)
    # outside training the rays are still checked, with one clear line
    from fastenerf.errors import InputError

    bad = torch.full((2, 3), float("nan"))
    with pytest.raises(InputError, match="NaN or inf"):
        trainer.field.render(bad, bad, near=0.0, background=None, train=False)


def test_self_calibration_on_the_device_path(scene, tmp_path):
    """Pose refinement and threshold estimation step with the device-paced trainer; their
    estimates reach the history at the flush steps, as floats."""
    trainer = make(
        scene, tmp_path / "run", "device", steps=20, refine_poses=True, estimate_threshold=True
    )
    summary = trainer.run([])
    assert summary["steps"] == 20 and summary["failure"] is None
    with_cal = [s for s in trainer.history if "pose_correction_deg" in s]
    assert with_cal and len(with_cal) < len(trainer.history)
    for s in trainer.history:
        assert all(not torch.is_tensor(v) for v in s.values())
        assert math.isfinite(s["loss"])


def calibration(trainer: Trainer) -> dict[str, torch.Tensor]:
    sc = trainer.selfcal
    return {
        "delta": sc.poses.delta.detach().clone(),
        **{k: v.detach().clone() for k, v in sc.thresholds.state_dict().items()},
    }


SELFCAL = dict(refine_poses=True, estimate_threshold=True, refine_start=0.0, steps=6)


def test_device_path_takes_the_plain_paths_calibration_steps(scene, tmp_path):
    plain = make(scene, tmp_path / "plain", "plain", **SELFCAL)
    a = [plain.step()["loss"] for _ in range(6)]
    device = make(scene, tmp_path / "device", "device", **SELFCAL)
    for _ in range(6):
        device.step()
    device.flush_stats()
    assert_same_losses(a, [s["loss"] for s in device.history])
    ca, cb = calibration(plain), calibration(device)
    assert not torch.equal(ca["delta"], torch.zeros_like(ca["delta"]))  # the poses moved
    for k in ca:
        assert_same_tensor(ca[k], cb[k], k)


def test_device_path_skips_a_non_finite_calibration_gradient(scene, tmp_path):
    """A NaN reaching only the pose corrections' gradient skips the whole step on the device:
    field, poses and thresholds keep their values (no host check ran)."""
    trainer = make(scene, tmp_path / "run", "device", **SELFCAL)
    trainer.step()
    forward = trainer._forward

    def nan_pose_grad(batch):
        out, loss, parts = forward(batch)
        return out, loss + torch.sqrt(trainer.selfcal.poses.delta.sum() * 0.0), parts

    trainer._forward = nan_pose_grad
    before, cal = weights(trainer), calibration(trainer)
    trainer.step()
    trainer.flush_stats()
    assert trainer.skipped_steps == 1 and trainer.selfcal.skipped_steps == 0
    after, cal_after = weights(trainer), calibration(trainer)
    assert all(torch.equal(before[k], after[k]) for k in before)
    assert all(torch.equal(cal[k], cal_after[k]) for k in cal)


def test_the_wait_in_a_stats_flush_is_training_time(scene, tmp_path):
    """A flush's copy waits for the steps the device still has queued; that wait is the steps'
    time, so the training clock (budgets, error-vs-time) must count it."""
    import time

    trainer = make(scene, tmp_path / "run", "device", steps=4)
    for _ in range(2):
        trainer.step()
    flush = trainer.pending.flush

    def slow_flush(extra=None):  # as a GPU would: the copy returns when the queue has run
        time.sleep(0.2)
        return flush(extra)

    trainer.pending.flush = slow_flush
    before = trainer.train_seconds
    trainer.flush_stats()
    assert trainer.train_seconds - before >= 0.2


def test_settling_the_clock_twice_adds_nothing(scene, tmp_path):
    """Once the queue is drained (a settle, a flush, or a CPU step), another settle has
    nothing to wait for and must not charge its own call to the training clock: a curve
    point and the checkpoint written after its evaluation then agree on the time."""
    trainer = make(scene, tmp_path / "run", "device", steps=4)
    trainer.step()
    trainer.flush_stats()
    before = trainer.train_seconds
    for _ in range(3):
        trainer.settle_clock()
    assert trainer.train_seconds == before


def test_pending_stats_rotate_reads_each_copy_one_flush_later():
    """The trainer's own flushes start a copy and take it at the next one (on CUDA it has
    long arrived by then); an explicit flush takes the copy in flight and the rest at once."""
    from fastenerf.device_step import PendingStats

    p = PendingStats()
    first = [{"loss": torch.tensor(float(i))} for i in range(3)]
    for d in first:
        p.add(d)
    assert p.rotate([torch.tensor(7.0)]) is None and p.in_flight and len(p) == 0
    second = {"loss": torch.tensor(5.0), "step": 4}
    p.add(second)
    done, extra = p.rotate([torch.tensor(8.0)])
    assert done == first and [d["loss"] for d in done] == [0.0, 1.0, 2.0] and extra == [7.0]
    assert torch.is_tensor(second["loss"])  # its copy is in flight now
    p.add({"loss": torch.tensor(6.0)})
    done, extra = p.flush([torch.tensor(9.0)])
    assert [d["loss"] for d in done] == [5.0, 6.0] and extra == [9.0] and not p.in_flight
