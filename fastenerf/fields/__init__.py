"""Field backends behind one interface (`fields.base.Field`), chosen by name.

The backend names are `fastenerf.backends.BACKENDS` (the one registry); a backend is a module
`fastenerf.fields.<name>` exposing
    build(scene: SceneConfig, cfg: TrainConfig) -> Field   a new field for a scene
    from_config(config: dict) -> Field                     rebuild from `Field.config_dict()`
Modules are imported lazily, so the vanilla path works without the ngp kernels.
"""

from __future__ import annotations

import importlib
from types import ModuleType

from ..backends import BACKEND_NAMES
from ..backends import backend as registry_entry
from ..errors import InputError
from .base import Field, RenderOutput

BACKENDS = BACKEND_NAMES  # the registry's names (fastenerf.backends)

__all__ = [
    "BACKENDS",
    "Field",
    "RenderOutput",
    "backend_module",
    "canonical_field_config",
    "field_from_config",
    "make_field",
]


def backend_module(name: str) -> ModuleType:
    """The module implementing backend `name`, or a one-line `InputError`."""
    backend = registry_entry(name).name
    name = f"fastenerf.fields.{backend}"
    try:
        return importlib.import_module(name)
    except ModuleNotFoundError as e:
        if e.name != name:
            raise
        raise InputError(
            f"backend {backend!r} is not available in this build "
            f"({name} is missing); use --backend vanilla"
        ) from None


def make_field(backend: str, scene, cfg) -> Field:
    """A new field of `backend` for scene (SceneConfig) trained with cfg (TrainConfig)."""
    return backend_module(backend).build(scene, cfg)


def field_from_config(backend: str, config: dict) -> Field:
    """Rebuild a field of `backend` from the `config_dict()` saved in a checkpoint."""
    return backend_module(backend).from_config(config)


def canonical_field_config(backend: str, config: dict) -> dict:
    """The `config_dict()` that `field_from_config(backend, config)` would give, without
    building the field: older (flat) saved forms in today's form, for comparing a checkpoint's
    field config with a new field's on resume."""
    return backend_module(backend).canonical_config(config)
