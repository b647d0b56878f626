"""The ngp CPU preset: applied on a CPU to the options left unset, never on a GPU."""

import math

import pytest

from fastenerf.backends import get_option, parse_options
from fastenerf.config import (
    FAST_WINDOW_FRACTION,
    NGP_GPU_RAYS,
    SETTLE_PX,
    CylinderConfig,
    IntrinsicsConfig,
    SceneConfig,
    TrainConfig,
    TrajectoryConfig,
    train_preset,
)
from fastenerf.cpu_preset import NGP_CPU_OPTIONS, NGP_CPU_RAYS
from fastenerf.errors import InputError


def scene(cylinder=None) -> SceneConfig:
    return SceneConfig(
        "s",
        64,
        48,
        IntrinsicsConfig(50, 50, 32, 24),
        TrajectoryConfig(),
        aabb=[-1.0, -0.5, -1.0, 1.0, 0.5, 1.0],
        cylinder=cylinder,
    )


def test_cpu_fills_unset_ngp_options_and_rays():
    c = train_preset("fast", "ngp").resolved(scene(), "cpu")
    for key, value in NGP_CPU_OPTIONS.items():
        assert get_option("ngp", c.backend_options, key) == value
    assert get_option("ngp", c.backend_options, "dt_min") is None  # from the field's box
    assert c.rays_per_step == NGP_CPU_RAYS
    opts = parse_options("ngp", c.backend_options)  # valid options, as the field reads them
    assert opts.encoding.n_levels == NGP_CPU_OPTIONS["n_levels"]
    assert c.resolved(scene(), "cpu").backend_options == c.backend_options  # idempotent


def test_user_options_win_flat_or_nested():
    cfg = train_preset(
        "fast",
        "ngp",
        rays_per_step=64,
        backend_options={"encoding": {"n_levels": 12}, "grid_resolution": 64},
    )
    c = cfg.resolved(scene(), "cpu")
    assert get_option("ngp", c.backend_options, "n_levels") == 12
    assert get_option("ngp", c.backend_options, "grid_resolution") == 64
    assert get_option("ngp", c.backend_options, "log2_table_size") == 14
    assert c.rays_per_step == 64
    parse_options("ngp", c.backend_options)  # no key given twice


def test_gpu_and_vanilla_untouched():
    c = train_preset("fast", "ngp").resolved(scene(), "cuda:0")
    assert get_option("ngp", c.backend_options, "log2_table_size") is None
    assert c.rays_per_step == NGP_GPU_RAYS == 4096
    v = TrainConfig(backend="vanilla").resolved(scene(), "cpu")
    assert v.backend_options == {} and v.rays_per_step == 512
    assert TrainConfig(backend="vanilla").resolved(scene(), "cuda:0").rays_per_step == 8192


def test_longer_windows_for_the_fast_preset_on_synthetic_scenes():
    import dataclasses

    synth = dataclasses.replace(scene(), n_views=1000)
    real = dataclasses.replace(synth, kind="real")
    fast = train_preset("fast", "ngp")
    refine = train_preset("fast", "ngp", refine_poses=True)
    assert fast.resolved(synth, "cpu").win_max == round(FAST_WINDOW_FRACTION * 1000) == 200
    assert fast.resolved(synth, "cuda:0").win_max == 200
    assert refine.resolved(synth, "cpu").win_max == 200
    gpu_refine = refine.resolved(synth, "cuda:0")  # the reference's until the poses settle
    assert (gpu_refine.win_max, gpu_refine.settle_win_max) == (50, 200)
    assert gpu_refine.refine_settle_px == SETTLE_PX
    assert refine.resolved(synth, "cpu").refine_settle_px is None  # long throughout on a CPU
    assert fast.resolved(real, "cpu").win_max == 100  # real scenes: not measured, reference's
    assert fast.resolved(real, "cuda:0").win_max == 100
    assert train_preset("eventnerf", "ngp").resolved(synth, "cuda:0").win_max == 50
    assert TrainConfig(backend="vanilla").resolved(synth, "cpu").win_max == 50
    assert train_preset("fast", "ngp", win_max=30).resolved(synth, "cuda:0").win_max == 30
    c = fast.resolved(synth, "cuda:0")
    assert c.resolved(synth, "cuda:0").win_max == 200  # idempotent


