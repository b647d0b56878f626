"""samples_per_step (#17, DESIGN §4): the pixels per step follow a target of samples per step,
decided where the sampler draws a block, from stats a fixed number of blocks back, so a run
and its resume take the same sizes."""

from __future__ import annotations

import json

import pytest
import torch

from fastenerf import batch_size as bs
from fastenerf import train as train_mod
from fastenerf.batch_size import HYSTERESIS, BatchSize, lag_blocks, pixels_for
from fastenerf.data.formats.native import load_scene
from fastenerf.errors import InputError
from fastenerf.train import Trainer
from tests.test_train import tiny_cfg


def test_pixels_for_rounds_to_the_quantum_within_the_bounds():
    q = bs.QUANTUM
    assert pixels_for(256 * 1024, 64.0, q, 8 * q) == 2 * q  # 256 k / (2 x 64) = 2,048
    assert pixels_for(256 * 1024, 50.0, q, 8 * q) == 3 * q  # 2,621 -> 3,072
    assert pixels_for(256 * 1024, 1.0, q, 8 * q) == 8 * q  # few samples: the most pixels
    assert pixels_for(256 * 1024, 1e4, q, 8 * q) == q  # fog: the fewest
    assert pixels_for(256 * 1024, 0.0, q, 8 * q) == 8 * q  # no samples at all: no division
    # the device path's stats reach the host two flushes late: 2 x 16 steps over blocks of 16
    assert lag_blocks(16, 16) == 4 and lag_blocks(8, 16) == 6


def test_batch_size_reads_the_block_lag_back_and_keeps_a_size_within_the_hysteresis():
    """A decision reads only the block LAG back (older ones are dropped, newer ones kept for
    later decisions); no data or a size within HYSTERESIS keeps the current one; the sums
    survive a state round trip."""
    q = bs.QUANTUM
    b = BatchSize(256 * 1024, q, 8 * q, block=4, lag=2)
    steps = [{"step": s, "samples_per_ray": 64.0} for s in range(1, 9)]  # blocks 0, 1
    steps += [{"step": s, "samples_per_ray": 16.0} for s in range(9, 13)]  # block 2
    steps += [{"step": 13, "samples_per_ray": float("nan")}, {"step": 14}]  # no count: skipped
    b.observe(steps)
    assert b.decide(4, 8 * q) is None  # block 1 is sized from block -1: nothing yet
    assert b.decide(8, 8 * q) == 2 * q  # block 2 from block 0: 64 per ray
    again = BatchSize(256 * 1024, q, 8 * q, block=4, lag=2)
    again.load_state_dict(json.loads(json.dumps(b.state_dict())))
    assert again.sums == b.sums and set(b.sums) == {0, 1, 2}
    assert b.decide(12, 2 * q) is None  # block 3 from block 1: 2 x q again
    assert set(b.sums) == {1, 2}  # older than the block read: never needed again
    assert b.decide(16, 2 * q) == 8 * q  # block 4 from block 2: 16 per ray -> the most
    # within the hysteresis: 2,048 wanted, 2,048 x (1 + HYSTERESIS) drawn now -> kept
    c = BatchSize(256 * 1024, q, 8 * q, block=4, lag=1)
    c.observe({"step": s, "samples_per_ray": 64.0} for s in range(1, 5))
    assert c.decide(4, int(2 * q * (1 + HYSTERESIS))) is None
    with pytest.raises(ValueError):
        BatchSize(1, 10, 5, 4, 1)


@pytest.fixture(scope="module")
def scene(tiny_scene):
    return load_scene(tiny_scene)


def small_quantum(monkeypatch):
    """A CPU-sized quantum and a one-block lag (the plain path's stats are on the host at
    once), so the size moves within a few steps of a tiny run."""
    monkeypatch.setattr(bs, "QUANTUM", 16)
    monkeypatch.setattr(train_mod, "QUANTUM", 16)
    monkeypatch.setattr(train_mod, "lag_blocks", lambda block, flush: 1)


def test_a_run_with_a_sample_target_resizes_at_block_starts_and_resumes_exactly(
    scene, tmp_path, monkeypatch
):
    """ngp on the CPU, 256 pixels a step at first: the target asks for far fewer, so from the
    second block (the sampler draws 16 steps at once) each step renders fewer rays, every step
    of a block as many; a run checkpointed mid-block after the change resumes bit for bit."""
    small_quantum(monkeypatch)
    kw = dict(steps=40, rays_per_step=256, windows_per_step=4, samples_per_step=2048)
    tr = Trainer(scene, tiny_cfg("ngp", **kw), tmp_path / "whole")
    tr.run(progress=False)
    rays = [h["rays"] for h in tr.history]
    assert rays[:16] == [512] * 16  # the first block: rays_per_step, two rays a pixel
    assert rays[16] < 512 and len(set(rays[16:32])) == 1  # resized where a block starts
    assert all(r % (2 * 16) == 0 and r >= 32 for r in rays)  # whole quanta, at least one
    part = Trainer(scene, tiny_cfg("ngp", **kw), tmp_path / "part")
    for _ in range(21):  # past the change, inside the second block
        part.step()
    part.save_checkpoint()
    del part
    resumed = Trainer(scene, tiny_cfg("ngp", **kw), tmp_path / "part", resume=True)
    resumed.run(progress=False)
    assert [h["rays"] for h in resumed.history][-19:] == rays[-19:]
    assert resumed.batch_size.sums == tr.batch_size.sums  # what the next decisions read
    a, b = dict(tr.field.named_parameters()), dict(resumed.field.named_parameters())
    assert a and all(torch.equal(a[k], b[k]) for k in a)


def test_eval_points_count_each_steps_own_rays(scene, tmp_path, monkeypatch):
    """A scheduled point's samples, marched samples and rays per step are the means over its
    steps of each step's own (a resized run's steps differ), not the config's rays_per_step."""
    from fastenerf.evaluate import make_eval_set
    from fastenerf.hooks import ScheduledEval

    small_quantum(monkeypatch)
    kw = dict(steps=40, rays_per_step=256, windows_per_step=4, samples_per_step=2048)
    tr = Trainer(scene, tiny_cfg("ngp", **kw), tmp_path / "r")
    points = []
    hook = ScheduledEval(make_eval_set(scene, 1, 0.25), [1e6], points.append)
    hook.on_start(tr)
    for _ in range(40):
        stats = tr.step()
        if tr.step_count == 40:  # the clock passes the point's time at the last step
            tr.train_seconds = 1e6
        hook.after_step(tr, stats)
    (p,) = points
    h = tr.history[-40:]
    assert h[0]["rays"] != h[-1]["rays"]
    assert p["rays_per_step"] == pytest.approx(sum(s["rays"] for s in h) / 40)
    want = sum(s["samples_per_ray"] * s["rays"] for s in h) / 40
    assert p["samples_per_step"] == pytest.approx(want)
    assert p["marched_per_step"] == pytest.approx(want)  # no compaction: the same samples


def test_without_a_target_the_pixels_stay_and_the_option_needs_ngp(scene, tmp_path):
    tr = Trainer(scene, tiny_cfg("ngp", steps=20, rays_per_step=64), tmp_path / "r")
    tr.run(progress=False)
    assert tr.batch_size is None and {h["rays"] for h in tr.history} == {128}
    with pytest.raises(InputError, match="'samples_per_step' needs the ngp backend"):
        tiny_cfg("vanilla", samples_per_step=4096).validate()
    with pytest.raises(InputError, match="samples_per_step"):
        tiny_cfg("ngp", samples_per_step=10).validate()
