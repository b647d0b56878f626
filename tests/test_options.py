"""Configuration by component: the backend registry, sectioned / flat backend options with one
line per mistake, docstrings on every knob, the field contract's defaults, and old (flat)
field configs that still rebuild the same field."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from fastenerf import backends
from fastenerf.backends import BACKENDS, NGPOptions, VanillaOptions, get_option, parse_options
from fastenerf.config import CylinderConfig, TrainConfig, train_preset
from fastenerf.errors import InputError
from fastenerf.fields import canonical_field_config, field_from_config, make_field
from fastenerf.fields.base import Field
from fastenerf.schema import field_docs

CYL = CylinderConfig(0.3, -0.25, 0.2)


def test_nested_and_flat_options_are_the_same():
    nested = parse_options(
        "ngp",
        {"encoding": {"n_levels": 8}, "marcher": {"cone_angle": 0.0}, "network": {"hidden": 32}},
    )
    flat = parse_options("ngp", {"n_levels": 8, "cone_angle": 0, "hidden": 32})
    mixed = parse_options("ngp", {"encoding": {"n_levels": 8}, "cone_angle": 0, "hidden": 32})
    assert nested == flat == mixed
    assert nested.encoding.n_levels == 8 and nested.marcher.cone_angle == 0.0
    assert nested.occupancy == NGPOptions().occupancy  # untouched sections keep defaults
    assert parse_options("vanilla", {"depth": 3}) == VanillaOptions(depth=3)
    assert get_option("ngp", {"marcher": {"cone_angle": 0.5}}, "cone_angle") == 0.5
    assert get_option("ngp", {"cone_angle": 0.25}, "cone_angle") == 0.25
    assert get_option("ngp", {"hidden": 3}, "cone_angle") is None
    # a preset sees a nested cone angle as set, and does not add a flat one beside it
    cfg = train_preset("fast", "ngp", minutes=5, backend_options={"marcher": {"cone_angle": 0.5}})
    assert cfg.backend_options == {"marcher": {"cone_angle": 0.5}}


@pytest.mark.parametrize(
    "backend,options,words",
    [
        ("ngp", {"hidden": -1}, "'network.hidden' must be in [1, 1024], got -1"),
        ("ngp", {"log2_table_size": 40}, "'encoding.log2_table_size' must be in [10, 24], got 40"),
        ("ngp", {"cone_angle": -5}, "'marcher.cone_angle' must be in [0, 1], got -5"),
        ("ngp", {"marcher": {"cone_angle": "wide"}}, "'marcher.cone_angle' must be a number"),
        ("ngp", {"n_features": 3}, "'encoding.n_features' must be one of [1, 2, 4, 8]"),
        ("ngp", {"grid_resolution": 33}, "'occupancy.grid_resolution' must be a multiple of 2"),
        ("ngp", {"dt_min": 0}, "'marcher.dt_min' must be in (0, 10]"),
        ("ngp", {"alpha_threshold": 2}, "'marcher.alpha_threshold' must be in [0, 1], got 2"),
        ("ngp", {"max_resolution": 8, "base_resolution": 16}, "base_resolution <= max_resolution"),
        (
            "ngp",
            {"win_max": 10},
            "unknown key 'win_max' (valid: compositing, encoding, marcher, network, ",
        ),
        ("ngp", {"distortion_layout": "warp"}, "'compositing.distortion_layout' must be one of"),
        ("ngp", {"marcher": {"hidden": 3}}, "unknown key 'marcher.hidden' (valid: cone_angle,"),
        ("ngp", {"marcher": 3}, "'marcher' must be an object"),
        ("ngp", {"hidden": 8, "network": {"hidden": 9}}, "'hidden' is given twice"),
        ("ngp", {"density_bias": float("nan")}, "'network.density_bias' is not finite"),
        ("vanilla", {"depth": 0}, "'depth' must be in [1, 32], got 0"),
        ("vanilla", {"density_activation": "tanh"}, "'density_activation' must be one of"),
        ("vanilla", {"cone_angle": 0}, "unknown key 'cone_angle' (valid: depth, width, skip"),
    ],
)
def test_bad_options_give_one_line_naming_key_and_range(backend, options, words):
    with pytest.raises(InputError) as e:
        TrainConfig(backend=backend, backend_options=options).validate()
    msg = str(e.value)
    assert words in msg and "\n" not in msg, msg
    assert msg.startswith("train config backend_options: ")


def test_every_option_and_training_knob_has_a_docstring():
    for cls in [TrainConfig, NGPOptions, VanillaOptions, CylinderConfig] + [
        f.default_factory for f in dataclasses.fields(NGPOptions)
    ]:
        docs = field_docs(cls)
        missing = [f.name for f in dataclasses.fields(cls) if not docs.get(f.name)]
        assert not missing, (cls.__name__, missing)


def test_one_registry_of_backends():
    from fastenerf.commands import demo, train, view
    from fastenerf.fields import BACKENDS as FIELD_BACKENDS

    assert FIELD_BACKENDS == tuple(BACKENDS) == backends.BACKEND_NAMES
    for mod in (train, demo, view):
        import argparse

        p = argparse.ArgumentParser()
        mod.add_arguments(p)
        (action,) = [a for a in p._actions if a.dest == "backend"]
        assert tuple(action.choices) == backends.BACKEND_NAMES, mod.__name__
    with pytest.raises(InputError, match=r"'backend' must be one of \['ngp', 'vanilla'\]"):
        TrainConfig(backend="nerf").validate()
    with pytest.raises(InputError, match=r"unknown backend 'nerf' \(choose from ngp, vanilla\)"):
        train_preset("fast", "nerf")


# -- the field contract ---------------------------------------------------------------------------


class _Minimal(Field):
    """A field that implements only what the contract requires."""

    def __init__(self):
        super().__init__()
        self.w = torch.nn.Parameter(torch.ones(2))
        self.frozen = torch.nn.Parameter(torch.ones(1), requires_grad=False)


def test_field_contract_defaults_need_no_probing():
    f = _Minimal()
    (group,) = f.param_groups()
    assert group["params"] == [f.w]  # trainable parameters only
    assert f.built() == {}
    assert f.observe_cameras(torch.eye(3).numpy(), torch.eye(4)[None].numpy(), 8, 6, 0.1) is None
    assert f.update(3) is None
    with pytest.raises(NotImplementedError):
        f.config_dict()


# -- old run folders ------------------------------------------------------------------------------

# What `config_dict()` returned before the options had sections (as saved in checkpoints and
# RUN/config.json by earlier versions), written out literally.
OLD_NGP = {
    "aabb": [-0.3, -0.25, -0.3, 0.3, 0.2, 0.3],
    "options": {
        "n_levels": 4,
        "n_features": 2,
        "log2_table_size": 12,
        "base_resolution": 8,
        "max_resolution": 64,
        "hidden": 16,
        "geo_features": 15,
        "grid_resolution": 16,
        "cone_angle": 0.0,
        "dt_min": 0.05,
        "max_samples": 64,
        "density_threshold": 0.01,
        "grid_decay": 0.95,
        "update_every": 16,
        "warmup_steps": 256,
        "density_bias": 1.5,
        "max_log_density": 15.0,
    },
    "cylinder": {"radius": 0.3, "y_min": -0.25, "y_max": 0.2},
}
OLD_VANILLA = {
    "aabb": [-1.0, -1.0, -1.0, 1.0, 1.0, 1.0],
    "cylinder": [0.3, -0.25, 0.2],
    "depth": 2,
    "width": 16,
    "skip": 4,
    "pos_freqs": 3,
    "dir_freqs": 2,
    "n_coarse": 8,
    "n_fine": 8,
    "density_activation": "softplus",
}


@pytest.mark.parametrize("backend,old", [("ngp", OLD_NGP), ("vanilla", OLD_VANILLA)])
def test_old_flat_field_config_rebuilds_the_same_field(backend, old, scene_config):
    flat = {k: v for k, v in (old.get("options") or old).items() if k not in ("aabb", "cylinder")}
    scene = scene_config(16, 12, cylinder=CYL, aabb=[-1.0] * 3 + [1.0] * 3)
    torch.manual_seed(0)
    new = make_field(backend, scene, TrainConfig(backend=backend, backend_options=flat))
    rebuilt = field_from_config(backend, old)
    assert rebuilt.config_dict() == new.config_dict()
    # a resume compares configs without building a field
    assert canonical_field_config(backend, old) == new.config_dict()
    assert rebuilt.cylinder == CYL and isinstance(rebuilt.cylinder, CylinderConfig)
    rebuilt.load_state_dict(new.state_dict())
    x = torch.rand(64, 3) - 0.5
    with torch.no_grad():
        assert torch.equal(rebuilt.density(x), new.density(x))
    # and the new form round-trips
    again = field_from_config(backend, new.config_dict())
    assert again.config_dict() == new.config_dict()


def test_ngp_box_shrinks_to_the_cylinder(scene_config):
    scene = scene_config(16, 12, cylinder=CylinderConfig(0.25, -0.14, 0.195))
    f = make_field(
        "ngp", scene, TrainConfig(backend="ngp", backend_options=dict(OLD_NGP["options"]))
    )
    assert f.aabb.tolist() == pytest.approx([-0.25, -0.14, -0.25, 0.25, 0.195, 0.25])
    assert f.grid.aabb_list == pytest.approx(f.aabb.tolist())
    # without a cylinder the scene's box is kept
    plain = make_field("ngp", scene_config(16, 12), TrainConfig(backend_options={"hidden": 16}))
    assert plain.aabb.tolist() == [-1.0] * 3 + [1.0] * 3
    with pytest.raises(InputError, match="'cylinder' does not overlap the box"):
        scene_config(16, 12, cylinder=CylinderConfig(0.25, 2.0, 3.0))


@pytest.mark.parametrize("where", ["flat", "nested"])
def test_a_retired_option_at_its_old_default_loads_and_turned_on_is_one_line(where):
    """A run saved while `relu_mask` existed has it false in its config: that still loads,
    as the same options; a config that turned it on is refused, naming the key."""
    off = {"relu_mask": False, "hidden": 32}
    on = {"relu_mask": True}
    if where == "nested":
        off, on = {"network": off}, {"network": on}
    assert parse_options("ngp", off) == parse_options("ngp", {"hidden": 32})
    with pytest.raises(InputError, match="'relu_mask' was removed"):
        parse_options("ngp", on)
    with pytest.raises(InputError, match="unknown key"):
        parse_options("ngp", {"relu_masks": False})
