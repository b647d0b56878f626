"""`fastenerf train` flags: every TrainConfig knob is a flag with its docstring as help, bad
values stop at the boundary with one line (exit 2, nothing written), and `--cylinder` clips
the density of an EventNeRF-format scene for both backends."""

from __future__ import annotations

import dataclasses
import json
import shutil

import pytest
import torch

from fastenerf.cli import main as cli
from fastenerf.config import TrainConfig
from fastenerf.schema import field_docs, flag_name

TINY = {
    "vanilla": '{"depth": 2, "width": 32, "pos_freqs": 4, "dir_freqs": 2, "n_coarse": 8, '
    '"n_fine": 8}',
    "ngp": '{"encoding": {"n_levels": 4, "log2_table_size": 12, "max_resolution": 64}, '
    '"network": {"hidden": 16}, "occupancy": {"grid_resolution": 16}, '
    '"marcher": {"dt_min": 0.03}}',
}


def test_help_lists_every_training_knob_with_its_docstring(capsys):
    with pytest.raises(SystemExit):
        cli(["train", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    for f in dataclasses.fields(TrainConfig):
        if f.name in ("backend_options", "perturb"):  # JSON; a section with its own flags
            continue
        assert flag_name(f.name) in text, f.name
        if f.name in ("backend", "preset"):  # hand-written help: choices of the registries
            continue
        first_words = " ".join(field_docs(TrainConfig)[f.name].split()[:4])
        assert first_words in text, f.name
    for flag in ("--win-min", "--win-max", "--win-redraw {step,load}", "--neg-ratio"):
        assert flag in text  # windows and negative sampling
    for flag in ("--distortion-weight", "--log-eps", "--gamma", "--lr-final", "--cone-angle"):
        assert flag in text  # loss and schedule
    assert "--rays-per-step N, --rays N" in text
    assert "TOTAL" in text  # --resume --steps N: the total budget, said in the help
    for flag in ("--pose-error-deg", "--mount-error-deg", "--noise-fraction", "--perturb-seed"):
        assert flag in text  # the studies' perturbations


@pytest.mark.parametrize(
    "flags,words",
    [
        (["--device", "tpu"], "--device: must be auto, cpu, cuda or cuda:N, got 'tpu'"),
        (["--seed", "-1"], "'seed' must be in [0, 4294967295], got -1"),
        (["--minutes", "inf"], "'minutes' is not finite (inf)"),
        (["--minutes", "nan"], "'minutes' is not finite (nan)"),
        (["--minutes", "-1"], "'minutes' must be in [0, 10000000], got -1"),
        (["--minutes", "0"], "--minutes 0: nothing to train"),
        (["--steps", "0"], "--steps 0: nothing to train"),
        (["--lr", "1e30"], "'lr' must be in (0, 1], got 1e+30"),
        (["--rays", "100000000"], "'rays_per_step' must be in [1, 1048576], got 100000000"),
        (["--win-min", "5", "--win-max", "2"], "'win_max' must be >= win_min (5), got 2"),
        (["--neg-ratio", "1.5"], "'neg_ratio' must be in [0, 1], got 1.5"),
        (["--refine-shared"], "'refine_shared' needs refine_poses"),
        (["--refine-gate", "-1"], "'refine_gate' must be in [0, 100], got -1"),
        (["--refine-gate-beta", "1"], "'refine_gate_beta' must be in [0, 0.9999], got 1"),
        (["--lr-decay-start", "1"], "'lr_decay_start' must be in [0, 0.99], got 1"),
        (["--options", '{"hidden": -1}'], "'network.hidden' must be in [1, 1024], got -1"),
        (
            ["--options", '{"log2_table_size": 40}'],
            "'encoding.log2_table_size' must be in [10, 24]",
        ),
        (["--options", '{"cone_angle": -5}'], "'marcher.cone_angle' must be in [0, 1], got -5"),
        (
            ["--options", '{"early_stop_eps": -1}'],
            "'marcher.early_stop_eps' must be in [0, 1], got -1",
        ),
        (["--options", '{"compact_below": 2}'], "'marcher.compact_below' must be in [0, 1]"),
        (["--options", '{"compaction_auto": "yes"}'], "'marcher.compaction_auto' must be true"),
        (["--options", '{"win_max": 10}'], "'win_max' is a training option, not a backend option"),
        (["--options", "[1]"], "--options must be a JSON object"),
        (["--cone-angle", "-1"], "'marcher.cone_angle' must be in [0, 1]"),
        (["--backend", "vanilla", "--cone-angle", "0"], "--cone-angle: an ngp option"),
        (["--cylinder", "1,2"], "--cylinder: expected R,YMIN,YMAX"),
        (["--cylinder", "0.3,0.2,0.1"], "needs radius > 0 and y_min < y_max"),
        (["--cylinder", "0.3,0,inf"], "cylinder values must be finite"),
    ],
)
def test_bad_flags_one_line_exit_2_nothing_written(tmp_path, capsys, flags, words):
    if "--device" in flags and torch.cuda.is_available():
        pytest.skip("CUDA present")
    out = tmp_path / "run"
    rc = cli(["train", str(tmp_path / "no-scene"), "--out", str(out), *flags])
    err = capsys.readouterr().err.strip()
    assert rc == 2
    assert len(err.splitlines()) == 1 and words in err, err
    assert not out.exists()


def test_cuda_refused_where_there_is_none(tmp_path, capsys):
    if torch.cuda.is_available():
        pytest.skip("CUDA present")
    rc = cli(["train", str(tmp_path), "--out", str(tmp_path / "r"), "--device", "cuda:0"])
    assert rc == 2 and "CUDA is not available" in capsys.readouterr().err


# -- the clip on an EventNeRF-format scene -----------------------------------------------------


@pytest.fixture(scope="module")
def eventnerf_scene(tmp_path_factory):
    """A tiny EventNeRF-format scene written by `synth --format eventnerf` (346x260, the
    sensor their loader hard-codes; 12 frames)."""
    out = tmp_path_factory.mktemp("en") / "blocks"
    rc = cli(
        ["synth", "--scene", "blocks", "--out", str(out), "--frames", "12", "--format", "eventnerf"]
    )
    assert rc == 0
    return out


def _outside_points(cyl: tuple[float, float, float], n: int = 3000) -> torch.Tensor:
    g = torch.Generator().manual_seed(0)
    x = 2 * torch.rand(n, 3, generator=g) - 1
    r, y0, y1 = cyl
    out = (x[:, 0] ** 2 + x[:, 2] ** 2 > r * r) | (x[:, 1] < y0) | (x[:, 1] > y1)
    # just outside each face, too
    edge = torch.tensor([[r + 1e-3, 0.0, 0.0], [0.0, y0 - 1e-3, 0.0], [0.0, y1 + 1e-3, 0.0]])
    return torch.cat([x[out], edge])


@pytest.mark.parametrize("backend", ["ngp", "vanilla"])
def test_cylinder_flag_clips_an_eventnerf_scene(tmp_path, eventnerf_scene, backend, capsys):
    from fastenerf.run import load_run

    cyl = (0.3, -0.25, 0.2)
    run = tmp_path / backend
    flags = ["--steps", "3", "--rays", "32", "--windows-per-step", "2", "--eval-every-s", "0"]
    rc = cli(
        [
            "train",
            str(eventnerf_scene),
            "--out",
            str(run),
            "--backend",
            backend,
            "--device",
            "cpu",
            "--no-progress",
            "--options",
            TINY[backend],
            "--cylinder",
            ",".join(map(str, cyl)),
            *flags,
        ]
    )
    assert rc == 0, capsys.readouterr().err
    assert "clip r=0.3 y -0.25..0.2" in capsys.readouterr().out
    conf = json.loads((run / "config.json").read_text())
    assert conf["scene"]["cylinder"] == {"radius": 0.3, "y_min": -0.25, "y_max": 0.2}
    assert conf["built"]["cylinder"] is True
    field, _, _ = load_run(run, device="cpu")
    with torch.no_grad():
        x = _outside_points(cyl)
        assert torch.equal(field.density(x), torch.zeros(len(x)))
        inside = torch.tensor([[0.0, 0.0, 0.0], [0.1, -0.2, 0.1], [0.0, 0.15, -0.2]])
        assert (field.density(inside) > 0).all()  # the clip leaves the inside alone
    if backend == "ngp":  # the hash grid covers the cylinder's box, not the scene's
        assert field.aabb.tolist() == pytest.approx([-0.3, -0.25, -0.3, 0.3, 0.2, 0.3])


def test_released_real_scene_name_gets_the_authors_clip(tmp_path, eventnerf_scene):
    """Without our export record and with float-seconds times, a folder named like one of the
    authors' released real scenes loads as that real scene: their clip and threshold."""
    from fastenerf.data.formats import load_scene_folder

    for name, y_min, threshold in [("bottle", -0.14, 0.1), ("cube", 0.045, 0.2)]:
        root = tmp_path / name
        shutil.copytree(eventnerf_scene, root)
        (root / "fastenerf_scene.json").unlink()
        sc = load_scene_folder(root).config
        assert sc.kind == "real"
        assert (sc.cylinder.radius, sc.cylinder.y_min, sc.cylinder.y_max) == (0.25, y_min, 0.195)
        assert sc.pos_threshold == sc.neg_threshold == threshold
    other = tmp_path / "teapot"
    shutil.copytree(eventnerf_scene, other)
    (other / "fastenerf_scene.json").unlink()
    assert load_scene_folder(other).config.cylinder is None
