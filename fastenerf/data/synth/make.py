"""Synthetic scene folders: render a turntable revolution, simulate events, write it all.

`make_scene` is what `fastenerf synth` runs; the trainer's tests and the demo call it for
tiny scenes (e.g. 64x48, 100 frames in a few seconds on a CPU).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...config import IntrinsicsConfig, SceneConfig, TrajectoryConfig
from ...errors import InputError
from ..rig import Turntable
from .scenes import SynthScene, build_scene, list_scenes, load_mesh
from .simulator import EventSimulator, SimulatorConfig

FRAME_US = 1000  # one frame per ms: 1000 fps, as the reference's synthetic data
GAMMA = 2.2


@dataclass
class SynthResult:
    """What `make_scene` wrote: folder, event count, stream seconds, wall time (and its split
    into rendering, simulating and writing, seconds)."""

    path: Path
    events: int
    duration_s: float
    frames: int
    wall_s: float
    render_s: float = 0.0
    simulate_s: float = 0.0
    write_s: float = 0.0


def resolve_scene(name_or_mesh: str | Path | SynthScene) -> SynthScene:
    """A built-in scene by name, a user mesh by path, or a ready `SynthScene`."""
    if isinstance(name_or_mesh, SynthScene):
        return name_or_mesh
    s = str(name_or_mesh)
    if isinstance(name_or_mesh, str) and s in list_scenes():
        return build_scene(s)
    p = Path(s)
    if p.suffix or p.exists():
        return load_mesh(p)
    raise InputError(
        f"unknown scene '{s}' (built-in scenes: {', '.join(list_scenes())}; or give a mesh file)"
    )


def scene_config(
    scene: SynthScene,
    width: int,
    height: int,
    frames: int,
    bayer: str | None,
    threshold: float,
    log_eps: float,
) -> SceneConfig:
    """scene.json for a turntable revolution of `frames` frames at 1000 fps."""
    v = scene.view
    intr = v.intrinsics(width, height)
    period = frames * FRAME_US
    b = scene.bounds()
    pad = 0.05
    aabb = np.concatenate([np.maximum(b[0] - pad, -1.0), np.minimum(b[1] + pad, 1.0)])
    return SceneConfig(
        name=scene.name,
        width=width,
        height=height,
        intrinsics=IntrinsicsConfig(intr.fx, intr.fy, intr.cx, intr.cy),
        trajectory=TrajectoryConfig(
            kind="turntable",
            radius=v.radius,
            center=[float(c) for c in v.target],
            elevation_deg=v.elevation_deg,
            period_us=period,
        ),
        bayer=bayer,
        pos_threshold=threshold,
        neg_threshold=threshold,
        t_start_us=0,
        t_end_us=period,
        n_views=frames,
        loop=True,
        aabb=[round(float(a), 4) for a in aabb],
        background=[float(c) for c in scene.background],
        sim_log_eps=log_eps,
        kind="synthetic",
    ).validate("synthetic scene")


def make_scene(
    name_or_mesh: str | Path | SynthScene,
    out: str | Path,
    width: int = 346,
    height: int = 260,
    frames: int = 1000,
    bayer: str | None = "rggb",
    threshold: float = 0.25,
    noise: float = 0.0,
    seed: int = 0,
    test_every: int = 10,
    **options,
) -> Path:
    """Render one turntable revolution, simulate its events, write a scene folder at `out`.

    Frames are at t = i * 1000 µs, i < `frames`; the stream is a closed loop (the last frame
    transitions back to the first at t = frames * 1000 µs). Ground-truth test views (display
    space) are every `test_every`-th frame. `bayer` is "rggb" or None (mono). `options` go to
    `make_scene_result` (fmt, supersample, chunk, progress, sim). Returns the folder.
    """
    return make_scene_result(
        name_or_mesh,
        out,
        width,
        height,
        frames,
        bayer,
        threshold,
        noise,
        seed,
        test_every,
        **options,
    ).path


def make_scene_result(
    name_or_mesh: str | Path | SynthScene,
    out: str | Path,
    width: int = 346,
    height: int = 260,
    frames: int = 1000,
    bayer: str | None = "rggb",
    threshold: float = 0.25,
    noise: float = 0.0,
    seed: int = 0,
    test_every: int = 10,
    fmt: str = "native",
    supersample: int = 1,
    chunk: int = 32,
    progress: bool = False,
    sim: SimulatorConfig | None = None,
) -> SynthResult:
    """`make_scene`, returning a `SynthResult` (folder, counts, timings).

    fmt: "native" or "eventnerf"; supersample: s renders at s x resolution with 4x MSAA and
    box-filters (s² x 4 coverage samples per pixel, ~s² x the render time); chunk: frames
    rendered and simulated at a time; sim: simulator settings overriding threshold, bayer,
    noise and seed.
    """
    from ...memory import check_memory, synth_bytes

    # imported before the clock starts (by the steps below), so that wall_s times the work only
    from ..formats.native import save_scene  # noqa: F401
    from .gl import GLRenderer  # noqa: F401

    wall0 = time.perf_counter()
    _check_options(fmt, width, height, frames, test_every, supersample, chunk)
    est = synth_bytes(width, height, frames, test_every, chunk, supersample)
    check_memory(est, f"{frames} frames at {width}x{height}")
    sim = sim or SimulatorConfig(pos_threshold=threshold, bayer=bayer, noise=noise, seed=seed)
    sim.validate()
    scene = resolve_scene(name_or_mesh)
    cfg = scene_config(scene, width, height, frames, sim.bayer, sim.pos_threshold, sim.log_eps)
    cfg.neg_threshold = sim.pos_threshold if sim.neg_threshold is None else sim.neg_threshold
    rig = Turntable(cfg.trajectory)
    t_all = np.arange(frames, dtype=np.int64) * FRAME_US
    test_idx = np.arange(0, frames, test_every)
    events, test_rgb, render_s, simulate_s = _render_and_simulate(
        scene, rig, sim, width, height, frames, test_every, supersample, chunk, progress
    )
    if len(events) == 0:
        raise InputError(
            f"scene '{scene.name}' produced no events at {width}x{height} "
            f"(threshold {sim.pos_threshold}): nothing to train on"
        )
    out = Path(out)
    t1 = time.perf_counter()
    _write(out, fmt, cfg, events, t_all[test_idx], rig(t_all[test_idx]), test_rgb)
    write_s = time.perf_counter() - t1
    return SynthResult(
        out,
        len(events),
        frames * FRAME_US * 1e-6,
        frames,
        time.perf_counter() - wall0,
        render_s,
        simulate_s,
        write_s,
    )


def _check_options(
    fmt: str, width: int, height: int, frames: int, test_every: int, supersample: int, chunk: int
) -> None:
    """`make_scene_result`'s arguments, checked before any work (`InputError` if bad)."""
    if fmt not in ("native", "eventnerf"):
        raise InputError(f"unknown output format '{fmt}' (use native or eventnerf)")
    if width < 2 or height < 2 or width > 8192 or height > 8192:
        raise InputError(f"sensor size {width}x{height} is not valid")
    if frames < 2:
        raise InputError(f"need at least 2 frames per revolution, got {frames}")
    if test_every < 1:
        raise InputError(f"test_every must be at least 1, got {test_every}")
    if fmt == "eventnerf":
        from ..formats.eventnerf import SENSOR

        if (width, height) != tuple(SENSOR):
            raise InputError(
                f"--format eventnerf needs the {SENSOR[0]}x{SENSOR[1]} sensor that "
                f"the EventNeRF loader hard-codes (got {width}x{height})"
            )
    if supersample < 1 or chunk < 1:
        raise InputError(f"supersample and chunk must be at least 1 (got {supersample}, {chunk})")


