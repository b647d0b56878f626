"""The contrast-threshold ratio counted over a recording's closed loop (issue #20)."""

from __future__ import annotations

import json
import math
import os

import numpy as np
import pytest
import torch

from fastenerf.cli import main as cli_main
from fastenerf.data.formats.native import load_scene
from fastenerf.data.loop_ratio import loop_span, scene_loop_ratio
from fastenerf.errors import InputError
from fastenerf.threshold import ThresholdEstimator


@pytest.fixture(scope="module")
def uneven(tmp_path_factory):
    """The default scene at 32x24, one 60-frame turn, simulated with C+ 0.15, C- 0.25."""
    from fastenerf.data.synth import DEFAULT_SCENE
    from fastenerf.data.synth.make import make_scene_result, resolve_scene
    from fastenerf.data.synth.simulator import SimulatorConfig

    out = tmp_path_factory.mktemp("uneven") / "scene"
    sim = SimulatorConfig(pos_threshold=0.15, neg_threshold=0.25, mismatch=0.03)
    make_scene_result(resolve_scene(DEFAULT_SCENE), out, width=32, height=24, frames=60, sim=sim)
    return out


def test_loop_ratio_counts_the_true_ratio_over_one_turn(uneven):
    """Over a whole turn every pixel's events cancel: N-/N+ is C+/C- (0.6) to a few %, with
    no field and no training; the span is the recording's turn."""
    scene = load_scene(uneven)
    loop = scene_loop_ratio(scene)
    assert loop.ratio == pytest.approx(0.6, rel=0.1), loop
    assert (loop.t0_us, loop.t1_us) == (scene.config.t_start_us, scene.config.t_end_us)
    assert "C+ = " in loop.summary(0.25) and loop.n_pos > loop.n_neg > 0


def test_loop_ratio_refuses_a_path_that_does_not_close(uneven, tmp_path):
    """Half a turn: the camera never comes back, a one-line InputError; `auto` then learns."""
    from fastenerf.config import TrainConfig
    from fastenerf.self_calibration import measured_ratio

    half = tmp_path / "half"
    half.mkdir()
    for f in uneven.iterdir():
        if f.name != "scene.json":
            (half / f.name).symlink_to(f)
    cfg = json.loads((uneven / "scene.json").read_text())
    cfg["t_end_us"] = cfg["t_start_us"] + (cfg["t_end_us"] - cfg["t_start_us"]) // 2
    cfg["loop"] = False
    (half / "scene.json").write_text(json.dumps(cfg))
    scene = load_scene(half)
    assert loop_span(scene.rig(), cfg["t_start_us"], cfg["t_end_us"]) is None
    with pytest.raises(InputError, match="never returns") as err:
        scene_loop_ratio(scene)
    assert "\n" not in str(err.value)
    auto = TrainConfig(estimate_threshold=True)
    assert measured_ratio(scene, auto) is None  # learnt instead
    with pytest.raises(InputError):
        measured_ratio(scene, TrainConfig(estimate_threshold=True, threshold_ratio="loop"))
    assert measured_ratio(load_scene(uneven), auto) == pytest.approx(0.6, rel=0.1)
    # on its own, from the command line: one line and exit 2, nothing written
    out = tmp_path / "ratio.json"
    assert cli_main(["calibrate", "--threshold-ratio", str(half), "--out", str(out)]) == 2
    assert not out.exists()
    assert cli_main(["calibrate", "--threshold-ratio", str(uneven), "--out", str(out)]) == 0
    assert json.loads(out.read_text())["ratio"] == pytest.approx(0.6, rel=0.1)
    # its own file is replaced; a path that is something else, or cannot be written, is not
    assert cli_main(["calibrate", "--threshold-ratio", str(uneven), "--out", str(out)]) == 0
    notes = tmp_path / "notes.json"
    notes.write_text('{"mine": 1}')
    assert cli_main(["calibrate", "--threshold-ratio", str(uneven), "--out", str(notes)]) == 2
    assert notes.read_text() == '{"mine": 1}'
    ro = tmp_path / "ro"
    ro.mkdir(mode=0o500)
    if not os.access(ro, os.W_OK):  # root writes anywhere
        assert (
            cli_main(["calibrate", "--threshold-ratio", str(uneven), "--out", str(ro / "r.json")])
            == 2
        )
    # a training run asked for the loop on a path that does not close: one line, no run made
    run = tmp_path / "run"
    args = ["train", str(half), "--out", str(run), "--steps", "2", "--device", "cpu"]
    assert cli_main(args + ["--estimate-threshold", "--threshold-ratio", "loop"]) == 2
    assert not run.exists()
    with pytest.raises(SystemExit) as bad:  # argparse's own one line
        cli_main(args + ["--threshold-ratio", "sometimes"])
    assert bad.value.code == 2 and not run.exists()


