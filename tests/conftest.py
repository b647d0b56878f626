"""Shared fixtures: small random event streams and scene configs (real arrays, real files)."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import numpy as np
import pytest

from fastenerf.config import IntrinsicsConfig, SceneConfig, TrajectoryConfig
from fastenerf.data.events import EventStream


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20240611)


@pytest.fixture
def random_stream(rng):
    """make(n, width, height, t_max, t_min=1) -> EventStream with random pixels, polarities
    and sorted integer µs times drawn with replacement (so timestamps repeat)."""

    def make(
        n: int = 2000, width: int = 16, height: int = 12, t_max: int = 100_000, t_min: int = 1
    ) -> EventStream:
        t = np.sort(rng.integers(t_min, t_max + 1, n))
        return EventStream.from_arrays(
            rng.integers(0, width, n),
            rng.integers(0, height, n),
            t,
            rng.choice([-1, 1], n),
            width,
            height,
            source="random",
        )

    return make


@pytest.fixture
def scene_config():
    """make(width, height, **overrides) -> SceneConfig: a turntable scene, 1 s loop, RGGB."""

    def make(width: int = 346, height: int = 260, **overrides) -> SceneConfig:
        kw = dict(
            name="test-scene",
            width=width,
            height=height,
            intrinsics=IntrinsicsConfig(
                fx=0.9 * width, fy=0.9 * width, cx=width / 2, cy=height / 2
            ),
            trajectory=TrajectoryConfig(
                kind="turntable", radius=3.0, tilt_deg=2.0, elevation_deg=10.0, period_us=1_000_000
            ),
            t_start_us=0,
            t_end_us=1_000_000,
            n_views=100,
            loop=True,
        )
        kw.update(overrides)
        return SceneConfig(**kw).validate()

    return make


TINY_SCENE_ENV = "FASTENERF_TINY_SCENE"


def make_tiny_scene(path) -> Path:
    """The built-in default scene at 64x48, 100 frames (a 0.1 s loop), RGGB, test view every
    10th frame, made into `path`."""
    from fastenerf.data.synth import DEFAULT_SCENE, make_scene

    return make_scene(DEFAULT_SCENE, Path(path), width=64, height=48, frames=100)


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory):
    """`make_tiny_scene` once per session; or the folder $FASTENERF_TINY_SCENE names, made by
    it beforehand where the scene cannot be drawn (the GPU machine has no trimesh or EGL)."""
    if os.environ.get(TINY_SCENE_ENV):
        path = Path(os.environ[TINY_SCENE_ENV])
        if not (path / "scene.json").is_file():
            pytest.exit(f"${TINY_SCENE_ENV}: {path} is no scene folder (no scene.json)", 2)
        return path
    return make_tiny_scene(tmp_path_factory.mktemp("tiny") / "scene")


AEDAT_ENV = "FASTENERF_AEDAT_DIR"
AEDAT_PROBE = "aedat__test_data.aedat4"


def aedat_dirs() -> list[Path]:
    """Where the real AEDAT4 recordings (third-party, not in git) may be, in order:
    $FASTENERF_AEDAT_DIR; the clone's ../shared/external-aedat; and, for a git worktree or
    a clone made from another checkout, shared/external-aedat in or beside the main
    checkout (the git common dir's parent)."""
    if os.environ.get(AEDAT_ENV):
        return [Path(os.environ[AEDAT_ENV])]
    repo = Path(__file__).resolve().parents[1]
    dirs = [repo.parent / "shared" / "external-aedat"]
    try:
        common = subprocess.run(
            ["git", "rev-parse", "--git-common-dir"],
            cwd=repo,
            capture_output=True,
            text=True,
            timeout=10,
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        common = ""
    if common:
        main_checkout = (repo / common).resolve().parent  # common: relative to repo, or absolute
        dirs += [d / "shared" / "external-aedat" for d in (main_checkout, main_checkout.parent)]
    return list(dict.fromkeys(dirs))


def find_aedat_dir() -> Path | None:
    """The first of `aedat_dirs()` holding the recordings, or None."""
    return next((d for d in aedat_dirs() if (d / AEDAT_PROBE).is_file()), None)


def aedat_skip_reason() -> str:
    looked = ", ".join(str(d) for d in aedat_dirs())
    return (
        f"real AEDAT4 recordings not found (looked in {looked}); set {AEDAT_ENV}=DIR to the "
        f"folder holding {AEDAT_PROBE} and the other recordings (shared/external-aedat)"
    )


@pytest.fixture
def make_untrained_run(tmp_path, scene_config, random_stream):
    """make(name="run", **scene_overrides) -> (run folder, density level): a (briefly
    initialised, untrained) vanilla run of a clipped real scene at 16x12, and a density level
    inside its field's range so that a surface exists (as test_mesh does)."""
    from fastenerf.clip import clip_aabb
    from fastenerf.config import CylinderConfig, TrainConfig
    from fastenerf.data.formats.native import load_scene, save_scene
    from fastenerf.mesh import density_grid
    from fastenerf.run import load_run
    from fastenerf.train import Trainer

    def make(name: str = "run", **overrides):
        kw = dict(width=16, height=12, cylinder=CylinderConfig(), kind="real")
        cfg = scene_config(**{**kw, **overrides})
        save_scene(tmp_path / f"{name}_scene", cfg, random_stream(width=16, height=12))
        trainer = Trainer(
            load_scene(tmp_path / f"{name}_scene"),
            TrainConfig(backend="vanilla", steps=0, device="cpu"),
            tmp_path / name,
        )
        trainer.save_checkpoint(finished=True)
        field, _, _ = load_run(tmp_path / name, device="cpu")
        box = clip_aabb(cfg.aabb, cfg.cylinder)
        vol, _ = density_grid(field.density, box, 16, cylinder=cfg.cylinder, progress=False)
        return tmp_path / name, float(np.quantile(vol[vol > 0], 0.5))

    return make


@pytest.fixture
def untrained_run(make_untrained_run):
    """(run folder, density level) of `make_untrained_run()`."""
    return make_untrained_run()
