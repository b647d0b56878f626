"""The viewer's control panel: one imgui section per concern, drawn once per frame.

`control_panel(v)` draws them all for a Viewer `v`; each section reads and edits only the
state it shows (the Display section just the ViewSettings, Training just the source and the
render worker). Widgets edit values in place, so the next frame renders with them.
"""

from __future__ import annotations

import numpy as np

from .frame import MODES, ViewSettings
from .tonemap import Exposure

MODE_LABELS = {"rgb": "RGB", "depth": "Depth", "opacity": "Opacity", "occupancy": "Occupancy cells"}


def control_panel(v) -> None:
    """All sections for Viewer `v`, then its last message."""
    from imgui_bundle import imgui

    imgui.text(v.src.name)
    imgui.text_disabled("drag orbit | right/shift-drag pan | wheel zoom")
    imgui.text_disabled("R reset | N snap to nearest scene pose")
    camera_section(v)
    display_section(v.settings)
    resolution_section(v)
    capture_section(v)
    if v.src.stats is not None:
        training_section(v.src, v.worker)
    if v.message:
        imgui.text_wrapped(v.message)


def camera_section(v) -> None:
    """Field of view (degrees), near / far (world units), reset / snap, the orbit target."""
    from imgui_bundle import imgui

    if not imgui.collapsing_header("Camera", imgui.TreeNodeFlags_.default_open):
        return
    s = v.settings
    _, v.fov_y = imgui.slider_float("fov y (deg)", v.fov_y, 5.0, 140.0, "%.1f")
    _, s.near = imgui.input_float("near", s.near, 0.0, 0.0, "%.4g")
    _, s.far = imgui.input_float("far (occupancy)", s.far, 0.0, 0.0, "%.4g")
    s.near = max(s.near, 0.0)
    s.far = max(s.far, s.near + 1e-6)
    if imgui.button("Reset (R)"):
        v.reset_camera()
    imgui.same_line()
    if imgui.button("Snap (N)"):
        v.snap()
    if v.snapped is not None:
        imgui.same_line()
        imgui.text(f"pose {v.snapped}")
    t = v.cam.target
    imgui.text(f"target {t[0]:.2f} {t[1]:.2f} {t[2]:.2f}  dist {v.cam.distance:.2f}")


def display_section(s: ViewSettings) -> None:
    """Mode, exposure and the depth colouring range."""
    from imgui_bundle import imgui

    if not imgui.collapsing_header("Display", imgui.TreeNodeFlags_.default_open):
        return
    labels = [MODE_LABELS[m] for m in MODES]
    _, i = imgui.combo("mode", MODES.index(s.mode), labels)
    s.mode = MODES[i]
    e = s.exposure
    _, e.ev = imgui.slider_float("exposure (EV)", e.ev, -6.0, 6.0, "%.2f")
    _, e.gain = imgui.slider_float(
        "log gain", e.gain, 0.25, 4.0, "%.2f", imgui.SliderFlags_.logarithmic
    )
    _, e.gamma = imgui.slider_float(
        "gamma", e.gamma, 0.25, 4.0, "%.2f", imgui.SliderFlags_.logarithmic
    )
    if imgui.button("Reset exposure"):
        s.exposure = Exposure()
    _, auto_depth = imgui.checkbox("auto depth range", s.depth_lo is None)
    if auto_depth:
        s.depth_lo = s.depth_hi = None
    else:
        lo = s.depth_lo if s.depth_lo is not None else s.near
        hi = s.depth_hi if s.depth_hi is not None else min(s.far, 10.0)
        _, (lo, hi) = imgui.drag_float2("depth lo/hi", [lo, hi], 0.01)
        s.depth_lo, s.depth_hi = lo, max(hi, lo + 1e-6)


