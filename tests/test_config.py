"""SceneConfig (scene.json): round trip, and one clear line for every kind of mistake."""

from __future__ import annotations

import json

import pytest

from fastenerf.config import CylinderConfig, SceneConfig
from fastenerf.errors import InputError


def test_round_trip_through_json(tmp_path, scene_config):
    cfg = scene_config(
        cylinder=CylinderConfig(0.25, -0.14, 0.195),
        bayer=None,
        background=None,
        polarity_offset=-0.4,
    )
    cfg.intrinsics.k1, cfg.intrinsics.distortion_model = -0.2, "eventnerf"
    cfg.save(tmp_path)
    back = SceneConfig.load(tmp_path)
    assert back == cfg and back.mono and back.cylinder.y_max == 0.195


def write(tmp_path, d) -> str:
    (tmp_path / "scene.json").write_text(json.dumps(d) if not isinstance(d, str) else d)
    return str(tmp_path)


def edit(d: dict, path: str, value) -> dict:
    """Set (or with value=... delete) a dotted key."""
    *parents, last = path.split(".")
    node = d
    for p in parents:
        node = node[p]
    if value is ...:
        del node[last]
    else:
        node[last] = value
    return d


@pytest.mark.parametrize(
    "key,value,words",
    [
        ("width", ..., "missing key 'width'"),
        ("intrinsics.fx", ..., "missing key 'intrinsics.fx'"),
        ("intrinsics", [[300, 0, 173], [0, 300, 130], [0, 0, 1]], "'intrinsics' must be an object"),
        ("frobnicate", 1, "unknown key 'frobnicate'"),
        ("trajectory.speed", 1, "unknown key 'trajectory.speed'"),
        ("width", "346", "'width' must be a number"),
        ("width", 346.5, "'width' must be an integer"),
        ("width", float("inf"), "'width' is not finite"),
        ("t_end_us", float("nan"), "'t_end_us' is not finite"),
        ("intrinsics.fx", -3.0, "'intrinsics.fx/fy' must be positive"),
        ("bayer", "bggr", "'bayer' must be one of"),
        ("loop", 1, "'loop' must be true or false"),
        ("trajectory.kind", "spiral", "'trajectory.kind' must be one of"),
        ("intrinsics.distortion_model", "fisheye", "'intrinsics.distortion_model' must be one of"),
        ("aabb", [0, 0, 0, 1, 1], "'aabb' must be 6 finite numbers"),
        ("aabb", [0, 0, 0, 1, -1, 1], "'aabb' min must be below max"),
        ("aabb", [0, 0, 0, 1, "a", 1], "'aabb[4]' must be a number"),
        ("t_end_us", -5, "'t_end_us' must be after t_start_us"),
        ("pos_threshold", 0.0, "'pos/neg_threshold' must be positive"),
        ("n_views", 1, "'n_views' must be at least 2"),
        ("background", [0.5, 0.5], "'background' must be [r, g, b] or null"),
        ("cylinder", {"radius": 0.25, "y_min": 0.2, "y_max": 0.1}, "'cylinder' needs"),
        ("trajectory", {"kind": "timed"}, "'trajectory.poses_file' is required"),
        ("near", -1.0, "'near' must not be negative"),
        ("trajectory.elevation_deg", 90.0, "'trajectory.elevation_deg' must be strictly between"),
    ],
)
def test_bad_scene_json_is_one_line_naming_the_key(tmp_path, scene_config, key, value, words):
    d = edit(scene_config().to_dict(), key, value)
    with pytest.raises(InputError) as e:
        SceneConfig.load(write(tmp_path, d))
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith(str(tmp_path / "scene.json") + ": ")
    assert words in msg


@pytest.mark.parametrize(
    "text,words",
    [
        ("{not json", "not valid JSON"),
        ("[1, 2]", "top level must be an object"),
        ("", "not valid JSON"),
    ],
)
def test_broken_json(tmp_path, text, words):
    with pytest.raises(InputError, match=words):
        SceneConfig.load(write(tmp_path, text))


def test_missing_file_names_the_folder(tmp_path):
    with pytest.raises(InputError, match="no scene.json here"):
        SceneConfig.load(tmp_path)


def test_defaults_fill_optional_keys(scene_config):
    d = scene_config().to_dict()
    for k in ("bayer", "cylinder", "background", "loop", "kind", "sim_log_eps"):
        d.pop(k)
    d["intrinsics"].pop("distortion_model")
    cfg = SceneConfig.from_dict(d)
    assert cfg.bayer == "rggb" and cfg.cylinder is None and cfg.loop is True
    assert cfg.intrinsics.distortion_model == "opencv"


def test_ngp_cone_angle_follows_the_budget_and_is_recorded():
    from fastenerf.config import TrainConfig, ngp_cone_for_budget, train_preset

    assert ngp_cone_for_budget(1.0, None) == 0.0  # any budget: constant steps
    assert ngp_cone_for_budget(5.0, None) == 0.0
    assert ngp_cone_for_budget(None, 500_000) == 0.0 and ngp_cone_for_budget(None, 50) == 0.0
    assert ngp_cone_for_budget(None, None) == 1 / 256  # open-ended (live viewer)
    assert train_preset("fast", "ngp", minutes=5.0).backend_options["cone_angle"] == 0.0
    assert train_preset("eventnerf", "ngp").backend_options["cone_angle"] == 0.0  # 5e5 steps
    short = train_preset("fast", "ngp", minutes=0.5, backend_options={"hidden": 32})
    assert short.backend_options == {"hidden": 32, "cone_angle": 0.0}
    live = train_preset("fast", "ngp", minutes=None, steps=None)
    assert live.backend_options["cone_angle"] == 1 / 256
    # an explicit choice wins; vanilla has no such option
    mine = train_preset("fast", "ngp", minutes=5.0, backend_options={"cone_angle": 0.01})
    assert mine.backend_options["cone_angle"] == 0.01
    assert "cone_angle" not in train_preset("fast", "vanilla", minutes=5.0).backend_options
    # it travels in the run's config: a resume with another budget keeps the run's marching
    again = TrainConfig.from_dict(json.loads(json.dumps(short.to_dict())))
    again.minutes, again.steps = None, None
    assert again.validate().backend_options["cone_angle"] == 0.0


def test_a_preset_takes_the_perturbation_as_a_dict(scene_config):
    """A benchmark's `--set perturb={...}` hands train_preset a dict: it becomes the dataclass
    (a resolved config copies it with dataclasses.replace), and a bad key is one clear error."""
    from fastenerf.config import PerturbConfig, train_preset

    cfg = train_preset("fast", "ngp", perturb={"pose_error_deg": 1.0})
    assert isinstance(cfg.perturb, PerturbConfig) and cfg.perturb.pose_error_deg == 1.0
    assert cfg.resolved(scene_config(), "cpu").perturb.pose_error_deg == 1.0
    with pytest.raises(InputError, match="perturb"):
        train_preset("fast", "ngp", perturb={"pose_err": 1.0})
