"""`fastenerf bench study` (issue #15) on the CPU: the perturbations and knobs each level
trained with are what the level says (read back from the runs), the outputs exist and decode,
and a resumed study redoes nothing.

The runs train real ngp fields (Warp kernels) for one or two steps on the tiny scene, so the
PSNRs are meaningless; the tests check what each run was given and what was written.
"""

from __future__ import annotations

import json
import math

import imageio.v3 as iio
import numpy as np
import pytest

from fastenerf.cli import main as cli_main
from fastenerf.commands.bench import import_benchmark
from fastenerf.errors import InputError

import_benchmark("study")  # puts the repo's benchmarks/ on the path
from benchmarks import study_levels as lv  # noqa: E402

# Small fields and batches: a couple of steps a second on a 2-core CPU.
TINY = [
    "--set",
    "rays_per_step=32",
    "windows_per_step=4",
    "log2_table_size=12",
    "n_levels=4",
    "grid_resolution=32",
    "dt_min=0.02",
]
FAST = ["--device", "cpu", "--eval-views", "2", "--eval-scale", "0.125"]
FAST += ["--warmup-steps", "0", "--quiet", *TINY]


def study(name, scene, out, *extra):
    return cli_main(["bench", "study", name, str(scene), "--out", str(out), *FAST, *extra])


def run_config(out, slug) -> dict:
    return json.loads((out / "runs" / slug / "config.json").read_text())


def progress(out) -> dict[str, tuple]:
    """Each run folder's step and checkpoint / evaluation file times."""
    return {
        d.name: (
            json.loads((d / "progress.json").read_text())["step"],
            (d / "checkpoint.pt").stat().st_mtime_ns,
            (d / "study_eval.json").stat().st_mtime_ns,
        )
        for d in sorted((out / "runs").iterdir())
    }


def check_outputs(out, name: str) -> tuple[dict, str]:
    res = json.loads((out / f"{name}.json").read_text())
    for png in (f"{name}.png", f"{name}_grid.png"):
        img = iio.imread(out / png)
        assert img.ndim == 3 and img.shape[0] > 100 and img.shape[1] > 100
        assert img[..., :3].std() > 0  # not a blank canvas
    md = (out / f"{name}.md").read_text()
    assert res["complete"] and res["cpu_numbers"] and "CPU numbers" in md
    for r in res["levels"]:
        assert r["finished"] and math.isfinite(r["psnr"]) and -1 <= r["ssim"] <= 1
        assert r["psnr"] == pytest.approx(r["psnr_reloaded"])  # one evaluation path
        assert r["train_s"] > 0 and r["sessions"][0]["machine"].startswith("CPU:")
        tile = iio.imread(out / r["tile"])
        assert tile.shape == (6, 8, 3)  # the evaluation scale: 64x48 at 1/8
    return res, md


# The pose studies at 0° and 1°, one step each; the mount study refines its shared row back,
# after a motion prior that must keep the shared turn (the names continue FAST's --set).
ANGLE_EXTRA = {
    "pose-error": (),
    "mount-error": ("refine_poses=true", "refine_shared=true", "smooth_poses=21", "smooth_order=1"),
}


@pytest.fixture(scope="module")
def angle_studies(tiny_scene, tmp_path_factory):
    """name -> the OUT of that pose study, run once per module on first use."""
    done: dict = {}

    def get(name):
        if name not in done:
            out = tmp_path_factory.mktemp("study") / name
            extra = (*ANGLE_EXTRA[name], "--levels", "1", "0", "--steps", "1")
            assert study(name, tiny_scene, out, *extra) == 0
            done[name] = out
        return done[name]

    return get


@pytest.fixture(scope="module")
def pose_study(angle_studies):
    return angle_studies("pose-error")