def resolution_section(v) -> None:
    """AutoScale's switch, target and full scale; fast marching; the last render's time."""
    from imgui_bundle import imgui

    if not imgui.collapsing_header("Resolution", imgui.TreeNodeFlags_.default_open):
        return
    auto = v.auto
    _, v.auto_on = imgui.checkbox("drop resolution while moving", v.auto_on)
    _, auto.target_fps = imgui.slider_float("target fps", auto.target_fps, 1.0, 120.0, "%.0f")
    _, auto.max_scale = imgui.slider_float("full scale", auto.max_scale, 0.1, 1.0, "%.2f")
    auto.min_scale = min(auto.min_scale, auto.max_scale)
    _, fast = imgui.checkbox("fast marching (cone 1/256)", v.settings.cone_angle is not None)
    v.settings.cone_angle = 1.0 / 256 if fast else None
    imgui.text(f"render {v.cache.render_s * 1e3:.1f} ms at scale {v.cache.scale:.2f}")


def capture_section(v) -> None:
    """Screenshot, and recording / saving a camera path."""
    from imgui_bundle import imgui

    if not imgui.collapsing_header("Capture", imgui.TreeNodeFlags_.default_open):
        return
    if imgui.button("Screenshot"):
        v.message = f"saved {v.screenshot()}"
    imgui.same_line()
    ch, rec = imgui.checkbox("record path", v.recording)
    if ch:
        v.set_recording(rec)
    if v.path and not v.recording:
        imgui.same_line()
        if imgui.button(f"Save path ({len(v.path)})"):
            v.message = f"saved {v.save_path()}"


def training_section(src, worker) -> None:
    """Pause / resume, the latest stats of `src.stats` and its loss curve (log scale).

    worker: the RenderWorker or None; resuming waits for it, as it may be rendering
    lock-free under the pause."""
    from imgui_bundle import imgui, implot

    st = src.stats
    if not imgui.collapsing_header("Training", imgui.TreeNodeFlags_.default_open):
        return
    th = src.train_thread
    if th is not None and not st.done:
        ch, paused = imgui.checkbox("pause training", th.paused)
        if ch and paused:
            th.pause()
        elif ch:
            if worker is not None:
                worker.wait_idle()
            th.resume()
    last = st.last
    step = st.steps[-1] if st.steps else 0
    loss = st.losses[-1] if st.losses else float("nan")
    imgui.text(f"step {step}   loss {loss:.4g}")
    imgui.text(f"{st.rays_per_s:,.0f} rays/s   {last.get('elapsed_s', 0.0):.1f} s trained")
    if "eval_psnr" in last and last["eval_psnr"] is not None:
        imgui.text(f"quick eval PSNR {last['eval_psnr']:.2f} dB")
    if "pose_correction_deg" in last:  # --refine-poses
        err, jitter = last.get("pose_error_deg"), last.get("pose_jitter_deg")
        imgui.text(
            f"pose corrections {last['pose_correction_deg']:.3f} deg mean"
            + ("" if err is None else f", error {err:.3f} deg")
            + ("" if jitter is None else f" ({jitter:.3f} pose to pose)")
            + (", frozen" if last.get("poses_frozen") else "")  # --refine-freeze
            + (", field restarted" if last.get("field_restarts") else "")  # --refine-restart
        )
    if "field_win_max" in last:  # --refine-settle-px
        moved = last.get("pose_settle_px")
        imgui.text(
            f"windows up to {last['field_win_max']:.0f} views"
            + ("" if moved is None else f", poses moved {moved:.3f} px")
        )
    if "threshold_pos" in last:  # --estimate-threshold
        imgui.text(f"thresholds +{last['threshold_pos']:.4f} / -{last['threshold_neg']:.4f}")
    if st.done:
        imgui.text("training finished" if st.error is None else f"failed: {st.error}")
    if len(st.losses) >= 2 and implot.begin_plot("loss", imgui.ImVec2(-1, 180)):
        implot.setup_axes("step", "loss", implot.AxisFlags_.auto_fit, implot.AxisFlags_.auto_fit)
        implot.setup_axis_scale(implot.ImAxis_.y1, implot.Scale_.log10)
        xs = np.asarray(st.steps, np.float64)
        ys = np.maximum(np.asarray(st.losses, np.float64), 1e-12)
        implot.plot_line("loss", xs, ys)
        implot.end_plot()
