"""Benchmarks (issue #5): error against training time and the knob study, tiny and on the CPU.

The runs train real fields (ngp with Warp kernels, vanilla in PyTorch) on a tiny synthetic
scene for a second or two each, so the numbers are meaningless; the tests check the protocol:
clock, schedule, resume, outputs, and the summary arithmetic.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import zipfile
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from fastenerf.cli import main as cli_main
from fastenerf.commands.bench import import_benchmark

evt = import_benchmark("error-vs-time")
knobs = import_benchmark("knobs")

# Small fields and batches: a 2-core CI machine takes a few steps per second with these.
TINY = [
    "rays_per_step=32",
    "windows_per_step=4",
    "ngp:log2_table_size=12",
    "ngp:n_levels=4",
    "ngp:grid_resolution=32",
    "ngp:dt_min=0.02",
    "vanilla:depth=2",
    "vanilla:width=32",
    "vanilla:n_coarse=16",
    "vanilla:n_fine=16",
]
EVAL = ["--device", "cpu", "--eval-views", "2", "--eval-scale", "0.5", "--quiet"]


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    from fastenerf.data.synth import make_scene

    return make_scene(
        "blocks", tmp_path_factory.mktemp("bench") / "blocks", width=48, height=32, frames=60
    )


def test_schedule_is_geometric_and_ends_at_the_budget():
    assert evt.schedule(300) == [1, 2, 4, 8, 15, 30, 60, 120, 300]
    assert evt.schedule(480)[-3:] == [120, 300, 480]
    assert evt.schedule(3, first_s=0.25) == [0.25, 0.5, 1, 2, 3]
    assert evt.schedule(0.3) == [0.3]
    dense = evt.schedule(300, ladder="dense")
    assert dense[:5] == [1, 1.5, 2, 3, 4] and dense[-1] == 300
    # ~6 points a decade: neighbours at most 1.5x apart, so a crossing is bracketed within 1.5x
    assert max(b / a for a, b in zip(dense, dense[1:], strict=False)) <= 1.5
    assert evt.parse_schedules(["vanilla=dense"], ["ngp", "vanilla"]) == {
        "ngp": "dense",
        "vanilla": "dense",
    }
    for bad in (["sparse"], ["foo=dense"]):
        with pytest.raises(evt.InputError):
            evt.parse_schedules(bad, ["ngp", "vanilla"])


def test_budget_preset_and_set_parsing():
    assert evt.parse_budgets(["ngp=30", "vanilla=90"], ["ngp", "vanilla"]) == {
        "ngp": 30.0,
        "vanilla": 90.0,
    }
    assert evt.parse_budgets(["5"], ["ngp", "vanilla"]) == {"ngp": 5.0, "vanilla": 5.0}
    assert evt.parse_presets(["vanilla=eventnerf"], ["ngp", "vanilla"]) == {
        "ngp": "fast",
        "vanilla": "eventnerf",
    }
    sets = evt.parse_sets(["rays_per_step=64", "ngp:n_levels=8"], ["ngp", "vanilla"])
    assert sets["vanilla"] == {"train": {"rays_per_step": 64}, "backend_options": {}}
    assert sets["ngp"]["backend_options"] == {"n_levels": 8}
    for bad in (["ngp=-1"], ["foo=3"], ["ngp=abc"]):
        with pytest.raises(evt.InputError):
            evt.parse_budgets(bad, ["ngp", "vanilla"])


def _curve(backend, pts):
    return {
        "scene": "s",
        "backend": backend,
        "budget_s": pts[-1][0],
        "finished": True,
        "points": [
            {"train_s": t, "psnr": p, "ssim": 0.5, "step": i + 1} for i, (t, p) in enumerate(pts)
        ],
    }


def test_summary_speedup_time_to_psnr_and_60s_gap():
    ngp = _curve("ngp", [(1.1, 20.0), (2.2, 24.5), (4.1, 26.0), (61.0, 28.0), (300.5, 28.3)])
    van = _curve("vanilla", [(1.5, 12.0), (120.2, 22.0), (479.9, 24.0), (480.3, 23.9)])
    s = evt.summarize_scene({"ngp": ngp, "vanilla": van})
    c = s["ngp_vs_vanilla"]
    assert c["vanilla_best_psnr"] == 24.0 and c["vanilla_time_to_best_s"] == 479.9
    assert c["ngp_time_to_same_s"] == 2.2  # first point at or above 24 dB
    assert c["speedup"] == pytest.approx(479.9 / 2.2)
    # the crossing lies between the 1.1 s (20 dB) and 2.2 s (24.5 dB) points: 8/9 of the way
    # in log time; the bracket gives the speed-up's upper bound
    assert c["ngp_time_to_same_lower_s"] == 1.1
    t = math.exp(math.log(1.1) + 8 / 9 * (math.log(2.2) - math.log(1.1)))
    assert c["ngp_time_to_same_interp_s"] == pytest.approx(t)
    assert c["speedup_interp"] == pytest.approx(479.9 / t)
    assert c["speedup_upper"] == pytest.approx(479.9 / 1.1)
    assert c["speedup"] < c["speedup_interp"] < c["speedup_upper"]
    g = s["ngp_60s"]
    assert g["psnr_at_60s"] == 28.0 and g["gap_db"] == pytest.approx(0.3) and g["met"]
    # ngp never reaching vanilla's best is reported as such, not as a number
    slow = _curve("ngp", [(1.0, 10.0), (61.0, 20.0), (300.0, 23.0)])
    s2 = evt.summarize_scene({"ngp": slow, "vanilla": van})
    assert not s2["ngp_vs_vanilla"]["reached"] and s2["ngp_vs_vanilla"]["speedup"] is None
    assert not s2["ngp_60s"]["met"]
    # a vanilla run that never beat its first evaluation (an untrained field's score) gives
    # no speed-up, however fast ngp passes that level
    flat = _curve("vanilla", [(1.0, 25.7), (60.0, 25.4), (200.0, 25.4)])
    s3 = evt.summarize_scene({"ngp": ngp, "vanilla": flat})
    assert not s3["ngp_vs_vanilla"]["vanilla_learned"]
    assert (
        s3["ngp_vs_vanilla"]["speedup"] is None and s3["ngp_vs_vanilla"]["speedup_interp"] is None
    )
    assert evt.summarize_scene({"ngp": ngp, "vanilla": van})["ngp_vs_vanilla"]["vanilla_learned"]
    md = evt.markdown(
        {
            "machines": ["GPU X"],
            "cpu_numbers": False,
            "complete": True,
            "git_commits": ["abc"],
            "torch": ["t"],
            "warp": ["w"],
            "protocol": {
                "preset": "fast",
                "budgets_s": {"ngp": 300, "vanilla": 480},
                "eval_views_used": {"s": [0, 10, 20]},
                "eval_scale": 1.0,
                "warmup_steps": 2,
            },
            "summary": {"s": s, "slow": s2, "flat": s3},
        }
    )
    assert (
        "≥ 218.1× (met; 236× interpolated)" in md and "not reached" in md and "+0.30 dB (met)" in md
    )
    assert "none: vanilla never rose above its first evaluation" in md


def _read(out):
    res = json.loads((out / "error_vs_time.json").read_text())
    img = iio.imread(out / "error_vs_time.png")
    assert img.ndim == 3 and img.shape[0] > 100 and img.shape[1] > 100
    return res, (out / "error_vs_time.md").read_text()


def test_error_vs_time_runs_both_backends_and_resumes(tiny_scene, tmp_path):
    out = tmp_path / "evt"
    args = [
        "bench",
        "error-vs-time",
        "--scenes",
        str(tiny_scene),
        "--out",
        str(out),
        "--budget-s",
        "ngp=1.5",
        "vanilla=1",
        "--first-s",
        "0.5",
        "--warmup-steps",
        "1",
        *EVAL,
        "--set",
        *TINY,
    ]
    assert cli_main(args) == 0
    res, md = _read(out)
    assert res["cpu_numbers"] and res["complete"]
    assert {r["backend"] for r in res["runs"]} == {"ngp", "vanilla"}
    assert sum(len(r["points"]) for r in res["runs"]) >= 3
    for r in res["runs"]:
        pts = r["points"]
        assert len(pts) >= 1  # one slow step may pass several scheduled times
        t = [p["train_s"] for p in pts]
        assert all(b > a for a, b in zip(t, t[1:], strict=False))
        assert [p["target_s"] for p in pts][-1] == r["budget_s"] and t[-1] >= r["budget_s"]
        assert all(
            b > a
            for a, b in zip([p["step"] for p in pts], [p["step"] for p in pts][1:], strict=False)
        )
        for p in pts:
            assert math.isfinite(p["psnr"]) and 5 < p["psnr"] < 60
            assert -1 <= p["ssim"] <= 1 and p["eval_s"] > 0 and p["loss"] is not None
        assert r["eval_views"] == [0, 5]  # 2 evenly spaced of the 6 test views (first, last)
    for p in res["points"]:
        assert p["machine"].startswith("CPU:") and p["git_commit"] and p["torch"] and p["warp"]
    assert "**CPU numbers**" in md and "| ngp |" in md and "| vanilla |" in md

    # a second call without --resume refuses to overwrite
    assert cli_main(args) == 2
    # --resume with a larger ngp budget continues ngp's clock and appends to its curve;
    # vanilla's budget is spent, so it is left as it was
    before = {r["backend"]: r for r in res["runs"]}
    args2 = [a if a != "ngp=1.5" else "ngp=2.5" for a in args]
    args2[args2.index("--warmup-steps") + 1] = "0"
    assert cli_main([*args2, "--resume"]) == 0
    res2, _ = _read(out)
    after = {r["backend"]: r for r in res2["runs"]}
    old, new = before["ngp"]["points"], after["ngp"]["points"]
    assert new[: len(old)] == old and len(new) > len(old)
    assert new[len(old)]["train_s"] > old[-1]["train_s"] and new[-1]["train_s"] >= 2.5
    assert new[len(old)]["step"] > old[-1]["step"] and new[-1]["session"] == 1
    assert after["vanilla"]["points"] == before["vanilla"]["points"]
    ck = json.loads((out / "runs" / "blocks-ngp" / "progress.json").read_text())
    assert ck["step"] == new[-1]["step"] and ck["train_seconds"] == pytest.approx(
        new[-1]["train_s"]
    )


def test_knobs_two_variants(tiny_scene, tmp_path):
    out = tmp_path / "knobs"
    base = [t.split(":", 1)[-1] for t in TINY if not t.startswith("vanilla:")]
    rc = cli_main(
        [
            "bench",
            "knobs",
            "--scene",
            str(tiny_scene),
            "--out",
            str(out),
            "--budget-s",
            "1",
            "--variants",
            "default",
            "dt_min_x2",
            "--warmup-steps",
            "0",
            *EVAL,
            "--set",
            *base,
        ]
    )
    assert rc == 0
    res = json.loads((out / "knobs.json").read_text())
    rows = {r["name"]: r for r in res["variants"]}
    assert set(rows) == {"default", "dt_min_x2"} and res["complete"] and res["cpu_numbers"]
    assert rows["default"]["default"] and not rows["dt_min_x2"]["default"]
    for r in rows.values():
        assert math.isfinite(r["psnr"]) and r["step_ms"] > 0 and r["steps"] >= 1
        assert r["samples_per_step"] > 0
    assert any(r["pareto"] for r in rows.values())
    # dt_min x2 was resolved against the box: its run really used twice the step
    cfg = json.loads((out / "runs" / "dt_min_x2" / "config.json").read_text())
    assert cfg["field"]["options"]["marcher"]["dt_min"] == pytest.approx(0.04)
    assert iio.imread(out / "knobs.png").ndim == 3
    md = (out / "knobs.md").read_text()
    assert "**default**" in md and "dt_min_x2" in md and "CPU numbers" in md
    assert np.isfinite(rows["dt_min_x2"]["psnr"])


def test_kernel_benchmark_table_on_cpu(tmp_path):
    """`python -m benchmarks.kernels` at tiny CPU sizes: every op timed against PyTorch."""
    from benchmarks import kernels

    assert kernels.main(["--device", "cpu", "--out", str(tmp_path)]) == 0
    md = (tmp_path / "kernels.md").read_text()
    for label, *_ in kernels.ROWS:
        assert f"| {label} |" in md
    res = json.loads((tmp_path / "kernels.json").read_text())
    assert res["hashgrid"]["max_abs_err"] < 1e-5 and res["copy_GBps"] > 0


def test_profile_step_names_every_stage_on_cpu(tiny_scene, tmp_path):
    from benchmarks import profile_step as ps

    assert ps.kernel_kind("march_kernel_cuda_kernel_forward") == "march"
    assert ps.kernel_kind("sm90_xmma_gemm_bf16bf16_bf16f32") == "mlp"
    assert ps.kernel_kind("_kernels__locals__backward_table_4e5_cuda_kernel_forward") == "hash grid"
    assert ps.kernel_kind("void at::native::vectorized_elementwise_kernel") == "torch other"
    # the march's helpers and the compaction are theirs, not "torch other" (gpu_s46's profiles)
    for name, kind in [
        ("_place_rows_12c0c832_cuda_kernel_forward", "march"),
        ("pad_tail_4b219bce_cuda_kernel_forward", "march"),
        ("reserve_slices_f1103ae2_cuda_kernel_forward", "march"),
        ("_cap_segments_0a1b_cuda_kernel_forward", "march"),
        ("_compact_7d35ce40_cuda_kernel_forward", "compaction"),
        ("_visibility_99470a68_cuda_kernel_forward", "compaction"),
        ("_points_forward_76779c75_cuda_kernel_forward", "ray points"),
    ]:
        assert ps.kernel_kind(name) == kind, name
    out = tmp_path / "prof"
    argv = ["--scene", str(tiny_scene), "--device", "cpu", "--warmup", "1", "--steps", "2"]
    assert ps.main(argv + ["--out", str(out), "--quiet"]) == 0
    res = json.loads((out / "profile_step.json").read_text())
    # every stage of an ngp step was seen by the profiler, and the stages fit in the step
    for stage in ("sample_rays", "render", "march", "field", "composite", "backward", "optimizer"):
        assert res["host_ms"][stage] > 0, stage
    assert res["host_ms"]["render"] < res["wall_ms"]
    assert res["samples_per_step"] > 0 and res["session"]["machine"]["cpu_numbers"]
    assert "CPU numbers" in (out / "profile_step.md").read_text()
    # the CPU step captures no CUDA graph; a run with a graphed step says how many it made
    assert res["captures"] in (None, {"unprofiled": 0, "profiled": 0})
    assert res["device_gaps"] is None  # no device timeline on the CPU
    # the plain CPU step asks for no synchronisation (Warp's CPU launches are synchronous)
    assert res["explicit_syncs_per_step"] == 0.0 and res["explicit_sync_examples"] == []
    md = (out / "profile_step.md").read_text()
    assert "Explicit synchronisations per step: 0.00 (at none)." in md
    # with Python calls recorded the stages are still the step's own
    stacks = ["--quiet", "--stacks", "--trace"]
    assert ps.main(argv + ["--out", str(tmp_path / "stacks"), *stacks]) == 0
    stacked = json.loads((tmp_path / "stacks" / "profile_step.json").read_text())
    assert stacked["host_ms"]["render"] > 0 and stacked["host_ms"]["render"] < stacked["wall_ms"]
    # --trace: the profiled steps' events, a Chrome trace (gzipped) holding the stages
    import gzip

    trace = json.loads(
        gzip.decompress((tmp_path / "stacks" / "run" / "trace.json.gz").read_bytes())
    )
    names = {e.get("name") for e in trace["traceEvents"]}
    assert {"render", "sample_rays"} <= names
    assert not (out / "run" / "trace.json.gz").exists()  # only when asked


def test_mlp_widths_times_the_padded_colour_mlp_beside_the_unpadded_on_cpu(tmp_path, capsys):
    from benchmarks import mlp_widths

    out = tmp_path / "m.json"
    argv = ["--device", "cpu", "--n", "256", "--geo", "10", "--repeats", "1"]
    assert mlp_widths.main(argv + ["--out", str(out)]) == 0
    rows = {r["variant"]: r for r in json.loads(out.read_text())}
    assert set(rows) == {"unpadded", "padded", "padded_cat", "density"}
    assert rows["unpadded"]["speedup_fwdbwd"] == 1.0 and rows["padded"]["fwdbwd_ms"] > 0
    assert rows["padded"]["max_diff"] < 1e-2  # the same function (bf16 rounding at most)
    assert rows["padded_cat"]["max_diff"] < 1e-2  # and so is the old way of feeding it
    assert "| " not in capsys.readouterr().out  # a plain table on stdout
    assert mlp_widths.main(["--device", "cpu", "--n", "0", "--out", str(tmp_path / "x.json")]) == 2
    assert not (tmp_path / "x.json").exists()


def test_hashgrid_runs_times_each_run_length_beside_one_point_per_thread(tmp_path, capsys):
    from benchmarks import hashgrid_runs

    out = tmp_path / "r.json"
    argv = ["--device", "cpu", "--runs", "1", "4", "--rays", "8", "--per-ray", "16"]
    assert hashgrid_runs.main(argv + ["--repeats", "1", "--json", str(out)]) == 0
    res = json.loads(out.read_text())
    assert res["n_points"] == 128 and set(res["sets"]) == {"ray_order", "uniform"}
    for rows in res["sets"].values():
        assert [r["run"] for r in rows] == [1, 4] and rows[0]["speedup_vs_first"] == 1.0
        assert rows[1]["bwd_ms"] > 0 and rows[1]["max_rel_diff"] < 1e-5  # the same sum
    assert "| ray_order | 4 |" in capsys.readouterr().out
    capsys.readouterr()
    bad = tmp_path / "x.json"
    assert hashgrid_runs.main(["--device", "cpu", "--runs", "0", "--json", str(bad)]) == 2
    assert not bad.exists()
    # an output that is no JSON file, or a folder, is refused before any work, untouched
    other = tmp_path / "notes.txt"
    other.write_text("mine")
    for out in (other, tmp_path):
        assert hashgrid_runs.main(["--device", "cpu", "--rays", "2", "--json", str(out)]) == 2
    assert other.read_text() == "mine"
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 3 and all(e.startswith("hashgrid_runs: error:") for e in err)


def test_profile_step_lists_every_kernel_no_kind_claims():
    """`tally_kernels` on launches named as the H200 profiles name them (gpu_s45): kinds sum
    to the device time, and every "torch other" kernel is listed with its launches per step,
    largest first, in the JSON and (to OTHER_ROWS) in the Markdown."""
    from benchmarks import profile_step as ps

    cat = "void at::native::(anonymous namespace)::CatArrayBatchedCopy<OpaqueType<2u>, |4>"
    scan = "void at::native::tensor_kernel_scan_innermost_dim<int, std::plus<int> >"
    launches = [
        ("run_backward__locals__backward_table_runs_f5aba31e_cuda_kernel_forward", 0.8),
        ("nvjet_sm90_tst_64x384_64x3_1x2_h_bz_coopB_NNT", 0.25),
        (cat, 0.15),
        (scan, 0.05),
        (scan, 0.05),
        ("_march_kernel__locals__march_b1a3b49c_cuda_kernel_forward", 0.45),
    ] * 2  # two steps
    t = ps.tally_kernels(launches, steps=2, top=3)
    assert sum(t["device_ms"].values()) == pytest.approx(1.75)
    assert t["device_ms"]["torch other"] == pytest.approx(0.25)
    assert list(t["top_kernels_ms"]) == [launches[0][0], launches[5][0], launches[1][0]]
    assert list(t["other_kernels"]) == [cat, scan]
    assert t["other_kernels"][scan] == {"ms": pytest.approx(0.1), "launches": 2.0}
    assert t["other_kernels"][cat]["launches"] == 1.0
    assert ps.tally_kernels([], steps=3) == {
        "device_ms": {},
        "top_kernels_ms": {},
        "other_kernels": {},
    }
    res = {
        "session": {"machine": {"name": "H200", "cpu_numbers": False}},
        "scene": "s",
        "backend": "ngp",
        "preset": "fast",
        "warmup": 1,
        "steps": 2,
        "rays_per_step": 8,
        "samples_per_step": 10.0,
        "samples_per_ray": None,
        "marched_per_ray": None,
        "trained_slots": None,
        "wall_ms_unprofiled": 2.0,
        "wall_ms": 2.0,
        "device_busy_ms": 1.75,
        "device_busy_share": 0.875,
        "host_ms": dict.fromkeys(ps.STAGES, 0.1),
        **t,
    }
    md = ps.markdown(res)
    rows = [ln for ln in md.splitlines() if ln.startswith("| `")]
    assert len(rows) == 2 and rows[0].endswith("| 0.150 | 1.0 |") and "2u>, \\|4>" in rows[0]
    assert rows[1].endswith("| 0.100 | 2.0 |")


def test_device_gaps_names_what_the_host_was_doing_when_the_device_ran_dry():
    """Kernel intervals merged, gaps under GAP_MIN_US ignored, each gap charged to the
    innermost host event containing its start (or to none), per step; and the Markdown."""
    from benchmarks import profile_step as ps
    from benchmarks.device_gaps import GAP_MIN_US, device_gaps, merge_intervals

    kernels = [(0, 10), (5, 12), (20, 30), (30, 31), (100, 110), (113, 130), (300, 310)]
    kernels += [(500, 510)]
    assert merge_intervals(kernels[:4]) == [(0, 12), (20, 31)]
    host = [
        (0, 400, "step"),
        (11, 25, "sample_rays"),
        (11.5, 13, "aten::item"),  # innermost at 12: the 8 us gap is its
        (26, 28, "aten::add"),  # over before the gap at 31 begins
    ]
    g = device_gaps(kernels, host, steps=2)
    assert 113 - 110 < GAP_MIN_US  # ignored
    # gaps: 12-20 (aten::item); 31-100, 130-300 and 310-500 (step)
    assert g["idle_by_host_ms"] == {
        "step": pytest.approx((69 + 170 + 190) / 1e3 / 2),
        "aten::item": pytest.approx(8 / 1e3 / 2),
    }
    assert g["idle_by_path_ms"] == {  # the containing events, outer first
        "step": pytest.approx((69 + 170 + 190) / 1e3 / 2),
        "step › sample_rays › aten::item": pytest.approx(8 / 1e3 / 2),
    }
    assert g["idle_ms"] == pytest.approx((8 + 69 + 170 + 190) / 1e3 / 2)
    # with Python calls profiled (--stacks) a path keeps this repository's lines, not torch's
    from benchmarks.device_gaps import path_name

    calls = [
        (0, 100, "/var/tmp/after/fastenerf/train.py(226): sync"),
        (1, 99, "torch/cuda/__init__.py(1219): synchronize"),
        (2, 98, "cudaDeviceSynchronize"),
    ]
    stacked = device_gaps([(0, 3), (50, 60)], calls, steps=1)
    assert stacked["idle_by_path_ms"] == {
        "fastenerf/train.py(226): sync › cudaDeviceSynchronize": pytest.approx(0.047)
    }
    assert path_name("kernels/common.py(9): launch") == "kernels/common.py(9): launch"
    assert path_name("<stdin>(6): <module>") is None and path_name("aten::mm") == "aten::mm"
    assert g["gaps"] == 2.0 and g["largest_gap_ms"] == pytest.approx(0.19)
    lone = device_gaps([(0, 1), (50, 60)], [(70, 80, "late")], steps=1)
    assert lone["idle_by_host_ms"] == {"no host event": pytest.approx(0.049)}
    assert device_gaps([(0, 1)], [], steps=1)["idle_ms"] == 0.0
    res = {
        "session": {"machine": {"name": "H200", "cpu_numbers": False}},
        "scene": "s", "backend": "ngp", "preset": "fast", "warmup": 1, "steps": 2,
        "rays_per_step": 8, "samples_per_step": 10.0, "samples_per_ray": None,
        "marched_per_ray": None, "trained_slots": None, "wall_ms_unprofiled": 2.0,
        "wall_ms": 2.0, "device_busy_ms": 1.0, "device_busy_share": 0.5,
        "host_ms": dict.fromkeys(ps.STAGES, 0.1), "device_ms": {"mlp": 1.0},
        "device_gaps": g,
    }  # fmt: skip
    md = ps.markdown(res)
    assert "0.218 ms/step in 2.0 gaps (largest 0.190 ms)" in md
    # a profile's own event objects (torch's FunctionEvent), CUDA rows as a GPU run has them
    from torch.autograd import DeviceType
    from torch.autograd.profiler_util import FunctionEvent

    def event(i, name, t0, t1, kind=DeviceType.CPU, **kw):
        return FunctionEvent(i, name, 0, t0, t1, use_device="cuda", device_type=kind, **kw)

    cuda = DeviceType.CUDA
    RELU = "void at::native::vectorized_elementwise_kernel<8, launch_clamp_scalar::{lambda()#1}>"
    evs = [
        event(0, "sample_rays", 0, 50),
        event(1, "cudaGraphLaunch", 5, 8),
        event(2, "_march_kernel_forward", 10, 30, cuda),
        event(3, "sample_rays", 10, 40, cuda, is_user_annotation=True),  # a range's own row
        event(4, "nvjet_sm90_gemm", 40, 45, cuda),
        event(5, "Optimizer.step#Adam.step", 45, 60, cuda),  # a range: no kernel
        event(6, RELU, 45, 47, cuda),  # a kernel with "#" in its template name
    ]
    kernels, spans, host_events = ps.split_events(evs)
    assert kernels == [("_march_kernel_forward", 0.02), ("nvjet_sm90_gemm", 0.005), (RELU, 0.002)]
    assert spans == [(10, 30, "_march_kernel_forward"), (40, 45, "nvjet_sm90_gemm"), (45, 47, RELU)]
    assert host_events == [(0, 50, "sample_rays", 0), (5, 8, "cudaGraphLaunch", 0)]
    split = device_gaps(spans, host_events, 1)
    assert split["idle_by_host_ms"] == {"sample_rays": 0.01}
    assert split["idle_by_next_kernel_ms"] == {"nvjet_sm90_gemm": 0.01}
    assert "| `step` | 0.214 |" in md and "| `aten::item` | 0.004 |" in md
    assert "| `step › sample_rays › aten::item` | 0.004 |" in md


def test_device_gaps_charge_the_training_thread_and_name_the_kernel_after_each_gap():
    """A sync another thread sits in (a profiler's, the autograd engine's) is not the step's:
    the gap goes to the training thread's event (the thread of most events) and the other
    thread's is counted apart; the kernel that ends each gap is named. Fails if threads are
    mixed (the gap would be charged to the other thread's later-starting sync)."""
    from benchmarks.device_gaps import device_gaps, training_thread

    kernels = [(0, 10, "march"), (40, 50, "mlp"), (90, 100, "hash")]
    host = [
        (0, 200, "step", 1),
        (5, 45, "sample_rays", 1),
        (46, 95, "render", 1),
        (8, 80, "cudaDeviceSynchronize", 7),  # starts after sample_rays: innermost if mixed
    ]
    assert training_thread(host) == 1
    g = device_gaps(kernels, host, steps=1)
    # gaps 10-40 (sample_rays; thread 7's sync also running) and 50-90 (render; and the sync)
    assert g["idle_by_host_ms"] == {
        "sample_rays": pytest.approx(0.03),
        "render": pytest.approx(0.04),
    }
    assert g["idle_other_threads_ms"] == {"cudaDeviceSynchronize": pytest.approx(0.07)}
    assert g["idle_by_next_kernel_ms"] == {"hash": pytest.approx(0.04), "mlp": pytest.approx(0.03)}
    three = device_gaps([(0, 10), (40, 50)], [(0, 60, "step")], steps=1)  # no threads, names
    assert three["idle_by_host_ms"] == {"step": pytest.approx(0.03)}
    assert three["idle_other_threads_ms"] == {} and three["idle_by_next_kernel_ms"] == {}


def test_device_gaps_name_what_led_to_a_sync_the_device_ran_dry_in():
    """A gap that began inside a sync call is also charged to that call and the host events
    that ended just before it began (oldest first): here a graph launch, then a copy whose
    own cudaMemcpyAsync ended inside it; a gap in any other event gets no lead-in."""
    from benchmarks.device_gaps import LEAD_IN, device_gaps

    kernels = [(0, 10, "march"), (40, 50, "mlp"), (90, 100, "hash")]
    host = [
        (0, 3, "grid_update", 1),
        (3, 5, "cudaGraphLaunch", 1),
        (5, 8, "aten::copy_", 1),
        (6, 7, "cudaMemcpyAsync", 1),
        (9, 45, "cudaDeviceSynchronize", 1),
        (46, 95, "render", 1),
    ]
    g = device_gaps(kernels, host, steps=1)
    assert LEAD_IN == 4
    lead = "grid_update › cudaGraphLaunch › cudaMemcpyAsync › aten::copy_"
    assert g["idle_by_sync_lead_in_ms"] == {
        f"cudaDeviceSynchronize after {lead}": pytest.approx(0.03)
    }
    assert g["idle_by_host_ms"]["render"] == pytest.approx(0.04)


def test_profile_step_profiles_several_variants_side_by_side(tiny_scene, tmp_path, capsys):
    from benchmarks import profile_step as ps

    argv = ["--scene", str(tiny_scene), "--device", "cpu", "--warmup", "1", "--steps", "2"]
    refine = 'ref={"train": {"refine_poses": true}}'
    out = tmp_path / "prof"
    assert ps.main(argv + ["--variant", "plain={}", "--variant", refine, "--out", str(out)]) == 0
    res = json.loads((out / "profile_step.json").read_text())
    plain, ref = res["variants"]  # both profiled, in the order given, each in its own run
    assert plain["backend"] == "ngp, variant plain" and ref["backend"] == "ngp, variant ref"
    assert plain["wall_ms_unprofiled"] > 0 and ref["wall_ms_unprofiled"] > 0
    assert json.loads((out / "ref" / "config.json").read_text())["train"]["refine_poses"]
    md = (out / "profile_step.md").read_text()
    assert "| plain |" in md and "| ref |" in md and md.count("### Training step profile —") == 2
    # a name given twice, or one that is no folder name, is refused before any work
    capsys.readouterr()
    for bad in (["--variant", "a={}", "--variant", "a={}"], ["--variant", "../a={}"]):
        assert ps.main(argv + bad + ["--out", str(tmp_path / "x")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "--variant" in err[0], err
        assert not (tmp_path / "x" / "profile_step.json").exists()


def test_step_ops_counts_every_stage_on_cpu(tiny_scene, tmp_path, capsys):
    """`python -m benchmarks.step_ops`: aten ops, autograd nodes and Warp launches per step,
    by the step's named ranges; a missing scene folder is one line and exit code 2."""
    from benchmarks import step_ops

    out = tmp_path / "ops"
    # the counted steps hold the 17th step: a new sampler block and an occupancy update
    argv = ["--scene", str(tiny_scene), "--warmup", "15", "--steps", "2", "--rays", "32"]
    assert step_ops.main(argv + ["--out", str(out)]) == 0
    res = json.loads((out / "step_ops.json").read_text())
    per = res["per_step"]
    for stage in ("grid_update", "sample_rays", "march", "field", "composite", "loss"):
        assert per[stage]["aten"] >= per[stage]["aten_top"] > 0, stage
    assert per["backward"]["aten_top"] > 0 and per["optimizer"]["aten_top"] > 0
    assert per["backward"]["autograd"] > 0 and per["field"]["warp"] > 0
    assert per["march"]["warp"] > 0 and per["composite"]["warp"] > 0
    total = per["total"]
    assert total["aten_top"] == pytest.approx(
        sum(per[s]["aten_top"] for s in step_ops.STAGES) + per["other"]["aten_top"]
    )
    assert res["step_mode"] == "device" and res["amp"] and res["steps"] == 2
    assert any(k.startswith("warp::") for k in res["ops_per_step"]["field"])
    md = (out / "step_ops.md").read_text()
    assert "| backward |" in md and "**total**" in md
    # an earlier run's counts beside this one's
    capsys.readouterr()
    argv2 = argv + ["--out", str(tmp_path / "ops2"), "--baseline", str(out / "step_ops.json")]
    assert step_ops.main(argv2 + ["--no-amp", "--step-mode", "plain"]) == 0
    assert " → " in (tmp_path / "ops2" / "step_ops.md").read_text()
    capsys.readouterr()
    assert step_ops.main(["--scene", str(tmp_path / "missing"), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("step_ops: error:") and len(err.splitlines()) == 1


def test_mount_gauge_finds_the_turns_a_rigid_motion_imitates(tiny_scene, tmp_path, capsys):
    """`python -m benchmarks.mount_gauge`: on an orbit a pitch of every camera looks like the
    scene moved up (mostly imitated), a yaw like nothing rigid (not imitated); bad input is
    one line and exit code 2."""
    from benchmarks import mount_gauge

    out = tmp_path / "gauge"
    argv = ["--scene", str(tiny_scene), "--views", "24", "--points", "60", "--perturb-seed", "0"]
    assert mount_gauge.main(argv + ["--out", str(out)]) == 0
    turns = json.loads((out / "mount_gauge.json").read_text())["turns"]
    pitch, yaw = turns["x (pitch)"], turns["y (yaw)"]
    assert pitch["rms_px"] > 0 and yaw["rms_px"] > 0
    assert pitch["imitated"] > 0.5 and pitch["rigid_shift"] > 0
    assert yaw["imitated"] < 0.1
    assert turns["seed 0"]["rms_px_after_rigid"] <= turns["seed 0"]["rms_px"]
    assert "| y (yaw) |" in (out / "mount_gauge.md").read_text()
    capsys.readouterr()
    bad_args = (["--deg", "0"], ["--views", "0"], ["--points", "-3"], ["--perturb-seed", "-1"])
    for bad in (*bad_args, ["--scene", str(tmp_path / "missing")]):
        assert mount_gauge.main(argv + bad) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("mount_gauge: error:") and len(err.splitlines()) == 1, err
        assert "mount_gauge: error: mount_gauge" not in err


def test_mount_landscape_walks_the_line_without_writing_the_run(tiny_scene, tmp_path, capsys):
    """`python -m benchmarks.mount_landscape`: the loss at each point of the line from a shared
    row to the truth, the run folder untouched; bad input is one line and exit code 2."""
    from benchmarks import mount_landscape
    from fastenerf.cli import main

    study = tmp_path / "study"
    argv = ["bench", "study", "mount-error", str(tiny_scene), "--levels", "2", "--steps", "3",
            "--device", "cpu", "--quiet", "--eval-views", "1", "--out", str(study),
            "--set", "refine_poses=true", "refine_shared=true", "rays_per_step=32"]  # fmt: skip
    assert main(argv) == 0
    run = study / "runs" / "mount-2deg"
    before = {p.name: p.stat().st_mtime_ns for p in run.iterdir()}
    capsys.readouterr()
    args = [str(run), "--scene", str(tiny_scene), "--batches", "2"]
    assert mount_landscape.main(args + ["--ts", "0,1"]) == 0
    out = capsys.readouterr().out.splitlines()
    losses = [float(line.split("loss=")[1]) for line in out if line.startswith("t=")]
    assert len(losses) == 2 and all(math.isfinite(v) and v > 0 for v in losses)
    assert "truth [" in out[0]
    assert {p.name: p.stat().st_mtime_ns for p in run.iterdir()} == before
    bad_args = (
        ["--ts", "0,x"],
        ["--ts", "nan"],
        ["--batches", "0"],
        ["--field-from", str(tmp_path / "missing")],
    )
    for bad in bad_args:
        assert mount_landscape.main(args + bad) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("mount_landscape: error:") and len(err.splitlines()) == 1, err
    assert mount_landscape.main([str(tmp_path), "--scene", str(tiny_scene)]) == 2
    assert "no config.json" in capsys.readouterr().err


def test_study_sweep_tables_and_plots_runs_of_several_sweeps(tmp_path):
    """benchmarks.study_sweep reads one pose-error.json (or mount-error.json: a pose study) per
    (scene, option, level) folder of every sweep given, tables them (names prefixed by the
    other sweeps' folders; a study column once there are two studies) and plots PSNR at 1°
    against 0°."""
    from benchmarks import study_sweep

    def run(folder, name, level, psnr, err=None, study="pose-error", shared=None):
        d = tmp_path / folder / f"sweep_blocks_{name}_L{level:g}"
        d.mkdir(parents=True, exist_ok=True)
        stats = {} if err is None else {"pose_error_deg": err, "pose_centre_error": 0.0}
        if shared is not None:
            stats["pose_gauge_deg"] = shared
        lv = {"level": level, "psnr": psnr, "steps": 30, "train_s": 1.0,
              "self_calibration": {"stats": stats} if stats else None}  # fmt: skip
        (d / f"{study}.json").write_text(json.dumps({"levels": [lv], "git_commits": ["abc"]}))

    run("a", "plain", 0, 30.0)
    run("a", "new_one", 0, 29.9)
    run("a", "new_one", 1, 29.1, 0.08, shared=0.05)
    run("b", "old", 1, 25.0, 0.3)
    (tmp_path / "a" / "sweep_blocks_broken_L1").mkdir()  # no JSON: not a finished run
    assert study_sweep.main([str(tmp_path / "a"), str(tmp_path / "b")]) == 0
    rows = json.loads((tmp_path / "a" / "sweep.json").read_text())["runs"]
    assert [(r["name"], r["level"], r["psnr"]) for r in rows] == [
        ("b:old", 1.0, 25.0),
        ("new_one", 0.0, 29.9),
        ("new_one", 1.0, 29.1),
        ("plain", 0.0, 30.0),
    ]
    md = (tmp_path / "a" / "sweep.md").read_text()
    assert "| blocks | new_one | 1° | 29.10 | 0.080 | 0.050 |" in md
    assert "| blocks | plain | 0° | 30.00 | — | — |" in md  # nothing refined
    assert (tmp_path / "a" / "sweep.png").stat().st_size > 1000
    assert (tmp_path / "a" / "sweep_levels.png").stat().st_size > 1000
    # bad input: one line, exit 2, and the tables already there stay as they are
    (tmp_path / "empty").mkdir()
    assert study_sweep.main([str(tmp_path / "empty")]) == 2
    assert not any((tmp_path / "empty").iterdir())
    assert study_sweep.main([str(tmp_path / "a"), str(tmp_path / "missing")]) == 2
    assert (tmp_path / "a" / "sweep.md").read_text() == md
    # STUDY=mount-error sweeps (gpu_sweep.sh): alone, the table as before; beside pose-error
    # runs (even in one folder), each row names its study
    run("m", "shared", 0, 28.0, 0.01, study="mount-error")
    run("m", "shared", 2, 27.5, 0.2, study="mount-error")
    assert study_sweep.main([str(tmp_path / "m")]) == 0
    assert (
        "| blocks | shared | 2° | 27.50 | 0.200 | — |" in (tmp_path / "m" / "sweep.md").read_text()
    )
    run("m", "shared", 0, 29.0, study="pose-error")
    assert study_sweep.main([str(tmp_path / "m")]) == 0
    rows = json.loads((tmp_path / "m" / "sweep.json").read_text())["runs"]
    assert [(r["study"], r["level"]) for r in rows] == [
        ("mount-error", 0.0),
        ("mount-error", 2.0),
        ("pose-error", 0.0),
    ]
    md = (tmp_path / "m" / "sweep.md").read_text()
    assert "| option | study | level |" in md and "| shared | mount-error | 2° | 27.50 |" in md


@pytest.mark.parametrize(
    "module, args",
    [
        ("step_ops", ["--scene", "S"]),
        ("profile_step", ["--scene", "S"]),
        ("error_vs_time", ["--scenes", "S"]),
        ("cpu_preset", ["--scene", "S"]),
        ("knobs", []),
        ("mesh_texture", ["RUN"]),
        ("mount_gauge", ["--scene", "S"]),
    ],
)
def test_an_out_that_is_a_file_is_refused_before_any_work(module, args, tmp_path, capsys):
    import importlib

    bench = importlib.import_module(f"benchmarks.{module}")
    taken = tmp_path / "notes.txt"
    taken.write_text("keep")
    for out in (taken, taken / "sub"):  # a file, and a folder under a file
        assert bench.main([*args, "--out", str(out)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith(f"{module}: error: --out {out}"), err
    assert taken.read_text() == "keep"


def test_step_time_times_variants_side_by_side_on_cpu(tiny_scene, tmp_path):
    from benchmarks import step_time

    out = tmp_path / "steps"
    refine = 'refine={"train": {"refine_poses": true, "step_mode": "graph"}}'
    argv = ["--scene", str(tiny_scene), "--device", "cpu", "--warmup", "2", "--steps", "3"]
    argv += ["--variant", 'plain={"train": {"step_mode": "graph"}}', "--variant", refine]
    assert step_time.main(argv + ["--out", str(out), "--quiet"]) == 0
    res = json.loads((out / "step_time.json").read_text())
    plain, refined = res["rows"]
    assert plain["ratio"] == 1.0 and refined["ratio"] > 0 and refined["ms_per_step"] > 0
    assert plain["step_mode"] == refined["step_mode"] == "graph"  # eager body on a CPU
    assert plain["samples_per_ray"] > 0 and refined["variant"] == "refine"
    md = (out / "step_time.md").read_text()
    assert "CPU numbers" in md and "| refine |" in md
    bad = argv[:6] + ["--variant", "a={}", "--variant", "a={}", "--out", str(tmp_path / "x")]
    assert step_time.main(bad) == 2
    assert step_time.main(argv[:6] + ["--budget-s", "0", "--out", str(tmp_path / "y")]) == 2
    assert not (tmp_path / "y" / "step_time.json").exists()


def test_compare_runs_plots_one_panel_per_prefix_and_refuses_a_missing_folder(tmp_path, capsys):
    from benchmarks import compare_runs

    for name, psnr in (("a", [20.0, 25.0]), ("b", [21.0, 24.0])):
        (tmp_path / name).mkdir()
        pts = [{"train_s": t, "psnr": v} for t, v in zip((1.0, 2.0), psnr, strict=True)]
        runs = {"runs": [{"points": [{"train_s": 0.0, "psnr": 10.0}, *pts]}]}
        (tmp_path / name / "error_vs_time.json").write_text(json.dumps(runs))
    assert compare_runs.load_points(tmp_path / "a") == [(1.0, 20.0), (2.0, 25.0)]
    assert compare_runs.parse_item("0°:lr=1e-3=d") == ("0°", "lr=1e-3", "d")
    out = tmp_path / "cmp.png"
    items = [f"0°:x={tmp_path / 'a'}", f"1°:x={tmp_path / 'b'}", f"1°:y={tmp_path / 'a'}"]
    assert compare_runs.main([str(out), *items]) == 0
    h, w = iio.imread(out).shape[:2]
    assert w > 1.8 * h  # two panels side by side
    assert compare_runs.main([str(tmp_path / "no.png"), f"x={tmp_path / 'c'}"]) == 2
    assert "no error_vs_time.json here" in capsys.readouterr().err
    assert not (tmp_path / "no.png").exists()
    notes = tmp_path / "notes.txt"
    notes.write_text("mine")
    for bad in (str(notes), str(notes / "x.png"), str(tmp_path / "a")):  # not a png / no folder
        assert compare_runs.main([bad, items[0]]) == 2
    assert notes.read_text() == "mine"


def test_compare_runs_plots_the_pose_error_and_refuses_a_run_without_it(tmp_path, capsys):
    from benchmarks import compare_runs

    pts = [{"train_s": t, "psnr": 30.0, "pose_error_deg": e} for t, e in ((1, 0.1), (2, 0.02))]
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "error_vs_time.json").write_text(json.dumps({"runs": [{"points": pts}]}))
    assert compare_runs.load_points(tmp_path / "a", "pose_error_deg") == [(1, 0.1), (2, 0.02)]
    out = tmp_path / "pose.png"
    assert compare_runs.main([str(out), f"r={tmp_path / 'a'}", "--metric", "pose_error_deg"]) == 0
    assert iio.imread(out).ndim == 3
    no = tmp_path / "no.png"  # the pose-to-pose part: these points have none
    assert compare_runs.main([str(no), f"r={tmp_path / 'a'}", "--metric", "pose_jitter_deg"]) == 2
    assert "records no pose_jitter_deg" in capsys.readouterr().err and not no.exists()
    for p in pts:
        p["pose_jitter_deg"] = p["pose_error_deg"] / 2
    (tmp_path / "a" / "error_vs_time.json").write_text(json.dumps({"runs": [{"points": pts}]}))
    assert compare_runs.load_points(tmp_path / "a", "pose_jitter_deg") == [(1, 0.05), (2, 0.01)]
    jit = tmp_path / "jitter.png"
    assert compare_runs.main([str(jit), f"r={tmp_path / 'a'}", "--metric", "pose_jitter_deg"]) == 0
    for p in pts:
        del p["pose_error_deg"]
    (tmp_path / "a" / "error_vs_time.json").write_text(json.dumps({"runs": [{"points": pts}]}))
    assert compare_runs.main([str(no), f"r={tmp_path / 'a'}", "--metric", "pose_error_deg"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "records no pose_error_deg" in err[0]
    assert not no.exists()


def test_gpu_runs60_bad_input_is_one_line_exit_2_and_leaves_out_alone(tmp_path):
    """benchmarks/gpu_runs60.sh refuses a missing DATA or RUNS, an existing OUT, an OUT it
    cannot make and a WAIT_READY that is no number, before it runs or writes anything."""
    script = Path(__file__).parents[1] / "benchmarks" / "gpu_runs60.sh"
    runs = tmp_path / "runs.txt"
    runs.write_text("plain scene\n")
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.json").write_text("{}")
    blocker = tmp_path / "file"
    blocker.write_text("x")
    cases = [
        ([], {}, "usage"),
        ([str(tmp_path / "no-data"), str(tmp_path / "o1"), str(runs)], {}, "is not a folder"),
        ([str(tmp_path), str(tmp_path / "o2"), str(tmp_path / "no-runs")], {}, "readable file"),
        ([str(tmp_path), str(out), str(runs)], {}, "exists"),
        ([str(tmp_path), str(blocker / "o3"), str(runs)], {}, "cannot be made"),
        ([str(tmp_path), str(tmp_path / "o4"), str(runs)], {"WAIT_READY": "x"}, "WAIT_READY"),
    ]
    for args, extra, words in cases:
        env = {**os.environ, **extra}
        r = subprocess.run(["bash", str(script), *args], capture_output=True, text=True, env=env)
        err = r.stderr.strip()
        assert r.returncode == 2 and len(err.splitlines()) == 1 and words in err, (args, err)
    assert sorted(p.name for p in out.iterdir()) == ["keep.json"]
    assert not any((tmp_path / n).exists() for n in ("o1", "o2", "o4"))


def test_gpu_runs60_skips_a_scene_whose_data_never_arrives(tmp_path):
    """WAIT_READY: a run waits for DATA/SCENE.ready; one that does not come is logged as
    skipped, and the list still ends (all.done), running nothing for it."""
    script = Path(__file__).parents[1] / "benchmarks" / "gpu_runs60.sh"
    (tmp_path / "data" / "late").mkdir(parents=True)
    runs = tmp_path / "runs.txt"
    runs.write_text("# a comment\nfirst late refine_poses=true\n")
    out = tmp_path / "out"
    env = {**os.environ, "WAIT_READY": "1", "PY": "false"}
    r = subprocess.run(
        ["bash", str(script), str(tmp_path / "data"), str(out), str(runs)],
        capture_output=True,
        text=True,
        env=env,
    )
    assert r.returncode == 0, r.stderr
    log = (out / "progress.log").read_text()
    assert "late first skipped" in log and (out / "all.done").exists()
    assert not (out / "late").exists()


def test_gpu_poll_packs_results_without_checkpoints(tmp_path):
    """gpu_poll.sh: once every list is done, RESULTS' JSON (lines too, gzipped traces), Markdown
    and logs go to $OUT/res.tgz, checkpoints left out; in a job's folder only the job's own
    all.done ends the wait; bad arguments are one line and exit code 2."""
    import tarfile

    script = Path(__file__).parents[1] / "benchmarks" / "gpu_poll.sh"
    res = tmp_path / "o20"
    run = res / "a" / "plant" / "none0"
    run.mkdir(parents=True)
    (run / "error_vs_time.json").write_text("{}")
    (run / "metrics.jsonl").write_text("{}\n")
    (run / "ckpt.pt").write_bytes(b"x" * 100)
    (run / "trace.json.gz").write_bytes(b"x" * 10)  # profile_step --trace
    (res / "a" / "progress.log").write_text("[00:00:01 +0s] plant none0 rc 0\n")
    (res / "a" / "all.done").touch()
    back = tmp_path / "back"
    back.mkdir()
    env = {**os.environ, "OUT": str(back)}
    r = subprocess.run(
        ["bash", str(script), str(res), "30"], capture_output=True, text=True, env=env
    )
    assert r.returncode == 0 and "all done" in r.stdout, r.stderr
    with tarfile.open(back / "res.tgz") as t:
        names = set(t.getnames())
    assert "o20/a/plant/none0/error_vs_time.json" in names and "o20/a/progress.log" in names
    assert "o20/a/plant/none0/metrics.jsonl" in names
    assert "o20/a/plant/none0/trace.json.gz" in names
    assert not any(n.endswith(".pt") for n in names)
    # a job's own folder (its progress.log): a finished list is not the job's end
    (res / "progress.log").write_text("[00:00:00] start\n")
    r = subprocess.run(
        ["bash", str(script), str(res), "0"], capture_output=True, text=True, env=env
    )
    assert r.returncode == 0 and "still running" in r.stdout, r.stderr
    (res / "all.done").touch()
    r = subprocess.run(
        ["bash", str(script), str(res), "0"], capture_output=True, text=True, env=env
    )
    assert "all done" in r.stdout
    for args in ([], [str(tmp_path / "nothing"), "5"], [str(res), "soon"]):
        r = subprocess.run(["bash", str(script), *args], capture_output=True, text=True, env=env)
        assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1


def test_run_table_phases_give_step_time_between_points(tmp_path, capsys):
    """run_table --phases: ms per step between the points at consecutive --at times ("—"
    where a point is missing), the first point from which most steps compacted, the last
    compositing share; fewer than two times, or --base, refused in one line."""
    from benchmarks import run_table

    pts = [
        {"target_s": 1.0, "train_s": 1.0, "step": 100, "compacted_share": 0.0},
        {"target_s": 5.0, "train_s": 5.0, "step": 300, "compacted_share": 0.2},
        {"target_s": 12.0, "train_s": 12.0, "step": 1000, "compacted_share": 1.0},
    ]
    pts[-1]["compositing_share"] = 0.61
    folder = tmp_path / "s" / "none0"
    folder.mkdir(parents=True)
    (folder / "error_vs_time.json").write_text(json.dumps({"runs": [{"points": pts}]}))
    assert run_table.main([str(folder), "--phases", "--at", "1", "5", "12", "30"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[0] == "| run | 1–5 s | 5–12 s | 12–30 s | compacting from | share |"
    assert lines[2] == "| s/none0 | 20.00 | 10.00 | — | 12 s | 0.61 |"
    for bad, words in (
        ([str(folder), "--phases", "--at", "5"], "two --at times"),
        ([str(folder), "--phases", "--base", "none0"], "--base"),
    ):
        assert run_table.main(bad) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and words in err[0], (bad, err)


def test_gpu_carry_scene_cuts_a_scene_into_carries_whichever_completes_joins(tmp_path):
    """gpu_carry_scene.sh: parts of PART_MB MiB whose stage.sh scripts, run in any order, land
    the scene byte for byte in DATA and touch DATA/NAME.ready only once every part is there
    (in order, or the last part first); bad arguments are one line and exit code 2, nothing
    written, old parts left alone."""
    script = Path(__file__).parents[1] / "benchmarks" / "gpu_carry_scene.sh"
    scene = tmp_path / "big"
    (scene / "test").mkdir(parents=True)
    blob = np.random.default_rng(0).bytes(int(2.5 * 2**20))
    (scene / "events.npz").write_bytes(blob)
    (scene / "test" / "poses.npz").write_bytes(b"poses")

    def run(*args, data=None):
        env = {**os.environ, **({"DATA": str(data)} if data else {})}
        return subprocess.run(["bash", *map(str, args)], capture_output=True, text=True, env=env)

    r = run(script, scene, tmp_path / "c" / "big", 1)
    assert r.returncode == 0, r.stderr
    parts = sorted((tmp_path / "c").iterdir())
    assert [p.name for p in parts] == ["big.p0", "big.p1", "big.p2"]
    for name, order in (("data", parts), ("backwards", [parts[-1], *parts[:-1]])):
        data = tmp_path / name
        for i, p in enumerate(order):
            assert not (data / "big.ready").exists() and not (data / "big").exists()
            r = run(p / "stage.sh", data=data)
            assert r.returncode == 0, r.stderr
            assert f"{i + 1} of 3 here" in r.stdout or i == 2
        assert (data / "big.ready").exists()
        assert (data / "big" / "events.npz").read_bytes() == blob
        assert (data / "big" / "test" / "poses.npz").read_bytes() == b"poses"
        assert sorted(x.name for x in data.iterdir()) == ["big", "big.ready"]  # parts gone
    before = {p: sorted(x.name for x in p.iterdir()) for p in parts}
    for args, words in (
        ([], "usage"),
        ([tmp_path / "none", tmp_path / "x"], "is not a folder"),
        ([scene, tmp_path / "y", "0"], "PART_MB"),
        ([scene, tmp_path / "c" / "big"], "exists"),
        ([scene, scene / "events.npz" / "big"], "cannot be made"),
    ):
        r = run(script, *args)
        err = r.stderr.strip()
        assert r.returncode == 2 and len(err.splitlines()) == 1 and words in err, (args, err)
    assert not any((tmp_path / n).exists() for n in ("x.p0", "y.p0"))
    assert before == {p: sorted(x.name for x in p.iterdir()) for p in parts}


def test_gpu_stage_parts_pieces_rejoin_to_the_same_warp_so(tmp_path):
    """gpu_stage_parts.sh: the cached xz stream cut into PART_MB carries whose stage.sh scripts
    and the last one's activate.sh rebuild warp.so byte for byte (and the later calls'
    activate.sh); activating with a piece missing is refused; bad input is one line and exit
    code 2 with the old pieces left alone."""
    script = Path(__file__).parents[1] / "benchmarks" / "gpu_stage_parts.sh"
    cache = tmp_path / "cache" / "gpu-warp-1.19.0"
    cache.mkdir(parents=True)
    so = np.random.default_rng(1).bytes(int(3.5 * 2**20))
    xz = subprocess.run(["xz", "-0", "-c"], input=so, capture_output=True, check=True).stdout
    (cache / "warp.so.xz.part00").write_bytes(xz[: len(xz) // 2])
    (cache / "warp.so.xz.part01").write_bytes(xz[len(xz) // 2 :])
    with zipfile.ZipFile(cache / "warp_rest.zip", "w") as z:
        z.writestr("warp/__init__.py", "")
    work, machine = tmp_path / "work", tmp_path / "machine"
    work.mkdir()
    env = {
        **os.environ,
        "XDG_CACHE_HOME": str(tmp_path / "cache"),
        "PART_MB": "2",
        "GPU_WARP_DIR": str(machine / "gw"),
        "GPU_WARP_SITE": str(machine / "site"),
    }

    def run(cmd, **extra):
        return subprocess.run(
            ["bash", "-c", cmd], capture_output=True, text=True, cwd=work, env={**env, **extra}
        )

    r = run(f"bash {script}")
    assert r.returncode == 2 and "no staged Warp" in r.stderr  # no done mark yet
    (cache / "done").touch()
    assert run(f"bash {script}").returncode == 0
    n = math.ceil(len(xz) / 2**20)  # PART_MB - 1 MiB of the stream a piece
    pieces = sorted(p.name for p in work.iterdir())
    assert n >= 3 and pieces == [f".gpu-wp-{i:02d}" for i in range(n)]
    assert all((work / p / "stage.sh").exists() for p in pieces)
    activate = f". {pieces[-1]}/activate.sh && echo $PYTHONPATH"
    r = run(" && ".join(f"bash {p}/stage.sh" for p in pieces[:-2]) + f" && {activate}")
    assert r.returncode == 1 and "pieces missing" in r.stderr
    r = run(f"bash {pieces[-2]}/stage.sh && {activate}")
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip().splitlines()[-1].split(":")[0] == str(machine / "site")
    assert (machine / "site" / "warp" / "bin" / "warp.so").read_bytes() == so
    assert (machine / "site" / "warp" / "__init__.py").exists()
    later = run(f". {machine / 'gw' / 'activate.sh'} && echo $PYTHONPATH")
    assert later.stdout.strip().split(":")[0] == str(machine / "site")
    before = sorted(str(p.relative_to(work)) for p in work.rglob("*"))
    for extra, words in (
        ({"PART_MB": "1"}, "PART_MB"),
        ({"XDG_CACHE_HOME": str(work)}, "no staged"),
    ):
        r = run(f"bash {script}", **extra)
        err = r.stderr.strip()
        assert r.returncode == 2 and len(err.splitlines()) == 1 and words in err, err
    assert before == sorted(str(p.relative_to(work)) for p in work.rglob("*"))


def test_run_table_rows_deltas_and_refusals(tmp_path, capsys):
    """run_table: PSNR at the asked times ("—" where none was scheduled), Δ against the same
    scene's --base row, step time, samples, buffer slots, compaction, error left, its jitter, the
    largest correction and settled_at from the run's config.json (↺ where the field restarted
    there); --out is written once, an existing one refused and left alone."""
    from benchmarks import run_table

    def result(folder, psnrs, settled, restart=None, **last):
        pts = [
            {"target_s": t, "train_s": t + 0.01, "psnr": v, "step": 100 * t}
            for t, v in zip((5.0, 10.0, 60.0), psnrs, strict=True)
        ]
        pts[-1].update(last)
        run = {"points": pts, "train_s": 60.0, "step": 10_000}
        folder.mkdir(parents=True)
        (folder / "error_vs_time.json").write_text(json.dumps({"runs": [run]}))
        conf = folder / "runs" / "s-ngp" / "config.json"
        conf.parent.mkdir(parents=True)
        calib = None if settled is None else {"poses": {"settled_at": settled}}
        conf.write_text(json.dumps({"self_calibration": calib, "field_restart": restart}))

    out = tmp_path / "res" / "s"
    result(out / "none0", (30.0, 31.0, 32.0), None, samples_per_step=9e5)
    result(
        out / "ref2",
        (25.0, 26.0, 29.5),
        0.27,
        samples_per_step=1.4e6,
        marched_per_step=2.1e6,
        compacted_share=1.0,
        trained_slots=1_802_240,
        graph_captures=7,
        graph_returns=12,
        pose_error_deg=0.0871,
        pose_jitter_deg=0.0312,
        pose_correction_max_deg=9.4981,
    )
    restart = {"step": 300, "progress": 0.31, "restarts": 1}  # refine_restart's new field
    result(out / "rs2", (25.0, 26.0, 30.5), 0.31, restart=restart)
    args = [str(out / "none0"), str(out / "ref2"), "--at", "5", "15", "60", "--base", "none0"]
    assert run_table.main(args) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[0].startswith("| run | 5 s | 15 s | 60 s | Δ | ms/step |") and len(lines) == 4
    none0 = "| s/none0 | 30.00 | — | 32.00 | +0.00 | 6.00 | 0.90 | — | — | — | — | — | — | — | — |"
    assert lines[2] == none0
    assert lines[3] == (
        "| s/ref2 | 25.00 | — | 29.50 | -2.50 | 6.00 | 1.40 | 2.10 | 1.80 | 7 (12 back) | 1.00 "
        "| 0.087° | 0.031° | 9.50° | 27% |"
    )
    assert run_table.main([str(out / "rs2")]) == 0
    assert capsys.readouterr().out.strip().splitlines()[-1].endswith("| 31% ↺ |")
    table = tmp_path / "t.md"
    assert run_table.main([f"mine={out / 'ref2'}", "--out", str(table)]) == 0
    assert "| mine | 25.00 | 26.00 | — | — | 29.50 | — |" in table.read_text()
    capsys.readouterr()
    for bad, words in (
        ([str(out / "ref2"), "--out", str(table)], "exists"),
        ([str(out / "ref2"), "--out", str(tmp_path / "t.txt")], ".md file"),
        ([str(tmp_path / "nothing")], "no error_vs_time.json here"),
        ([str(out / "ref2"), "--at", "0"], "--at"),
        ([str(out / "ref2"), "--out", str(table / "under-a-file.md")], "cannot be written"),
    ):
        assert run_table.main(bad) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and words in err[0], (bad, err)
    assert "| mine |" in table.read_text() and not (tmp_path / "t.txt").exists()


def test_capacity_replay_counts_what_each_patience_would_have_recaptured(tmp_path, capsys):
    """`python -m benchmarks.capacity_replay`: a run's capacity readings through
    `SampleCapacity` at each patience. Readings with one low in three (at the 32,768-slot
    quantum) flap at patience 1, each shrink letting a later high reading overflow, and hold
    at 3; a run's own headroom is used; a run without readings, a bad --patience or an
    existing --out is one line and exit code 2, and the file is left as it was."""
    from benchmarks import capacity_replay

    q = 1 << 15
    high, low = 9 * q, 7 * q  # sized 10 and 8 quanta at headroom 1.1: a shrink of two

    def result(folder, readings, **options):
        pts = [{"target_s": 1.0, "train_s": 1.0, "step": 1, "psnr": 20.0}]
        pts += [{**pts[0], "capacity_readings": r} for r in readings]
        run = {"points": pts, "train_config": {"backend_options": options}}
        folder.mkdir(parents=True)
        (folder / "error_vs_time.json").write_text(json.dumps({"runs": [run]}))

    seq = [high, high] + [low, high, high] * 10
    result(tmp_path / "s" / "flap", [seq[:11], [], seq[11:]])
    result(tmp_path / "s" / "roomy", [seq], capacity_headroom=1.5, capacity_shrink_below=0.5)
    result(tmp_path / "s" / "old", [None])
    argv = [str(tmp_path / "s" / "flap"), str(tmp_path / "s" / "roomy"), "--patience", "1", "3"]
    assert capacity_replay.main(argv) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[-2] == "| s/flap | 32 | 20 (19) · +0.0% · 10 | 0 (0) · +6.7% · 0 |"
    assert lines[-1] == "| s/roomy | 32 | 0 (0) · +0.0% · 0 | 0 (0) · +0.0% · 0 |"
    table = tmp_path / "t.md"
    assert capacity_replay.main([str(tmp_path / "s" / "flap"), "--out", str(table)]) == 0
    kept = table.read_text()
    assert "| s/flap | 32 | 20 (19) · +0.0% · 10 |" in kept
    capsys.readouterr()
    for bad, words in (
        ([str(tmp_path / "s" / "old")], "no capacity_readings"),
        ([str(tmp_path / "s" / "flap"), "--patience", "0"], "--patience"),
        ([str(tmp_path / "s" / "flap"), "--out", str(table)], "exists"),
    ):
        assert capacity_replay.main(bad) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and words in err[0], (bad, err)
    assert table.read_text() == kept


def test_kernels_render_refuses_bad_numbers_and_outputs_in_one_line(tmp_path, capsys):
    from benchmarks import kernels_render

    folder = tmp_path / "a_folder.pt"
    folder.mkdir()
    (folder / "keep").write_text("keep")
    for bad, words in (
        (["--n-rays", "-3"], "--n-rays must be at least 1"),
        (["--repeats", "0"], "--repeats must be at least 1"),
        (["--mean-samples", "0"], "--mean-samples must be at least 1"),
        (["--dump", str(folder)], "a_folder.pt"),
    ):
        assert kernels_render.main(["--device", "cpu", *bad]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("kernels_render: error:") and words in err[0]
    assert (folder / "keep").read_text() == "keep"  # nothing touched


def test_explicit_syncs_names_the_line_that_waits_and_restores_the_entry_points():
    """Every wrapped call is counted against the caller's own file and line (not torch's or
    Warp's), the wrapped function still runs, and leaving the context restores the originals."""
    import sys

    import torch
    import warp as wp

    from benchmarks.explicit_syncs import ExplicitSyncs

    before = (wp.synchronize, torch.cuda.synchronize, torch.cuda.Event.synchronize)
    with ExplicitSyncs() as syncs:
        assert wp.synchronize is not before[0]
        for _ in range(3):
            wp.synchronize()  # a no-op without CUDA, counted all the same
        line = sys._getframe().f_lineno - 1
        wp.synchronize_device("cpu")
    assert (wp.synchronize, torch.cuda.synchronize, torch.cuda.Event.synchronize) == before
    here = f"{Path(__file__).name}:{line}"
    assert syncs.per_step(2) == 2.0
    (first, n), (second, m) = syncs.calls.most_common()
    assert n == 3 and m == 1
    assert here in first and "[warp.synchronize]" in first and "(test_explicit_syncs" in first
    assert "[warp.synchronize_device]" in second
    assert syncs.examples(1) == [f"{first} x3"]


def test_trace_syncs_names_the_calls_before_a_device_wide_sync(tmp_path, capsys):
    """trace_syncs: each cudaDeviceSynchronize of a (gzipped) Chrome trace, on any thread,
    counted by what contains it and the events of its thread that ended last before it,
    with the device idle gap it returned in (a call that returned while a kernel ran: none).
    Bad input: one line, exit 2, an existing --out left alone."""
    import gzip

    from benchmarks import trace_syncs

    def x(name, ts, dur, cat="cpu_op", tid=1):
        return {"ph": "X", "name": name, "ts": ts, "dur": dur, "cat": cat, "pid": 0, "tid": tid}

    events = [
        x("grid_update", 0, 10, "user_annotation"),
        x("aten::copy_", 2, 3),
        x("cudaGraphLaunch", 12, 2, "cuda_runtime"),
        x("cudaDeviceSynchronize", 20, 30, "cuda_runtime"),
        x("cudaDeviceSynchronize", 60, 1, "cuda_runtime", tid=2),
        x("step", 100, 50, "user_annotation"),
        x("aten::copy_", 102, 3),
        x("cudaGraphLaunch", 112, 2, "cuda_runtime"),
        x("cudaDeviceSynchronize", 120, 30, "cuda_runtime"),  # the same context, in `step`
        x("march", 0, 30, "kernel", tid=7),
        x("mlp", 55, 15, "kernel", tid=7),
        x("hash", 160, 5, "kernel", tid=7),
        x("grid_update", 18, 0.0, "user_annotation", tid=7),
    ]
    path = tmp_path / "trace.json.gz"
    path.write_bytes(gzip.compress(json.dumps({"traceEvents": events}).encode()))
    rows = trace_syncs.sync_contexts(trace_syncs.load_trace(path), "cudaDeviceSynchronize", 2)
    # gaps 30-55 (the first call returns in it at 50) and 70-160 (the third at 150; the
    # second thread's call returned at 61, while mlp ran)
    assert [(r["calls"], r["idle_us"], r["in"], r["after"]) for r in rows] == [
        (1, 90.0, ["step"], ["aten::copy_", "cudaGraphLaunch"]),
        (1, 25.0, [], ["grid_update", "cudaGraphLaunch"]),
        (1, 0.0, [], []),
    ]
    out = tmp_path / "syncs.md"
    assert trace_syncs.main([str(path), "--before", "2", "--out", str(out)]) == 0
    md = out.read_text()
    assert "| 1 | 0.090 | step | aten::copy_ › cudaGraphLaunch |" in md
    assert "(3 calls)" in md
    capsys.readouterr()
    for bad in ([str(tmp_path / "none.json.gz")], [str(out)], [str(path), "--out", str(out)]):
        assert trace_syncs.main(bad) == 2
        assert len(capsys.readouterr().err.strip().splitlines()) == 1
    assert out.read_text() == md


def test_trace_gaps_puts_each_device_gap_in_one_class(tmp_path, capsys):
    """trace_gaps: a gap ended by work launched after it began is the host's (named by the
    innermost host op then running on the launching thread), one launched before it began is
    queued, one between two nodes of a graph replay is in the graph, one with no launch call
    unlinked; per step from the profile_step.json above the run folder. Bad input: one line,
    exit 2, an existing --out left alone."""
    import gzip

    from benchmarks import trace_gaps

    def x(name, ts, dur, cat="cpu_op", tid=1, corr=None):
        e = {"ph": "X", "name": name, "ts": ts, "dur": dur, "cat": cat, "pid": 0, "tid": tid}
        return e | ({"args": {"correlation": corr}} if corr is not None else {})

    events = [
        x("sample_rays", 0, 40, "user_annotation"),
        x("aten::copy_", 30, 8),
        x("cudaLaunchKernel", 2, 1, "cuda_runtime", corr=1),
        x("cudaMemcpyAsync", 32, 2, "cuda_runtime", corr=2),  # issued after fill ended
        x("cudaGraphLaunch", 36, 3, "cuda_runtime", corr=3),  # issued before copy ended
        x("fill", 5, 10, "kernel", tid=7, corr=1),
        x("Memcpy HtoD", 35, 5, "gpu_memcpy", tid=7, corr=2),  # host late: 15-35
        x("march", 44, 6, "kernel", tid=7, corr=3),  # queued: 40-44
        x("mlp", 50.5, 1, "kernel", tid=7, corr=3),  # in graph: 50-50.5
        x("Memset", 60, 1, "gpu_memset", tid=7, corr=99),  # unlinked: 51.5-60
    ]
    run = tmp_path / "prof" / "run"
    run.mkdir(parents=True)
    path = run / "trace.json.gz"
    path.write_bytes(gzip.compress(json.dumps({"traceEvents": events}).encode()))
    (tmp_path / "prof" / "profile_step.json").write_text(json.dumps({"steps": 2}))
    gaps = trace_gaps.classify_gaps(trace_gaps.load_trace(path))
    assert [(g["cls"], g["idle_us"], g["before"], g["after"]) for g in gaps] == [
        ("host late", 20.0, "fill", "Memcpy HtoD"),
        ("queued", 4.0, "Memcpy HtoD", "march"),
        ("in graph", 0.5, "march", "mlp"),
        ("unlinked", 8.5, "mlp", "Memset"),
    ]
    assert gaps[0]["host"] == "sample_rays" and gaps[0]["launch"] == "cudaMemcpyAsync"
    assert trace_gaps.profiled_steps(path) == 2.0
    # several variants side by side: the steps of the variant whose folder holds the trace
    side = tmp_path / "side"
    (side / "fr").mkdir(parents=True)
    rows = [
        {"backend": "ngp, variant base", "steps": 3},
        {"backend": "ngp, variant fr", "steps": 4},
    ]
    (side / "profile_step.json").write_text(json.dumps({"variants": rows}))
    assert trace_gaps.profiled_steps(side / "fr" / "trace.json.gz") == 4.0
    s = trace_gaps.summary(gaps, 2.0)
    assert s["classes"][0] == ("host late", 0.01, 0.5)
    assert s["host_doing"] == [("sample_rays", 0.01)]
    out = tmp_path / "gaps.md"
    assert trace_gaps.main([str(path), "--out", str(out)]) == 0
    md = out.read_text()
    assert "0.017 ms a step over 2 steps" in md and "| queued | 0.002 | 0.5 |" in md
    # the device's own time: busy is the union of its events, every kernel in a kind
    busy = trace_gaps.device_time(trace_gaps.load_trace(path), 2.0)
    assert busy["busy_ms"] == pytest.approx(23 / 2e3) and busy["span_ms"] == pytest.approx(0.028)
    assert busy["device_ms"] == pytest.approx({"torch other": 17 / 2e3, "march": 0.003})
    assert "(41 % of the profiled span" in md and "| march | 0.003 |" in md
    capsys.readouterr()
    for bad in (
        [str(tmp_path / "none.json.gz")],
        [str(path), "--steps", "0"],
        [str(path), "--out", str(out)],
    ):
        assert trace_gaps.main(bad) == 2
        assert len(capsys.readouterr().err.strip().splitlines()) == 1
    assert out.read_text() == md


def test_error_vs_time_refused_for_a_bad_option_makes_no_folder(tiny_scene, tmp_path, capsys):
    """An option the trainer would refuse (here a backend option out of range, checked only
    where the config is resolved for the scene) stops the benchmark before its --out folder
    exists: one line, exit 2, nothing left behind."""
    from benchmarks import error_vs_time

    out = tmp_path / "evt"
    argv = ["--scenes", str(tiny_scene), "--out", str(out), "--device", "cpu", "--quiet"]
    for bad in ("update_offset=-1", "samples_per_step=10"):
        assert error_vs_time.main([*argv, "--backends", "ngp", "--set", bad]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("error_vs_time: error:")
        assert not out.exists()


def test_a_refused_benchmark_removes_the_empty_out_folder_it_made(tiny_scene, tmp_path, capsys):
    """A study refused only once its levels' trainers resolve (after making --out) leaves no
    folder behind; a folder that existed before, or one a run wrote a file into, is kept."""
    from benchmarks import study
    from benchmarks.cli import drop_if_empty

    argv = [str(tiny_scene), "--device", "cpu", "--steps", "1", "--quiet"]
    bad = ["--set", "update_offset=-1"]
    out = tmp_path / "study"
    assert study.main(["pose-error", *argv, "--out", str(out / "inner"), *bad]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1
    assert not out.exists()  # the folders it made on the way too
    out.mkdir()
    assert study.main(["pose-error", *argv, "--out", str(out), *bad]) == 2
    assert out.is_dir()  # there before the run: not the run's to remove
    (out / "a" / "b").mkdir(parents=True)
    (out / "a" / "keep.txt").write_text("x")
    drop_if_empty(out)
    assert (out / "a" / "keep.txt").read_text() == "x"
    (out / "a" / "keep.txt").unlink()
    drop_if_empty(out)
    assert not out.exists()


def test_graph_relaunch_times_each_pattern_and_refuses_a_cpu(tiny_scene, tmp_path, capsys):
    """graph_relaunch: ms per call of each replay pattern and its ratio to the drained one
    (here plain functions on the CPU's clock: the slow one's ratio shows); on a CPU the
    benchmark itself is refused in one line, exit 2, leaving no --out folder."""
    import time as _time

    import torch

    from benchmarks import graph_relaunch

    calls = []

    def slow(i):
        calls.append(i)
        _time.sleep(0.002)

    fast = {k: (lambda _i: None) for k in graph_relaunch.PATTERNS}
    res = graph_relaunch.relaunch_times(
        {**fast, "alone": slow, "as trained": slow}, 5, torch.device("cpu")
    )
    assert set(res["ms"]) == set(graph_relaunch.PATTERNS) and len(calls) == 10
    assert res["ms"]["alone"] >= 2.0 and res["ms"]["as trained"] >= 2.0
    assert res["over_alone"]["back to back"] < 0.5 < res["over_alone"]["as trained"]
    md = graph_relaunch.markdown(
        {**res, "scene": "s", "rays_per_step": 4096, "warmup": 0, "replays": 5}
    )
    assert "| alternating |" in md and "| alone |" in md
    out = tmp_path / "gr"
    argv = ["--scene", str(tiny_scene), "--device", "cpu", "--out", str(out)]
    assert graph_relaunch.main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "needs CUDA" in err[0] and not out.exists()


def test_fused_mlp_probe_is_float64s_mlp_and_refuses_bad_input(tmp_path, capsys):
    """The tile-fused MLPs' outputs and gradients (Warp's CPU tiles; the density and the
    colour network's shapes; two backward blocks, each summing 16 tiles' weight gradients)
    are the float64 MLPs' within float16 rounding, as torch's float16 MLPs are (at 2,048
    samples a few pre-activations round across 0: both ~1 % off in the colour MLP's gx); a
    bad --n, an existing --out or one that is no .json file is one line and exit code 2,
    and an existing file stays as it was."""
    from benchmarks import fused_mlp_probe as probe

    out = tmp_path / "p.json"
    assert probe.main(["--device", "cpu", "--n", "1024", "--out", str(out)]) == 0
    before = out.read_text()
    res = json.loads(before)
    assert res["n"] == 1024 and "torch_ms" not in res["density"]  # no CPU timing
    assert set(res["density"]["scalar"]["errors"]) == {"y", "gx", "gw1", "gw2"}
    assert set(res["colour"]["scalar"]["errors"]) == {"y", "gx", "gw1", "gw2", "gw3"}
    for net in ("density", "colour"):
        assert "cublasdx" not in res[net] and "ms" not in res[net]["scalar"]
        for key, err in res[net]["scalar"]["errors"].items():
            assert err < 2e-2 and err <= 2 * res[net]["torch_errors"][key], (net, key, res)
    progress = capsys.readouterr().err
    assert "density: scalar done" in progress and "colour: scalar done" in progress
    # cuBLASDx is a module option: each variant's kernels are their own, without adjoints
    both = [probe.kernels(v)["_backward2"] for v in probe.VARIANTS]
    assert both[0].module is not both[1].module
    assert [k.module.options["enable_mathdx_gemm"] for k in both] == [False, True]
    assert not any(k.options.get("enable_backward", True) for k in both)
    capsys.readouterr()
    for bad, words in (
        (["--n", "512"], "multiple of 1024"),
        (["--out", str(out)], "exists"),
        (["--out", str(tmp_path / "p.txt")], ".json"),
        (["--out", str(out / "under-a-file.json")], "not a folder"),
        (["--device", "tpu"], "not one of"),
    ):
        assert probe.main(["--device", "cpu", *bad]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and words in err[0], (bad, err)
    assert out.read_text() == before and not (tmp_path / "p.txt").exists()
