"""AEDAT4 reader and `fastenerf import` on real DV recordings (third-party, read in place)."""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest
from conftest import aedat_skip_reason, find_aedat_dir

from fastenerf.cli import main as cli
from fastenerf.config import SceneConfig, TrajectoryConfig
from fastenerf.data.calibrate import fit_turntable, synthetic_poses, write_calibration
from fastenerf.data.formats.aedat import load_aedat4, read_aedat4
from fastenerf.data.formats.native import load_scene
from fastenerf.errors import InputError
from fastenerf.io import savez

DATA = find_aedat_dir()
if DATA is None:
    pytest.skip(aedat_skip_reason(), allow_module_level=True)

TEST_DATA = DATA / "aedat__test_data.aedat4"

# sha3-224 of the t / x / y / on arrays of test_data.aedat4, as the `aedat` package's own test
# suite publishes them (neuromorphicsystems/aedat, tests/assets.py): t is absolute DV time.
DIGESTS = {
    "t": "f1e093cad5afb6ecb971dfa2ef7646ab4ae0f467f73a48804e40bb68",
    "x": "1d8ea97b0febadfde24dd0b9e608682fc6934fc88656823b15f0e7a7",
    "y": "18f89da35f8f10b24c3407b03aa7f82bdd7c8e6ab5369e2c30f8bad0",
    "on": "6f99cf01187da8a05e1a032f3782de51b87e51bdc31356669bdd7cb9",
}


def test_reproduces_the_aedat_suites_digests():
    rec = load_aedat4(TEST_DATA)
    ev = rec.events
    arrays = {
        "t": (ev.t + rec.t_origin_us).astype("<u8"),
        "x": ev.x.astype("<u2"),
        "y": ev.y.astype("<u2"),
        "on": ev.p > 0,
    }
    for k, a in arrays.items():
        assert hashlib.sha3_224(a.tobytes()).hexdigest() == DIGESTS[k], k


def test_time_origin_is_the_first_event_not_the_first_frame():
    import aedat

    first_frame = first_event = None
    for packet in aedat.Decoder(TEST_DATA):
        if "frame" in packet and first_frame is None:
            first_frame = packet["frame"]["t"]
        if "events" in packet and first_event is None and len(packet["events"]):
            first_event = int(packet["events"]["t"][0])
    assert first_frame < first_event  # this file's frames start before its events
    rec = load_aedat4(TEST_DATA)
    assert rec.t_origin_us == first_event
    assert rec.events.t[0] == 0 and np.all(np.diff(rec.events.t) >= 0)
    assert rec.frame_formats == ("L",) and not rec.color_frames


@pytest.mark.parametrize(
    "name, n_events, duration_us",
    [
        ("aedat__test_data.aedat4", 78830, 2359945),
        ("aestream__davis.aedat4", 117667, 129999),
        ("cuke-emlb__demo-01.aedat4", 319512, 510990),
    ],
)
def test_real_recordings(name, n_events, duration_us):
    ev = read_aedat4(DATA / name, expect_size=(346, 260))
    assert (ev.width, ev.height) == (346, 260)
    assert len(ev) == n_events and ev.duration_us == duration_us
    assert ev.x.max() < 346 and ev.y.max() < 260
    assert set(np.unique(ev.p).tolist()) == {-1, 1}


def test_crop_is_relative_to_the_first_event():
    full = load_aedat4(TEST_DATA)
    rec = load_aedat4(TEST_DATA, t_crop_us=(500_000, 1_000_000))
    keep = (full.events.t >= 500_000) & (full.events.t < 1_000_000)
    assert len(rec.events) == keep.sum()
    first = int(np.flatnonzero(keep)[0])
    assert rec.t_origin_us == full.t_origin_us + int(full.events.t[first])
    np.testing.assert_array_equal(rec.events.t, full.events.t[keep] - full.events.t[first])
    np.testing.assert_array_equal(rec.events.x, full.events.x[keep])