@pytest.mark.parametrize("name", sorted(lv.POSE_STUDIES))
def test_pose_studies_apply_the_angle_they_report(angle_studies, name):
    out = angle_studies(name)
    spec = lv.STUDIES[name]
    res, md = check_outputs(out, name)
    rows = {r["level"]: r for r in res["levels"]}
    assert list(rows) == [0.0, 1.0]  # levels in ascending order
    assert rows[0.0]["measured"]["mean_deg"] == 0.0
    assert rows[0.0]["perturbation"][spec.report] is None
    m = rows[1.0]["measured"]
    assert abs(m["mean_deg"] - 1.0) < 1e-6 and abs(m["max_deg"] - 1.0) < 1e-6
    assert m["poses"] == 100  # every training pose of the 100-view loop, once
    # the JSON's number is the trainer's own measurement of the rig it trained with
    conf = run_config(out, f"{spec.slug}-1deg")
    assert conf["train"]["perturb"][spec.perturb] == 1.0
    assert conf["perturbation"][spec.report]["measured_mean_deg"] == m["mean_deg"]
    assert run_config(out, f"{spec.slug}-0deg")["perturbation"][spec.report] is None
    # the same clean test views score both levels
    assert res["break"]["largest_drop"]["from"] == 0.0 and res["break"]["largest_drop"]["to"] == 1
    assert "°" in md and f"| {name.replace('-', ' ')} | measured mean / max (°) |" in md
    if name == "pose-error":
        assert "27.43" in md and "18.11" in md and "between 0.1° and 1°" in md
        assert "| 1° | 1 / 1 | no refinement |" in md and "after the prior" not in md
        assert all(r["psnr_aligned"] is None for r in rows.values())  # nothing learnt
        assert "PSNR, aligned" not in md
        return
    # a refined level with true poses to compare with (a perturbed one) is also scored with
    # its test views turned by the learnt shared turn
    assert math.isfinite(rows[1.0]["psnr_aligned"])
    assert "PSNR, aligned |" in md and "BARF's protocol" in md
    # mount-error: one camera-frame axis, refined back with the shared row; no supplement
    assert len(m["axis"]) == 3 and abs(math.hypot(*m["axis"]) - 1.0) < 1e-9
    assert run_config(out, "mount-1deg")["perturbation"]["pose"] is None
    cal = rows[1.0]["self_calibration"]
    assert cal["knobs"]["refine_shared"] is True
    assert 0.0 <= cal["stats"]["pose_error_deg"] <= cal["stats"]["pose_error_max_deg"] < 2.0
    assert res["supplement"]["psnr"] == {} and res["supplement"]["break"] is None
    assert "no mount-error study" in md and "Supplement:" not in md
    assert "no refinement" not in md
    assert f"(jitter {cal['stats']['pose_jitter_deg']:.3f})" in md  # its pose-to-pose part
    # the prior's column: a turn shared by every pose is no jitter, so the prior keeps it all;
    # the exact poses of level 0 (a turntable) it leaves as they are
    assert "| measured mean / max (°) | after the prior mean (°) | after refinement" in md
    kept = rows[1.0]["pose_smoothing"]["error_after_deg"]
    assert abs(kept - 1.0) < 1e-3 and f"| 1° | 1 / 1 | {kept:.3f} |" in md
    assert rows[0.0]["pose_smoothing"]["mean_turn_deg"] < 1e-9 and "| 0° | 0 / 0 | 0.000 |" in md


def test_resumed_study_redoes_nothing_and_unfinished_levels_continue(pose_study, tiny_scene):
    before = progress(pose_study)
    args = ("--levels", "0", "1", "--steps", "1")
    assert study("pose-error", tiny_scene, pose_study, *args, "--resume") == 0
    assert progress(pose_study) == before
    # never overwrites, and refuses before training a new level
    assert study("pose-error", tiny_scene, pose_study, "--levels", "0.5", "1") == 2
    assert not (pose_study / "runs" / "pose-0.5deg").exists()
    # a larger budget: both levels continue from their checkpoints to the new one
    assert study("pose-error", tiny_scene, pose_study, *args[:3], "--steps", "2", "--resume") == 0
    after = progress(pose_study)
    assert {k: v[0] for k, v in after.items()} == {"pose-0deg": 2, "pose-1deg": 2}
    res = json.loads((pose_study / "pose-error.json").read_text())
    assert [len(r["sessions"]) for r in res["levels"]] == [2, 2]


