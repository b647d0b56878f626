"""The training loop's hooks: divergence guard, step-based checkpoints, scheduled evaluation."""

from __future__ import annotations

import json
import math

import pytest
import torch

from fastenerf.cli import main as cli_main
from fastenerf.data.formats.native import load_scene
from fastenerf.hooks import Checkpointer, DivergenceGuard, Hook, ScheduledEval
from fastenerf.run import load_checkpoint, read_progress
from fastenerf.train import Trainer
from tests.test_train import HAVE_NGP, NGP_TINY, tiny_cfg


@pytest.fixture(scope="module")
def scene(tiny_scene):
    return load_scene(tiny_scene)


def poison_after(trainer: Trainer, good_steps: int) -> None:
    """From step `good_steps` on, the loss is NaN (as a run whose weights blew up)."""
    forward = trainer._forward

    def nan_forward(batch):
        out, loss, parts = forward(batch)
        if trainer.step_count >= good_steps:
            loss = loss * float("nan")
        return out, loss, parts

    trainer._forward = nan_forward


def test_divergence_guard_stops_and_keeps_the_last_good_checkpoint(scene, tmp_path):
    trainer = Trainer(scene, tiny_cfg(steps=200), tmp_path / "run")
    poison_after(trainer, 3)
    hooks = [DivergenceGuard(patience=5), Checkpointer(every_s=0, every_steps=1)]
    summary = trainer.run(hooks)
    # without the guard the run would go on to its 200 steps
    assert summary["failure"] and "diverged" in summary["failure"]
    assert summary["steps"] == 3 + 5 and "\n" not in summary["failure"]
    ck = load_checkpoint(tmp_path / "run" / "checkpoint.pt")
    assert ck["step"] == 3  # no checkpoint of a non-finite step, none at the end
    weights = {k: v for k, v in trainer.field.state_dict().items()}
    for k, v in ck["field"].items():  # the NaN steps never reached the weights
        assert torch.equal(v, weights[k].cpu()), k
    assert not read_progress(tmp_path / "run")["finished"]


def test_train_command_reports_divergence_in_one_line(tiny_scene, tmp_path, capsys, monkeypatch):
    """`fastenerf train` turns the guard's stop into exit 2 and one line."""
    forward = Trainer._forward

    def nan_forward(self, batch):
        out, loss, parts = forward(self, batch)
        return out, (loss * float("nan") if self.step_count >= 2 else loss), parts

    monkeypatch.setattr(Trainer, "_forward", nan_forward)
    argv = ["train", str(tiny_scene), "--out", str(tmp_path / "r"), "--backend", "vanilla"]
    argv += ["--device", "cpu", "--rays", "32", "--steps", "100", "--no-progress"]
    code = cli_main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "diverged" in err[0], err
    assert read_progress(tmp_path / "r").get("step", 0) < 100


def test_checkpoints_by_steps(scene, tmp_path):
    seen = []

    class Watch(Hook):
        def before_checkpoint(self, trainer):
            seen.append(trainer.step_count)

    trainer = Trainer(scene, tiny_cfg(steps=7), tmp_path / "run")
    trainer.run([Watch(), Checkpointer(every_s=0, every_steps=3)])
    assert seen == [3, 6, 7]  # every 3 steps, then the end
    assert read_progress(tmp_path / "run")["finished"]


def test_scheduled_eval_takes_points_and_stops(scene, tmp_path):
    from fastenerf.evaluate import make_eval_set

    ev = make_eval_set(scene, 2, 0.25)
    points = []
    trainer = Trainer(scene, tiny_cfg(steps=1000), tmp_path / "run")
    sched = ScheduledEval(ev, [1e-9, 2e-9], points.append)
    summary = trainer.run([sched])
    assert [p["target_s"] for p in points] == [1e-9, 2e-9] or len(points) == 1
    assert sched.finished and summary["steps"] <= 2 and summary["interrupted"]
    assert all(p["psnr"] > 0 and p["step"] >= 1 for p in points)
    prog = json.loads((tmp_path / "run" / "progress.json").read_text())
    assert prog["step"] == summary["steps"]


def test_scheduled_eval_points_carry_the_learnt_calibration(scene, tmp_path):
    """With the poses and thresholds learnt, each point has their stats at that time (how
    they move over a run); without, none of those keys."""
    from fastenerf.evaluate import make_eval_set
    from fastenerf.hooks import CALIBRATION_KEYS

    ev = make_eval_set(scene, 1, 0.25)
    for learnt in (True, False):
        points = []
        cfg = tiny_cfg(steps=1000, refine_poses=learnt, estimate_threshold=learnt)
        trainer = Trainer(scene, cfg, tmp_path / f"run{learnt}")
        trainer.run([ScheduledEval(ev, [1e-9, 2e-9], points.append)])
        assert points
        for p in points:
            keys = {k for k in CALIBRATION_KEYS if k in p}
            want = {"pose_correction_deg", "pose_correction_max_deg", "threshold_pos"}
            assert want <= keys if learnt else not keys
            assert all(math.isfinite(p[k]) for k in keys)