def _render_and_simulate(
    scene: SynthScene,
    rig: Turntable,
    sim: SimulatorConfig,
    width: int,
    height: int,
    frames: int,
    test_every: int,
    supersample: int,
    chunk: int,
    progress: bool,
):
    """Render the revolution `chunk` frames at a time and feed them to the simulator, closing
    the loop at t = frames * 1000 µs.

    Returns (events, test_rgb (T, height, width, 3) uint8 display-space views of every
    `test_every`-th frame, render seconds, simulate seconds).
    """
    from .gl import GLRenderer

    t_all = np.arange(frames, dtype=np.int64) * FRAME_US
    test_rgb = np.zeros((len(range(0, frames, test_every)), height, width, 3), np.uint8)
    simulator = EventSimulator(width, height, sim)
    bar = _progress(frames, f"synth {scene.name}", progress)
    intr = scene.view.intrinsics(width, height)
    clock = time.perf_counter
    render_s = simulate_s = 0.0
    with GLRenderer(intr, scene, batch=min(chunk, 16), supersample=supersample) as gl:
        for i in range(0, frames, chunk):
            t = t_all[i : i + chunk]
            t0 = clock()
            rgb = gl.render(rig(t))
            t1 = clock()
            simulator.add_frames(rgb, t)
            simulate_s += clock() - t1
            render_s += t1 - t0
            sel = (np.arange(i, i + len(t)) % test_every) == 0
            test_rgb[np.arange(i, i + len(t))[sel] // test_every] = _display_u8(rgb[sel])
            bar.update(len(t))
    t1 = clock()
    simulator.close_loop(frames * FRAME_US)
    bar.close()
    events = simulator.finish((0, frames * FRAME_US))
    simulate_s += clock() - t1
    return events, test_rgb, render_s, simulate_s


def _write(out: Path, fmt: str, cfg: SceneConfig, events, test_t, test_c2w, test_rgb) -> None:
    """The scene folder at `out` as a whole, native or EventNeRF (test views: times (T,) µs,
    c2w (T, 4, 4), display-space images (T, H, W, 3) uint8)."""
    from ...io import atomic_dir
    from ..formats.native import save_scene

    with atomic_dir(out) as tmp:
        save_scene(tmp, cfg, events, test_t=test_t, test_c2w=test_c2w, test_rgb=test_rgb)
        if fmt == "eventnerf":
            _to_eventnerf(tmp)


def _to_eventnerf(folder: Path) -> None:
    """Replace the native folder's content by its EventNeRF-format export."""
    import shutil
    import tempfile

    from ..formats.eventnerf_export import export_eventnerf
    from ..formats.native import load_scene

    with tempfile.TemporaryDirectory(dir=folder.parent) as native:
        for item in folder.iterdir():
            shutil.move(str(item), native)
        export_eventnerf(load_scene(native), folder)


def _display_u8(linear: np.ndarray) -> np.ndarray:
    """Linear [0, 1] -> display space (c ** (1/2.2)) as uint8."""
    return (np.clip(linear, 0.0, 1.0) ** (1.0 / GAMMA) * 255.0 + 0.5).astype(np.uint8)


def _progress(total: int, desc: str, enabled: bool):
    from ...progress import progress_bar

    return progress_bar(total=total, desc=desc, unit="frame", enabled=enabled)


def summary(res: SynthResult) -> str:
    """One line: events, seconds of stream, rates."""
    rate = res.events / res.duration_s if res.duration_s else math.nan
    return (
        f"{res.events:,} events over {res.duration_s:g} s ({rate:,.0f} ev/s of stream), "
        f"{res.frames} frames in {res.wall_s:.1f} s wall ({res.frames / res.wall_s:.0f} "
        f"frames/s, {res.events / res.wall_s:,.0f} events/s; render {res.render_s:.1f} s, "
        f"simulate {res.simulate_s:.1f} s, write {res.write_s:.1f} s)"
    )