def test_noise_study_adds_the_fraction_it_reports(tiny_scene, tmp_path):
    from fastenerf.data.formats import load_any

    out = tmp_path / "noise"
    assert study("noise", tiny_scene, out, "--levels", "0", "5", "--budget-s", "0.05") == 0
    res, md = check_outputs(out, "noise")
    rows = {r["level"]: r for r in res["levels"]}
    clean = len(load_any(tiny_scene).events)
    m = rows[5.0]["measured"]
    assert m["clean_events"] == clean
    assert abs(m["added_events"] - 0.05 * clean) <= 1  # within one event of F
    assert abs(m["fraction"] - 0.05) <= 1 / clean
    assert rows[0.0]["measured"]["added_events"] == 0
    assert run_config(out, "noise-5pct")["train"]["perturb"]["noise_fraction"] == 0.05
    # a time budget: evaluated in the loop at the budget (the last point)
    for r in res["levels"]:
        assert r["points"][-1]["target_s"] == 0.05 and r["points"][-1]["train_s"] >= 0.05
    assert "27.36" in md and "5.000 %" in md


def test_ablation_study_trains_each_variant_with_its_knobs(tiny_scene, tmp_path):
    out = tmp_path / "ablation"
    assert study("ablation", tiny_scene, out, "--steps", "1") == 0
    res, md = check_outputs(out, "ablation")
    assert [r["level"] for r in res["levels"]] == list(lv.STUDIES["ablation"].levels)
    want = {  # 100 views per loop: short 1 %, long 5 %; the full window is U{1..5}
        "full": (1, 5, 0.1, 1e-4),
        "short": (1, 1, 0.1, 1e-4),
        "long": (5, 5, 0.1, 1e-4),
        "no-negatives": (1, 5, 0.001, 1e-4),
        "no-distortion-loss": (1, 5, 0.1, 0.0),
    }
    for r in res["levels"]:
        train = run_config(out, f"ablation-{r['level']}")["train"]
        got = tuple(train[k] for k in ("win_min", "win_max", "neg_ratio", "distortion_weight"))
        assert got == pytest.approx(want[r["level"]]), r["level"]
        assert r["knobs"]["win_min"] == got[0] and r["knobs"]["neg_ratio"] == got[2]
        clean = {"pose_error_deg": 0.0, "noise_fraction": 0.0, "seed": 0, "mount_error_deg": 0.0}
        assert train["perturb"] == clean
    assert "| short | 1..1 |" in md and "1 % of 100" in md


def test_ablation_keeps_the_reference_windows_unless_set(tiny_scene):
    """On a CPU the fast preset draws longer windows (fastenerf.cpu_preset); the ablation's
    full model is the reference's U{1..5 %}, and a --set window still wins."""
    import argparse

    from benchmarks.error_vs_time import parse_sets
    from benchmarks.study import level_config
    from fastenerf.data.formats.native import load_scene

    scene = load_scene(tiny_scene)
    args = argparse.Namespace(seed=0, steps=1, budget_s=None)

    def win(study_name, level, *sets):
        base = parse_sets(list(sets), ["ngp"])["ngp"]
        cfg = level_config(study_name, level, scene, args, "cpu", base)
        return cfg.resolved(scene.config, "cpu").win_max

    assert win("ablation", "full") == win("ablation", "no-negatives") == 5  # 5 % of 100 views
    assert win("pose-error", 0.0) == 20  # the CPU preset's 20 %
    assert win("ablation", "full", "win_max=7") == 7
    assert win("ablation", "long") == 5


