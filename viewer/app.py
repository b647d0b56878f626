"""The interactive viewer: imgui-bundle window, frames drawn through a moderngl texture.

Layout: a control panel on the left, the view on the right (an `imgui.image` of the frame
texture, which the window's own moderngl context fills). Mouse: left-drag orbits, right- or
middle-drag (or shift + left) pans, the wheel zooms; R resets the camera, N snaps to the
nearest scene pose. Frames render through `fastenerf.render.render_image` (what eval uses),
at a resolution scale that drops while the camera moves to hold the target frame rate and
returns to full when it stops.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import torch

from .autoscale import AutoScale
from .camera import fov_y_of, intrinsics_for_fov, save_camera_path
from .controls import MouseDrag
from .frame import ViewSettings, render_raw, shade
from .framecache import FrameCache, render_key
from .panels import control_panel
from .source import ViewSource
from .worker import Job, RenderWorker

PANEL_WIDTH = 330
STILL_AFTER_S = 0.2  # the camera counts as still this long after its last change


class Viewer:
    """State and per-frame GUI of one viewer window. `run()` opens it."""

    def __init__(
        self,
        source: ViewSource,
        *,
        window_size=(1280, 800),
        target_fps: float = 30.0,
        max_frames: int | None = None,
        window_shot: str | Path | None = None,
        settings: ViewSettings | None = None,
    ):
        self.src = source
        self.cam = source.default_camera()
        self.settings = settings or ViewSettings(near=source.near, background=source.background)
        self.fov_y = fov_y_of(source.intrinsics) if source.intrinsics else 50.0
        self.auto = AutoScale(target_fps=target_fps)
        self.auto_on = True
        self.window_size = window_size
        self.max_frames = max_frames
        self.window_shot = Path(window_shot) if window_shot else None
        self.out_dir = Path(source.out_dir) if source.out_dir else Path(".")
        self.tex = None
        self.worker: RenderWorker | None = None
        self.frames = 0
        self.cache = FrameCache()
        self.last_move_t = -math.inf
        self._moved = False
        self.mouse = MouseDrag()
        self.snapped: int | None = None
        self.recording = False
        self.path: list = []
        self.message = ""

    @property
    def raw(self) -> dict[str, torch.Tensor] | None:
        """The renderer outputs shown (see FrameCache), None before the first render."""
        return self.cache.raw

    @property
    def raw_scale(self) -> float:
        """The resolution scale the shown frame was rendered at (1: full)."""
        return self.cache.scale

    # ---- lifecycle ------------------------------------------------------------------------

    def run(self) -> np.ndarray | None:
        """Open the window and run until it is closed (or `max_frames` frames have been
        drawn). Returns the final window image (H, W, 3) uint8 when `window_shot` is set."""
        from imgui_bundle import hello_imgui, immapp

        rp = hello_imgui.RunnerParams()
        rp.app_window_params.window_title = f"fastenerf view: {self.src.name}"
        rp.app_window_params.window_geometry.size = tuple(self.window_size)
        rp.imgui_window_params.default_imgui_window_type = (
            hello_imgui.DefaultImGuiWindowType.provide_full_screen_window
        )
        rp.ini_disable = True
        # a GUI spinning without vsync (Xvfb, some drivers) would steal the render thread's CPU
        rp.fps_idling.fps_max = 60.0
        rp.callbacks.post_init = self._post_init
        rp.callbacks.before_exit = self._before_exit
        rp.callbacks.show_gui = self._gui
        self.src.start_training()
        try:
            immapp.run(rp, add_ons_params=immapp.AddOnsParams(with_implot=True))
        finally:
            self.src.close()
        if self.window_shot is not None:
            shot = np.asarray(hello_imgui.final_app_window_screenshot())
            from fastenerf.io import write_image

            write_image(self.window_shot, shot[..., :3])
            return shot
        return None

    def _post_init(self) -> None:
        import moderngl

        from .blit import InteropTexture

        # moderngl attaches to the window's current GL context: the texture it fills is the
        # one imgui's renderer draws. CUDA frames go to it device to device where the driver
        # allows, else through the pinned buffer (InteropTexture decides on the first frame).
        self.ctx = moderngl.create_context()
        self.tex = InteropTexture(self.ctx)
        self.worker = RenderWorker(self.src)

    def _before_exit(self) -> None:
        if self.worker is not None:
            self.worker.stop()
            self.worker = None
        if self.tex is not None:
            self.tex.release()
            self.tex = None

    # ---- per frame ------------------------------------------------------------------------

    def _gui(self) -> None:
        from imgui_bundle import hello_imgui, imgui

        self.frames += 1
        self._poll_model()
        self._take_result()
        imgui.begin_child("panel", imgui.ImVec2(PANEL_WIDTH, 0), imgui.ChildFlags_.borders)
        control_panel(self)
        imgui.end_child()
        imgui.same_line()
        flags = imgui.WindowFlags_.no_scrollbar | imgui.WindowFlags_.no_scroll_with_mouse
        imgui.begin_child("view", imgui.ImVec2(0, 0), 0, flags)
        avail = imgui.get_content_region_avail()
        vw, vh = max(int(avail.x), 8), max(int(avail.y), 8)
        self._update_frame(vw, vh)
        pos = imgui.get_cursor_screen_pos()
        if self.tex is not None and self.tex.glo:
            imgui.image(imgui.ImTextureRef(self.tex.glo), imgui.ImVec2(vw, vh))
        else:
            imgui.dummy(imgui.ImVec2(vw, vh))
        if self.mouse.update(self.cam, self.fov_y, imgui.is_item_hovered(), vw, vh):
            self._camera_moved()
        w, h = self.tex.size if self.tex else (0, 0)
        ms = self.cache.render_s * 1e3
        overlay = f"{w}x{h}  {ms:.0f} ms/render  {imgui.get_io().framerate:.0f} ui fps"
        if self.worker is not None and self.worker.busy:
            overlay += "  rendering..."
        if self.recording:
            overlay += f"  REC {len(self.path)}"
        imgui.get_window_draw_list().add_text(
            imgui.ImVec2(pos.x + 8, pos.y + 6), 0xFFFFFFFF, overlay
        )
        imgui.end_child()
        self._keys()
        if self.recording and self._moved:
            self._record()
        self._moved = False
        rp = hello_imgui.get_runner_params()
        busy = self.worker is not None and (self.worker.busy or self.worker.has_result)
        # idle (sleep between frames) only when nothing is on its way
        rp.fps_idling.enable_idling = self.max_frames is None and not (
            busy or self._live() or self._moving()
        )
        if self.max_frames is not None and self.frames >= self.max_frames:
            # test hook: close on a finished frame, not on one still rendering
            if self.raw is not None and not busy:
                rp.app_shall_exit = True

    def _poll_model(self) -> None:
        if self.src.poll():
            self.cache.invalidate()
            self.message = "reloaded a newer checkpoint"

    def _moving(self) -> bool:
        return self.mouse.active or time.perf_counter() - self.last_move_t < STILL_AFTER_S

    def _live(self) -> bool:
        """Training in this process and not paused: the weights keep changing."""
        th = self.src.train_thread
        return th is not None and not th.paused and not self.src.stats.done

    def _take_result(self) -> None:
        """Adopt the render that finished since the last frame, if any."""
        res = self.worker.take() if self.worker is not None else None
        if res is not None:
            if res.error is not None:
                self.message = f"render failed: {res.error}"
            else:
                self.cache.adopt(res)

    def _update_frame(self, vw: int, vh: int) -> None:
        """Re-shade the cached outputs when only their colouring changed; ask the worker for
        a new render when the view, the model or the resolution target changed.

        While the camera moves, or the model trains live, frames render at the AutoScale's
        scale (holding the target frame rate); when both are still, at full scale."""
        self.cache.reshade(self.tex, self.settings)
        if self.worker is None or self.worker.busy:
            return
        moving = self._moving() or self._live()
        key = render_key(self.cam.c2w, self.fov_y, self.settings, vw, vh)
        model = self.src.model_version()
        full = self.auto.max_scale
        if not self.cache.due(key, model, moving, full):
            return
        pending = self.cache.take_pending_time()
        scale = self.auto.update(pending, moving) if self.auto_on else full
        rw, rh = max(1, round(vw * scale)), max(1, round(vh * scale))
        intr = intrinsics_for_fov(rw, rh, self.fov_y)
        self.worker.submit(Job(self.cam.c2w, intr, self.settings, key, scale, model))

    # ---- input ------------------------------------------------------------------------------

    def _camera_moved(self) -> None:
        self.last_move_t = time.perf_counter()
        self.snapped = None
        self._moved = True

    def _keys(self) -> None:
        from imgui_bundle import imgui

        if imgui.get_io().want_text_input:
            return
        if imgui.is_key_pressed(imgui.Key.r, False):
            self.reset_camera()
        if imgui.is_key_pressed(imgui.Key.n, False):
            self.snap()

    def reset_camera(self) -> None:
        self.cam.reset()
        self._camera_moved()

    def snap(self) -> None:
        """Snap to the nearest scene pose, with the scene camera's field of view."""
        if self.src.snap_poses is None:
            self.message = "no scene poses to snap to"
            return
        i = self.cam.snap(self.src.snap_poses, self.src.center)
        if self.src.intrinsics is not None:
            self.fov_y = fov_y_of(self.src.intrinsics)
        self._camera_moved()
        self.snapped = i
        self.message = f"snapped to pose {i}"

    # ---- capture ----------------------------------------------------------------------------

    def screenshot(
        self, path: str | Path | None = None, size: tuple[int, int] | None = None
    ) -> Path:
        """Render the current view at full resolution and write it as PNG (atomically)."""
        from fastenerf.io import write_image

        if size is None:
            size = (
                self.tex.size
                if self.tex is not None and self.raw_scale >= 1.0
                else (self._view_size())
            )
        intr = intrinsics_for_fov(size[0], size[1], self.fov_y)
        raw = render_raw(self.src.field, self.cam.c2w, intr, self.settings, self.src.lock)
        img = shade(raw, self.settings).cpu().numpy()
        return write_image(path or _next_free(self.out_dir / "screenshots", "view", ".png"), img)

    def _view_size(self) -> tuple[int, int]:
        w, h = self.tex.size if self.tex is not None else (640, 480)
        s = max(self.raw_scale, 1e-6)
        return max(1, round(w / s)), max(1, round(h / s))

    def set_recording(self, on: bool) -> None:
        """Start (with a new path, from the current view) or stop recording camera poses."""
        self.recording = on
        if on:
            self.path = []
            self._record()

    def _record(self) -> None:
        w, h = self._view_size()
        self.path.append((self.cam.c2w.copy(), intrinsics_for_fov(w, h, self.fov_y)))

    def save_path(self, path: str | Path | None = None) -> Path:
        """Write the recorded camera path as JSON for `fastenerf render RUN --path FILE`."""
        fps = self.auto.target_fps
        return save_camera_path(
            path or _next_free(self.out_dir / "paths", "path", ".json"), self.path, fps=fps
        )


def _next_free(folder: Path, stem: str, suffix: str) -> Path:
    i = 0
    while (folder / f"{stem}_{i:04d}{suffix}").exists():
        i += 1
    return folder / f"{stem}_{i:04d}{suffix}"


def run_app(
    source: ViewSource,
    *,
    max_frames: int | None = None,
    screenshot: str | Path | None = None,
    window_size=(1280, 800),
    target_fps: float = 30.0,
    settings: ViewSettings | None = None,
) -> np.ndarray | None:
    """Open the viewer on `source`. Test hook: with `max_frames` it closes itself after that
    many frames, and with `screenshot` it writes the final window image there (PNG)."""
    v = Viewer(
        source,
        window_size=window_size,
        target_fps=target_fps,
        max_frames=max_frames,
        window_shot=screenshot,
        settings=settings,
    )
    return v.run()
