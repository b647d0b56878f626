"""Synthetic data: built-in scenes (trimesh), a headless GL renderer (moderngl on EGL) and an
ESIM-style event simulator, tied together by `make_scene` (what `fastenerf synth` runs).

    from fastenerf.data.synth import make_scene
    make_scene("blocks", "scenes/blocks", width=64, height=48, frames=100)
"""

from .make import FRAME_US, SynthResult, make_scene, make_scene_result, resolve_scene
from .scenes import (
    DEFAULT_SCENE,
    Material,
    SceneObject,
    SynthScene,
    ViewSetup,
    build_scene,
    list_scenes,
    load_mesh,
)
from .simulator import (
    DEFAULT_LOG_EPS,
    LUMA_WEIGHTS,
    EventSimulator,
    SimulatorConfig,
    log_intensity,
    sensor_intensity,
    simulate,
)

__all__ = [
    "DEFAULT_LOG_EPS",
    "DEFAULT_SCENE",
    "FRAME_US",
    "LUMA_WEIGHTS",
    "EventSimulator",
    "Material",
    "SceneObject",
    "SimulatorConfig",
    "SynthResult",
    "SynthScene",
    "ViewSetup",
    "build_scene",
    "list_scenes",
    "load_mesh",
    "log_intensity",
    "make_scene",
    "make_scene_result",
    "resolve_scene",
    "sensor_intensity",
    "simulate",
]