def test_turned_views_turn_each_camera_about_its_centre(tiny_scene):
    import torch

    from benchmarks.study_report import learnt_gauge, turned_views
    from fastenerf.data.formats.native import load_scene
    from fastenerf.evaluate import make_eval_set
    from fastenerf.se3 import so3_exp

    ev = make_eval_set(load_scene(tiny_scene), 3, 0.125)
    assert learnt_gauge(None) is None and learnt_gauge({"pose_gauge_wx": 0.1}) is None
    w = learnt_gauge({"pose_gauge_wx": 0.01, "pose_gauge_wy": 0.0, "pose_gauge_wz": -0.02})
    turned = turned_views(ev, w)
    W = so3_exp(torch.from_numpy(w)).numpy()
    np.testing.assert_allclose(turned.c2w[:, :3, 3], ev.c2w[:, :3, 3])  # centres kept
    np.testing.assert_allclose(turned.c2w[:, :3, :3], W @ ev.c2w[:, :3, :3], atol=1e-15)
    assert turned.gt is ev.gt and not np.allclose(turned.c2w, ev.c2w)
    np.testing.assert_allclose(turned_views(ev, np.zeros(3)).c2w, ev.c2w)


def test_break_location_and_window_scaling():
    b = lv.supplement_break("pose-error")
    assert (b["largest_drop"]["from"], b["largest_drop"]["to"]) == (0.1, 1.0)
    assert b["largest_drop"]["drop_db"] == pytest.approx(26.18 - 18.11)
    assert b["first_below"] == 1.0
    assert lv.supplement_break("noise")["first_below"] is None
    assert lv.supplement_break("ablation") is None
    # missing PSNRs are skipped; the pair is of the levels that have one
    b = lv.locate_break([0, 0.1, 0.3, 1], [30.0, None, 29.0, 20.0])
    assert (b["largest_drop"]["from"], b["largest_drop"]["to"]) == (0.3, 1)
    assert lv.locate_break([0, 1], [30.0, float("nan")]) is None
    # the authors' 10 / 50 of a 1000-pose loop
    assert lv.level_overrides("ablation", "short", 1000, 0) == {"win_min": 10, "win_max": 10}
    assert lv.level_overrides("ablation", "long", 1000, 0) == {"win_min": 50, "win_max": 50}
    assert lv.level_overrides("ablation", "short", 30, 0)["win_max"] == 1  # never 0
    p = lv.level_overrides("noise", 15, 100, 7)["perturb"]
    assert (p.noise_fraction, p.seed) == (0.15, 7)
    p = lv.level_overrides("mount-error", 2, 100, 3)["perturb"]
    assert (p.mount_error_deg, p.pose_error_deg, p.noise_fraction, p.seed) == (2.0, 0, 0, 3)
    p = lv.level_overrides("pose-error", 0.5, 100, 3)["perturb"]
    assert (p.pose_error_deg, p.mount_error_deg) == (0.5, 0.0)
    assert (lv.level_label("mount-error", 0.5), lv.level_slug("mount-error", 2.0)) == (
        "0.5°",
        "mount-2deg",
    )
    assert lv.supplement_break("mount-error") is None


def test_bad_levels_are_one_line_errors(tiny_scene, tmp_path, capsys):
    assert lv.parse_levels("noise", ["30", "0", "5"]) == [0.0, 5.0, 30.0]
    assert lv.parse_levels("mount-error", ["5", "0", "179.5"]) == [0.0, 5.0, 179.5]
    assert lv.parse_levels("mount-error", None) == [0.0, 0.5, 1.0, 2.0, 5.0]
    for name, bad in (
        ("pose-error", ["180"]),
        ("pose-error", ["-1"]),
        ("mount-error", ["180"]),
        ("mount-error", ["-0.5"]),
        ("mount-error", ["nan"]),
        ("mount-error", ["1", "1.0"]),
        ("noise", ["abc"]),
        ("noise", ["5", "5.0"]),
        ("ablation", ["full", "medium"]),
    ):
        with pytest.raises(InputError):
            lv.parse_levels(name, bad)
    assert study("ablation", tiny_scene, tmp_path / "x", "--levels", "medium") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "medium" in err[0] and "Traceback" not in err[0]
    assert study("mount-error", tiny_scene, tmp_path / "m", "--levels", "1", "180") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "outside [0, 180)" in err[0] and "Traceback" not in err[0]
    assert not (tmp_path / "m" / "runs").exists()
    assert study("pose-error", tiny_scene, tmp_path / "x", "--grid-view", "3") == 2
    assert not (tmp_path / "x" / "runs").exists()