def test_windows_that_lengthen_once_the_poses_settle_start_at_the_reference_length():
    import dataclasses

    synth = dataclasses.replace(scene(), n_views=1000)
    real = dataclasses.replace(synth, kind="real")
    settle = train_preset("fast", "ngp", refine_poses=True, refine_settle_px=0.05)
    for device in ("cpu", "cuda:0"):  # the CPU too: without the option it starts long there
        c = settle.resolved(synth, device)
        assert (c.win_max, c.settle_win_max, c.refine_win_max) == (50, 200, 50)
        assert c.resolved(synth, device).settle_win_max == 200  # idempotent
    mine = dataclasses.replace(settle, win_max=30, settle_win_max=20, refine_win_max=10)
    c = mine.resolved(synth, "cuda:0")  # never shorter than where it starts
    assert (c.win_max, c.settle_win_max, c.refine_win_max) == (30, 30, 10)
    for plain in (  # windows of the user's, or a backend, preset or scene with no long ones
        train_preset("fast", "ngp", refine_poses=True, win_max=50).resolved(synth, "cuda:0"),
        train_preset("eventnerf", "ngp", refine_poses=True).resolved(synth, "cuda:0"),
        TrainConfig(backend="vanilla", refine_poses=True).resolved(synth, "cuda:0"),
        train_preset("fast", "ngp", refine_poses=True).resolved(real, "cuda:0"),
    ):
        assert plain.refine_settle_px is None and plain.settle_win_max is None
        assert plain.refine_win_max is None
    with pytest.raises(InputError, match="'refine_settle_px' needs refine_poses"):
        train_preset("fast", "ngp", refine_settle_px=0.05).validate()
    with pytest.raises(InputError, match="'settle_win_max' needs refine_settle_px"):
        train_preset("fast", "ngp", refine_poses=True, settle_win_max=100).validate()


def test_the_cpu_step_follows_the_fields_clipped_box():
    """√3 · the field's box side / 64 (`diagonal_steps`): the box shrunk to the clip
    cylinder where the scene has one; a dt_min the user gives wins."""
    from fastenerf.fields import make_field

    def step(cylinder=None, **options) -> float:
        cfg = train_preset("fast", "ngp", backend_options=options).resolved(scene(cylinder), "cpu")
        return make_field("ngp", scene(cylinder), cfg).sampler.grid.step_size

    steps = NGP_CPU_OPTIONS["diagonal_steps"]
    assert steps == 64
    assert step() == pytest.approx(math.sqrt(3) * 2.0 / steps)  # the box's longest side: 2
    cyl = CylinderConfig(0.25, -0.35, 0.15)  # clips the box to 0.5 x 0.5 x 0.5
    assert step(cyl) == pytest.approx(math.sqrt(3) * 0.5 / steps)
    assert step(dt_min=0.01) == 0.01
    assert step(diagonal_steps=32) == pytest.approx(math.sqrt(3) * 2.0 / 32)


def test_baton_gives_turns_in_a_ring():
    import threading

    from benchmarks.cpu_preset import Baton

    baton, order = Baton(3), []

    def worker(i, steps):
        baton.wait(i)
        for s in range(steps):
            order.append(i)
            if s < steps - 1:
                baton.pass_on(i)
                baton.wait(i)
        baton.leave(i)

    threads = [threading.Thread(target=worker, args=(i, n)) for i, n in enumerate((2, 4, 3))]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=10)
    assert order == [0, 1, 2, 0, 1, 2, 1, 2, 1]


def test_side_by_side_benchmark_on_the_tiny_scene(tiny_scene, tmp_path):
    """Two variants race on the tiny scene; each trains its own seconds and is scored."""
    import json

    from benchmarks import cpu_preset

    tiny = '{"backend_options": {"log2_table_size": 10, "n_levels": 4, "max_resolution": 32}}'
    argv = ["--scene", str(tiny_scene), "--seconds", "1.5", "--out", str(tmp_path)]
    argv += ["--variant", f"a={tiny}", "--variant", "b=" + tiny[:-1] + ', "optimizer": "dense"}']
    assert cpu_preset.main(argv) == 0
    res = json.loads((tmp_path / "cpu_preset.json").read_text())
    rows = {r["variant"]: r for r in res["rows"]}
    assert set(rows) == {"a", "b"}
    for r in rows.values():
        assert r["steps"] > 0 and r["train_seconds"] >= 1.5
        assert r["psnr"] > 0 and r["constant_psnr"] > 0
    md = (tmp_path / "cpu_preset.md").read_text()
    assert "| a |" in md and "Δ constant" in md
    assert cpu_preset.main(argv[:4] + ["--variant", "nope"]) == 2  # one line, not a traceback
