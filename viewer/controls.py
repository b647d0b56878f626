"""Mouse control of the orbit camera over the view: left-drag orbits, right- or middle-drag
(or shift + left) pans, the wheel zooms.

A drag starts on a click over the view and lasts while any button is held, wherever the
mouse goes; the wheel acts only over the view.
"""

from __future__ import annotations

import math

from .camera import OrbitCamera


class MouseDrag:
    """The drag in progress: `button` 0 orbits, 1 or 2 pans, None when there is none."""

    def __init__(self):
        self.button: int | None = None

    @property
    def active(self) -> bool:
        return self.button is not None

    def update(self, cam: OrbitCamera, fov_y: float, hovered: bool, vw: int, vh: int) -> bool:
        """Apply this frame's drag and wheel to `cam` for a view of vw x vh pixels with a
        vertical field of view of `fov_y` degrees; True when the camera moved."""
        from imgui_bundle import imgui

        io = imgui.get_io()
        moved = False
        if hovered and self.button is None:
            for b in (0, 1, 2):
                if imgui.is_mouse_clicked(b):
                    self.button = 1 if (b == 0 and io.key_shift) else b
        if self.button is not None:
            held = any(imgui.is_mouse_down(b) for b in (0, 1, 2))
            if not held:
                self.button = None
            else:
                dx, dy = io.mouse_delta.x, io.mouse_delta.y
                if dx or dy:
                    if self.button == 0:
                        # a drag across the view's width turns the scene once around
                        cam.orbit(-2 * math.pi * dx / vw, math.pi * dy / vh)
                    else:
                        f = 0.5 * vh / math.tan(math.radians(fov_y) / 2)
                        cam.pan(dx / f, dy / f)
                    moved = True
        if hovered and io.mouse_wheel:
            cam.zoom(0.9**io.mouse_wheel)
            moved = True
        return moved