def test_help_documents_levels_and_outputs(capsys):
    for argv in (
        ["bench", "study", "--help"],
        ["bench", "study", "noise", "--help"],
        ["bench", "study", "mount-error", "--help"],
    ):
        with pytest.raises(SystemExit) as e:
            cli_main(argv)
        assert e.value.code == 0
    text = capsys.readouterr().out
    assert "0 0.01 0.1 0.3 0.5 1 2 degrees" in text and "no-distortion-loss" in text
    assert "STUDY_grid.png" in text and "noise.md" in text and "27.31" in text
    assert "mount-error 0 0.5 1 2 5 degrees" in text and "refine_shared=true" in text
    flat = " ".join(text.split())  # help text wraps anywhere
    assert "no mount-error study" in flat and "mount-error.md" in flat


def test_threshold_study_simulates_trains_three_ways_and_reports_the_ratio(tmp_path):
    """One level (C+ 0.4, C- 0.25): simulated once (reused on a second call), trained as given
    (true), from the wrong start (0.25 / 0.25) and with the ratio estimated; the JSON records
    the thresholds each run used, the table and the plots are written."""
    data, out = tmp_path / "data", tmp_path / "out"
    args = ["bench", "study", "threshold", "blocks", "--data", str(data), "--levels", "0.4"]
    args += ["--size", "32x24", "--frames", "40", "--steps", "1", "--out", str(out), *FAST]
    assert cli_main(args + ["--make-only"]) == 0
    stamp = (data / "blocks-pos0.4" / "threshold_study.json").stat().st_mtime_ns
    assert cli_main(args) == 0
    assert (data / "blocks-pos0.4" / "threshold_study.json").stat().st_mtime_ns == stamp
    res = json.loads((out / "threshold.json").read_text())
    runs = {r["variant"]: r for r in res["runs"]}
    assert list(runs) == ["true", "start", "estimate"]
    assert runs["true"]["start"] == {"pos": 0.4, "neg": 0.25}
    assert runs["start"]["start"] == {"pos": 0.25, "neg": 0.25}
    assert runs["start"]["ratio_error"] == pytest.approx(1 / 1.6 - 1)
    est = runs["estimate"]["estimate"]
    assert est["pos"] * est["neg"] == pytest.approx(0.0625, rel=1e-5)  # only the ratio moves
    assert all(r["finished"] and math.isfinite(r["psnr"]) for r in runs.values())
    assert runs["true"]["psnr_vs_true"] == 1.0
    for png in ("threshold.png", "threshold_grid.png"):
        assert iio.imread(out / png)[..., :3].std() > 0
    assert "ratio within 10 %" in (out / "threshold.md").read_text()
    # a level folder made with other settings is refused in one line
    bad = [a if a != "0.03" else "0.05" for a in args] + ["--mismatch", "0.05", "--resume"]
    assert cli_main(bad) == 2


def test_threshold_study_refuses_a_file_as_its_data_folder(tmp_path, capsys):
    """--data naming a file: one line, exit 2, the file untouched and nothing simulated."""
    data = tmp_path / "data"
    data.write_text("mine")
    args = ["bench", "study", "threshold", "blocks", "--data", str(data), "--levels", "0.4"]
    assert cli_main([*args, "--size", "32x24", "--frames", "4", "--make-only"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--data" in err[0] and "is a file" in err[0]
    assert data.read_text() == "mine"