def test_errors_are_one_line(tmp_path):
    def err(path, **kw):
        with pytest.raises(InputError) as e:
            read_aedat4(path, **kw)
        msg = str(e.value)
        assert "\n" not in msg and str(path) in msg
        return msg

    assert "no event stream" in err(DATA / "aedat__test_data_gray16.aedat4")
    assert "no event stream" in err(DATA / "aedat__test_data_unknown_then_gray16.aedat4")
    assert "expected 640x480" in err(TEST_DATA, expect_size=(640, 480))
    raw = (DATA / "aestream__davis.aedat4").read_bytes()
    (tmp_path / "cut.aedat4").write_bytes(raw[: len(raw) // 2])
    assert "truncated or corrupt" in err(tmp_path / "cut.aedat4")
    (tmp_path / "junk.aedat4").write_bytes(b"not an aedat file" * 10)
    assert "not a readable AEDAT4" in err(tmp_path / "junk.aedat4")
    assert "no such" in err(tmp_path / "missing.aedat4")
    assert "no events in the crop" in err(TEST_DATA, t_crop_us=(10**9, 10**9 + 1))
    assert "0 <= T0 < T1" in err(TEST_DATA, t_crop_us=(5, 5))


def test_cli_error_exit_code(tmp_path, capsys):
    rc = cli(["import", str(DATA / "aedat__test_data_gray16.aedat4"), "--out", str(tmp_path / "s")])
    assert rc == 2 and "no event stream" in capsys.readouterr().err
    assert not (tmp_path / "s" / "scene.json").exists()


def test_import_turntable_scene(tmp_path):
    """DV recording + turntable calibration -> a native real-scene folder that loads back."""
    truth = TrajectoryConfig(
        radius=0.6,
        center=[0.01, -0.04, 0.02],
        tilt_deg=2.85,
        elevation_deg=15.0,
        period_us=1_333_333,
    )
    t, c2w = synthetic_poses(truth, 30, pos_noise=1e-3, rot_noise_deg=0.05, seed=3)
    calib = write_calibration(tmp_path / "calib.json", fit_turntable(c2w))  # no times
    (tmp_path / "K.txt").write_text("300 0 170\n0 300 128\n0 0 1\n")
    out = tmp_path / "scene"
    argv = [
        "import",
        str(TEST_DATA),
        "--out",
        str(out),
        "--turntable",
        str(calib),
        "--crop",
        "0",
        "1333333",
        "--intrinsics",
        str(tmp_path / "K.txt"),
        "--direction",
        "cw",
    ]
    assert cli(argv) == 2  # no period in a calibration without times, and no --rpm
    assert cli(argv + ["--rpm", "45"]) == 0
    scene = load_scene(out)
    cfg = scene.config
    assert cfg.kind == "real" and cfg.loop and cfg.bayer is None  # gray frames: mono
    assert (cfg.pos_threshold, cfg.neg_threshold, cfg.polarity_offset) == (0.1, 0.1, 0.0)
    assert cfg.t_start_us == 0 and cfg.t_end_us == 1_333_333  # one whole revolution
    tr = cfg.trajectory
    assert tr.kind == "turntable" and tr.period_us == 1_333_333 and tr.clockwise
    assert tr.tilt_deg == 0.0 and tr.center == [0.0, 0.0, 0.0]  # the turntable's own frame
    assert abs(tr.radius - 0.6) < 5e-3 and abs(tr.elevation_deg - 15.0) < 0.2
    assert cfg.cylinder is not None and cfg.intrinsics.fx == 300.0
    ref = read_aedat4(TEST_DATA, t_crop_us=(0, 1_333_333))
    np.testing.assert_array_equal(scene.events.t, ref.t)
    prov = json.loads((out / "import.json").read_text())
    assert prov["t_origin_us"] == load_aedat4(TEST_DATA).t_origin_us


def test_import_timed_poses_on_the_dv_clock(tmp_path):
    rec = load_aedat4(TEST_DATA)
    t_rel = np.linspace(0, rec.events.duration_us, 20).astype(np.int64)
    c2w = np.tile(np.eye(4), (20, 1, 1))
    c2w[:, 0, 3] = np.linspace(0, 1, 20)
    savez(tmp_path / "poses.npz", t=t_rel + rec.t_origin_us, c2w=c2w)
    out = tmp_path / "scene"
    assert (
        cli(
            [
                "import",
                str(TEST_DATA),
                "--out",
                str(out),
                "--poses",
                str(tmp_path / "poses.npz"),
                "--bayer",
                "rggb",
            ]
        )
        == 0
    )
    cfg = SceneConfig.load(out)
    assert cfg.trajectory.kind == "timed" and not cfg.loop and cfg.bayer == "rggb"
    with np.load(out / cfg.trajectory.poses_file) as z:
        np.testing.assert_array_equal(z["t"], t_rel)  # shifted onto the scene's clock