@pytest.mark.skipif(not HAVE_NGP, reason="ngp backend not built")
def test_scheduled_eval_points_say_how_many_steps_compacted(scene, tmp_path):
    """Each point: the samples marched beside those the field ran on, the share of its
    steps that compacted (the GPU switches compaction on and off as it pays), and the slots
    of the fixed-capacity buffer the field trains on (the device step's; None when the
    plain step sizes buffers exactly), and the graphs captured so far."""
    from fastenerf.evaluate import make_eval_set

    ev = make_eval_set(scene, 1, 0.25)
    for eps, mode in ((1e-4, "plain"), (0.0, "plain"), (1e-4, "device"), (0.0, "device")):
        points = []
        opts = {**NGP_TINY, "early_stop_eps": eps, "density_bias": 3.0}  # opaque: rays stop
        cfg = tiny_cfg("ngp", steps=1000, backend_options=opts, step_mode=mode)
        trainer = Trainer(scene, cfg, tmp_path / f"run{eps}{mode}")
        assert trainer.step_mode == mode
        trainer.run([ScheduledEval(ev, [1e-9, 2e-9], points.append)])
        assert points
        for p in points:
            if eps:
                assert p["compacted_share"] == 1.0
                assert p["marched_per_step"] > p["samples_per_step"] > 0
            else:
                assert p["compacted_share"] == 0.0
                assert p["marched_per_step"] == pytest.approx(p["samples_per_step"])
            sampler = trainer.field.sampler
            assert p["graph_captures"] is None  # no graphed step off CUDA (test_graph_step)
            assert p["graph_returns"] is None
            assert p["compositing_share"] is None  # compaction fixed on or off: no switch
            if mode == "plain":
                assert p["trained_slots"] is None and p["capacity_readings"] is None
            else:  # the compacted buffer while compacting, else the marched one
                cap = sampler.pruned_capacity if eps else sampler.sample_capacity
                assert p["trained_slots"] == cap.capacity >= p["samples_per_step"] > 0


@pytest.mark.skipif(not HAVE_NGP, reason="ngp backend not built")
def test_scheduled_eval_points_carry_the_compaction_switchs_share(scene, tmp_path):
    """With compaction_auto, a point carries the share of marched samples compositing used,
    as the switch last read it (None until its first reading: one refresh late)."""
    from fastenerf.evaluate import make_eval_set

    ev = make_eval_set(scene, 1, 0.25)
    points = []
    opts = {**NGP_TINY, "early_stop_eps": 1e-4, "compaction_auto": True, "update_every": 1}
    cfg = tiny_cfg("ngp", steps=1000, backend_options=opts)
    trainer = Trainer(scene, cfg, tmp_path / "run")
    trainer.run([ScheduledEval(ev, [1e-9], points.append)])  # a point at the first step
    for _ in range(3):  # a refresh per step: the sums copied at one are read at the next
        trainer.step()
    trainer.flush_stats()
    trainer.run([ScheduledEval(ev, [trainer.train_seconds + 1e-9], points.append)])
    shares = [p["compositing_share"] for p in points]
    assert len(shares) == 2 and shares[0] is None and 0.0 < shares[1] <= 1.0
    assert shares[1] == trainer.field.sampler.compaction.share


@pytest.mark.skipif(not HAVE_NGP, reason="ngp backend not built")
def test_scheduled_eval_points_carry_the_capacity_readings_since_the_last(scene, tmp_path):
    """With the device step, a point carries the marched buffer's readings since the point
    before (each the most a march wanted between two occupancy updates, read one update
    late), oldest first: each reading of the run is in exactly one point."""
    from fastenerf.evaluate import make_eval_set

    ev = make_eval_set(scene, 1, 0.25)
    points, seen = [], []
    opts = {**NGP_TINY, "update_every": 1}
    cfg = tiny_cfg("ngp", steps=1000, backend_options=opts, step_mode="device")
    trainer = Trainer(scene, cfg, tmp_path / "run")
    cap = trainer.field.sampler.sample_capacity
    apply = cap.apply

    def watch(wanted: int) -> None:
        seen.append(wanted)
        apply(wanted)

    cap.apply = watch
    trainer.run([ScheduledEval(ev, [1e-9], points.append)])
    for _ in range(4):  # a refresh per step: the maximum copied at one is read at the next
        trainer.step()
    trainer.flush_stats()
    trainer.run([ScheduledEval(ev, [trainer.train_seconds + 1e-9], points.append)])
    readings = [p["capacity_readings"] for p in points]
    assert len(readings) == 2 and len(readings[1]) >= 3
    assert readings[0] + readings[1] == seen and all(w > 0 for w in seen)
    assert cap.take_readings() == []  # taken by the points


class _ClockJump(Hook):
    """After step `at`, the clock jumps past the budget, as a checkpoint's settle of queued
    device-paced steps does between ScheduledEval's check and the loop's `done()`."""

    def __init__(self, at: int):
        self.at = at

    def after_step(self, trainer: Trainer, stats) -> None:
        if trainer.step_count == self.at:
            trainer.train_seconds += 3600.0


def test_scheduled_eval_takes_the_last_point_when_the_budget_ends_between_checks(scene, tmp_path):
    """The last target's point is taken at the end, not lost; a run that resumes after its
    budget without that point (interrupted while taking it) takes it, and only it."""
    from fastenerf.evaluate import make_eval_set

    ev = make_eval_set(scene, 2, 0.25)
    cfg = tiny_cfg(steps=None, minutes=30.0)  # a 1800 s budget the jump passes
    points = []
    trainer = Trainer(scene, cfg, tmp_path / "run")
    sched = ScheduledEval(ev, [1200.0, 1800.0], points.append)
    summary = trainer.run([sched, _ClockJump(at=3)])
    assert [p["target_s"] for p in points] == [1800.0]  # 1200 passed in the same jump
    assert sched.finished and summary["steps"] == 3 and not summary["interrupted"]
    assert summary["last_eval_psnr"] == points[0]["psnr"] > 0
    # the point lost: a resume past the budget takes it without a step
    again = []
    trainer = Trainer(scene, cfg, tmp_path / "run", resume=True)
    sched = ScheduledEval(ev, [1200.0, 1800.0], again.append)
    summary = trainer.run([sched])
    assert [p["target_s"] for p in again] == [1800.0] and summary["steps"] == 3
    assert again[0]["step"] == 3 and sched.finished