def test_a_measured_ratio_is_set_and_kept_with_the_product():
    """The estimator starts at the measured ratio, keeps C+·C- at the start's, learns no ratio
    (no gradient reaches it), and refuses a ratio that is not a positive number."""
    est = ThresholdEstimator(0.25, 0.25, 10, ratio=0.6)
    c = est.thresholds()
    assert float(c[0] / c[1]) == pytest.approx(0.6, rel=1e-6)
    assert float(c[0] * c[1]) == pytest.approx(0.0625, rel=1e-6)
    assert not est.log_ratio.requires_grad
    assert "sign" not in est.state_dict()  # a constant: checkpoints from before it still load
    assert [p for p in est.parameters() if p.requires_grad] == []
    parts = torch.tensor([[1.0, 0.0], [0.0, -1.0]])
    assert torch.isfinite(est.target(parts, torch.tensor([0, 1]))).all()
    for bad in (0.0, -1.0, math.inf, float("nan")):
        with pytest.raises(InputError, match="measured ratio"):
            ThresholdEstimator(0.25, 0.25, 10, ratio=bad)
    assert np.isclose(ThresholdEstimator(0.25, 0.25, 10).log_ratio.item(), 0.0)


def test_training_uses_the_loop_ratio_and_records_it(uneven, tmp_path):
    """--estimate-threshold on a closed loop: the run trains with the counted ratio (not
    learnt: it ends where it started) and config.json records it and what was learnt."""
    from fastenerf.train import Trainer
    from tests.test_train import tiny_cfg

    cfg = tiny_cfg("ngp", steps=3, estimate_threshold=True)
    trainer = Trainer(load_scene(uneven), cfg, tmp_path / "run")
    trainer.run(hooks=[])
    rec = json.loads((tmp_path / "run" / "config.json").read_text())["self_calibration"]
    th = rec["thresholds"]
    assert th["measured_ratio"] == pytest.approx(0.6, rel=0.1)
    assert th["estimate"]["ratio"] == pytest.approx(th["measured_ratio"], rel=1e-5)
    assert th["learnt"].startswith("nothing")


def test_a_measured_ratio_step_has_nothing_a_cuda_graph_cannot_capture(
    uneven, tmp_path, monkeypatch
):
    """What broke the capture on the GPU, checked on the CPU: the thresholds made a tensor from
    host values per call (a copy from the host), and the empty placeholder Adam stepped (torch
    refuses to capture an unfused, non-capturable step)."""
    from fastenerf.train import Trainer
    from tests.test_train import tiny_cfg

    trainer = Trainer(
        load_scene(uneven), tiny_cfg("ngp", steps=2, estimate_threshold=True), tmp_path / "run"
    )
    sc = trainer.selfcal
    assert sc.static

    def refuse(*a, **k):
        raise AssertionError("not capturable")

    monkeypatch.setattr(torch.Tensor, "new_tensor", refuse)
    monkeypatch.setattr(sc.optimizer, "step", refuse)
    sc.thresholds.thresholds()
    assert sc.step(found_inf=torch.zeros(()))
