"""Chequerboard -> poses -> turntable fit (`fastenerf calibrate --chequerboard`), on rendered
boards (real OpenCV detection on images with lens distortion and noise) and real DV files."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np
import pytest

from fastenerf.cli import main as cli
from fastenerf.config import IntrinsicsConfig, SceneConfig, TrajectoryConfig
from fastenerf.data.chequerboard import (
    Board,
    detect_corners,
    project,
    reject_outliers,
    render_chequerboard,
)
from fastenerf.data.formats.aedat import iter_aedat4_frames
from fastenerf.data.formats.native import save_scene
from fastenerf.data.intrinsics import read_intrinsics
from fastenerf.data.rig import Turntable
from fastenerf.errors import InputError
from fastenerf.io import write_image

DATA = Path(
    os.environ.get(
        "FASTENERF_AEDAT_DIR", Path(__file__).resolve().parents[2] / "shared" / "external-aedat"
    )
)
needs_aedat = pytest.mark.skipif(
    not (DATA / "aedat__test_data.aedat4").is_file(),
    reason=f"real AEDAT4 recordings not found in {DATA} (set FASTENERF_AEDAT_DIR)",
)

SIZE = (346, 260)  # DAVIS 346
BOARD = Board(9, 6, 0.04)  # 10 x 7 squares of 4 cm
LENS = IntrinsicsConfig(fx=300.0, fy=300.0, cx=173.0, cy=130.0, k1=-0.25, k2=0.08)
TILT, YAW = 2.85, 25.0  # the axis leans 2.85° from the board's +y, toward a 25° azimuth
PERIOD = 1_333_333  # 45 RPM
T0 = 1_600_000_000_000_000  # DV's clock: µs since the epoch


def rig_truth() -> TrajectoryConfig:
    """The turntable in the board frame before the yaw: the board stands near the centre
    (4 mm off the axis), the camera 12° above the plate at 45 cm."""
    return TrajectoryConfig(
        radius=0.45,
        center=[0.004, -0.006, 0.003],
        tilt_deg=TILT,
        elevation_deg=12.0,
        period_us=PERIOD,
    )


def yaw() -> np.ndarray:
    b = math.radians(YAW)
    return np.array([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])


def true_axis() -> np.ndarray:
    a = math.radians(TILT)
    return yaw() @ np.array([0.0, math.cos(a), math.sin(a)])


def turntable_poses(n: int, arc_deg: float = 120.0) -> tuple[np.ndarray, np.ndarray]:
    """(t (n,) µs on DV's clock, c2w (n, 4, 4) board frame): the camera on the tilted circle,
    the arc centred on the board's normal, the whole rig turned by YAW about the board's y."""
    th = np.linspace(-arc_deg / 2, arc_deg / 2, n) - YAW
    t = np.round(th / 360.0 * PERIOD).astype(np.int64)
    c2w = Turntable(rig_truth())(t)
    W = np.eye(4)
    W[:3, :3] = yaw()
    return t - t[0] + T0, W @ c2w


def write_frames(folder: Path, images: np.ndarray, t: np.ndarray | None = None) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    names = []
    for i, img in enumerate(images):
        write_image(folder / f"{i:04d}.png", img)
        names.append(f"{i:04d}.png")
    if t is not None:
        lines = [f"{n} {int(ti)}" for n, ti in zip(names, t, strict=True)]
        (folder / "timestamps.txt").write_text("# FILE T_US\n" + "\n".join(lines) + "\n")
    return folder


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """30 rendered frames over 120° of the turntable: noise σ 2 grey levels, blur 0.7 px."""
    root = tmp_path_factory.mktemp("chequerboard")
    t, c2w = turntable_poses(30)
    images = render_chequerboard(BOARD, LENS, SIZE, c2w, noise=2.0, seed=1)
    return write_frames(root / "frames", images, t), t, c2w, images


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    c = float(np.dot(a, b) / np.linalg.norm(a) / np.linalg.norm(b))
    return math.degrees(math.acos(min(1.0, c)))


def test_turntable_from_rendered_chequerboard(
    capture, tmp_path, capsys, scene_config, random_stream
):
    """The must-show: axis within 0.1°, radius within 1 %, through the user's command, with
    the lens calibrated from the same frames."""
    frames, t, c2w, _ = capture
    scene = tmp_path / "scene"
    save_scene(scene, scene_config(*SIZE), random_stream(width=SIZE[0], height=SIZE[1]))
    out = tmp_path / "calib.json"
    argv = ["calibrate", "--chequerboard", str(frames), "--board", "9x6", "--square", "0.04"]
    argv += ["--out", str(out), "--plot", str(tmp_path / "calib.png"), "--scene", str(scene)]
    assert cli(argv) == 0
    printed = capsys.readouterr().out
    d = json.loads(out.read_text())
    assert angle_deg(np.array(d["axis_in_poses_frame"]), true_axis()) < 0.1
    assert abs(d["trajectory"]["radius"] / 0.45 - 1) < 0.01
    # world = R_y(world_yaw) · board frame: the yaw that undoes the rig's turn.
    assert abs(d["trajectory"]["tilt_deg"] - TILT) < 0.1 and abs(d["world_yaw_deg"] + YAW) < 2
    assert abs(d["trajectory"]["period_us"] / PERIOD - 1) < 0.01  # the frames' times
    assert d["trajectory"]["elevation_deg"] == pytest.approx(12.0, abs=0.2)
    assert {"trajectory", "residuals", "angles_deg", "period_fitted"} <= d.keys()
    cb = d["chequerboard"]
    assert cb["frames"] == 30 and 25 <= cb["used"] <= cb["found"] <= 30
    skipped = 30 - cb["found"]
    assert f"found in {cb['found']} of 30 frames ({skipped} skipped" in printed
    # The poses beside the JSON: c2w and t of the used frames, close to the truth.
    z = np.load(tmp_path / "calib.poses.npz")
    assert z["c2w"].shape == (cb["used"], 4, 4) and z["t"].shape == (cb["used"],)
    truth = c2w[z["index"]]
    assert np.abs(z["c2w"][:, :3, 3] - truth[:, :3, 3]).max() < 3e-3  # metres
    assert np.array_equal(z["t"], t[z["index"]])
    # The lens, written in a form --intrinsics reads back.
    lens = read_intrinsics(tmp_path / "calib.intrinsics.json", *SIZE)
    assert lens.fx == pytest.approx(300.0, rel=0.01) and lens.k1 == pytest.approx(-0.25, abs=0.02)
    assert lens.cx == pytest.approx(173.0, abs=1.5) and lens.cy == pytest.approx(130.0, abs=1.5)
    cfg = SceneConfig.load(scene)
    assert cfg.intrinsics == lens and cfg.trajectory.radius == pytest.approx(0.45, rel=0.01)
    assert cfg.trajectory.tilt_deg == 0.0  # the turntable's own frame
    assert (tmp_path / "calib.png").stat().st_size > 20_000


def test_given_intrinsics_and_the_eventnerf_lens_model(tmp_path):
    """--intrinsics: the lens is not calibrated (nor written); a 5x4 EventNeRF file (division
    model) is undistorted exactly before PnP."""
    lens = IntrinsicsConfig(
        fx=300.0, fy=300.0, cx=173.0, cy=130.0, k1=0.2, k2=0.05, distortion_model="eventnerf"
    )
    t, c2w = turntable_poses(12)
    frames = write_frames(tmp_path / "f", render_chequerboard(BOARD, lens, SIZE, c2w, seed=2))
    K = tmp_path / "K.txt"
    K.write_text("300 0 173 0\n0 300 130 0\n0 0 1 0\n0 0 0 1\n0.2 0.05 0 0\n")
    out = tmp_path / "c.json"
    argv = ["calibrate", "--chequerboard", str(frames), "--board", "9x6", "--square", "0.04"]
    assert cli(argv + ["--intrinsics", str(K), "--out", str(out)]) == 0
    d = json.loads(out.read_text())
    assert not (tmp_path / "c.intrinsics.json").exists() and not d["period_fitted"]
    assert angle_deg(np.array(d["axis_in_poses_frame"]), true_axis()) < 0.2
    assert abs(d["trajectory"]["radius"] / 0.45 - 1) < 0.01
    assert d["chequerboard"]["intrinsics"]["distortion_model"] == "eventnerf"


def test_lens_only(capture, tmp_path):
    frames = capture[0]
    out = tmp_path / "lens.json"
    argv = ["calibrate", "--chequerboard", str(frames), "--board", "9x6", "--square", "0.04"]
    assert cli(argv + ["--lens-only", "--out", str(out)]) == 0
    lens = read_intrinsics(out, *SIZE)
    assert lens.fx == pytest.approx(300.0, rel=0.01) and lens.k2 == pytest.approx(0.08, abs=0.02)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["lens.json"]  # nothing else


def test_corners_follow_the_board_convention(capture):
    """Detected corners in `Board.object_points` order (origin at the centre, x right, y up,
    seen from the printed side), at the lens's projection to a fraction of a pixel."""
    _, _, c2w, images = capture
    i = 15  # facing the board
    c = detect_corners(images[i], BOARD)
    truth = project(BOARD.object_points(), c2w[i], LENS, SIZE)
    assert np.sqrt(np.mean(np.sum((c - truth) ** 2, -1))) < 0.15
    # x grows to the right, y upwards (image y down), in the image of the facing camera.
    assert c[1, 0] > c[0, 0] and c[BOARD.cols, 1] > c[0, 1]


def test_blank_images_say_board_not_found(tmp_path, capsys):
    rng = np.random.default_rng(0)
    blank = rng.normal(128, 3, (6, SIZE[1], SIZE[0])).clip(0, 255).astype(np.uint8)
    frames = write_frames(tmp_path / "blank", blank)
    out = tmp_path / "c.json"
    argv = ["calibrate", "--chequerboard", str(frames), "--board", "9x6", "--square", "0.04"]
    assert cli(argv + ["--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "board 9x6 not found in any of 6 frames" in err
    assert not any(tmp_path.glob("c.*"))  # nothing written


def test_too_few_frames(capture, tmp_path, capsys):
    _, t, _, images = capture
    mixed = np.concatenate([images[13:16], np.full((4, SIZE[1], SIZE[0]), 128, np.uint8)])
    frames = write_frames(tmp_path / "few", mixed)
    argv = ["calibrate", "--chequerboard", str(frames), "--board", "9x6", "--square", "0.04"]
    assert cli(argv + ["--out", str(tmp_path / "c.json")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "found in only 3 of 7 frames" in err and "at least 5 usable frames" in err


def test_arguments_and_outputs_checked_before_work(tmp_path, capsys):
    (tmp_path / "afile").write_text("x")
    bad = tmp_path / "afile" / "c.json"
    base = ["calibrate", "--chequerboard", str(tmp_path / "nowhere"), "--board", "9x6"]
    assert cli(base + ["--square", "0.04", "--out", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "--out" in err and "cannot be created" in err and "is a file" in err
    assert cli(base + ["--out", str(tmp_path / "c.json")]) == 2
    assert "needs --board COLSxROWS and --square" in capsys.readouterr().err
    assert cli(base + ["--square", "0.04", "--board", "9", "--out", "c.json"]) == 2
    assert "expected COLSxROWS" in capsys.readouterr().err
    assert cli(["calibrate", "--out", str(tmp_path / "c.json")]) == 2
    assert "give either POSES.npz or --chequerboard" in capsys.readouterr().err


def test_intrinsics_file_size_is_checked(tmp_path):
    from fastenerf.data.intrinsics import write_intrinsics

    write_intrinsics(tmp_path / "k.json", LENS, *SIZE)
    assert read_intrinsics(tmp_path / "k.json", *SIZE) == LENS
    with pytest.raises(InputError, match="calibrated for 346x260 images, but these are 640x480"):
        read_intrinsics(tmp_path / "k.json", 640, 480)


def test_reprojection_outliers_are_rejected():
    rms = np.array([0.05, 0.06, 0.04, 3.0, np.inf, 0.07])
    assert reject_outliers(rms).tolist() == [True, True, True, False, False, True]
    # A uniformly poor detection is not "outliers": the floor keeps it.
    assert reject_outliers(np.array([0.6, 0.9, 0.7])).all()


@needs_aedat
def test_aedat4_aps_frames_are_read():
    frames = list(iter_aedat4_frames(DATA / "aedat__test_data.aedat4"))
    assert len(frames) == 59  # the file's frame count (its README)
    assert all(f.pixels.shape == (260, 346) and f.pixels.dtype == np.uint8 for f in frames)
    t = np.array([f.t_us for f in frames])
    assert np.all(np.diff(t) > 0) and 1.5e15 < t[0] < 1.7e15  # DV clock, µs since the epoch
    assert np.std(frames[0].pixels) > 5  # a picture, not a blank


@needs_aedat
def test_aedat4_without_a_board_or_frames(tmp_path, capsys):
    argv = ["--board", "9x6", "--square", "0.04", "--out", str(tmp_path / "c.json")]
    rec = DATA / "aestream__davis.aedat4"
    assert cli(["calibrate", "--chequerboard", str(rec), *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert err.endswith(
        "board 9x6 not found in any of 3 frames (--board counts inner corners: 9x6 for a "
        "board of 10x7 squares)"
    )
    # A DV header with an event stream only (the aedat suite's tiny file, its frame stream
    # renamed and its packets dropped) and one with a frame stream but no frames.
    head = (DATA / "aedat__test_data_gray16.aedat4").read_bytes()[:0x17A]
    assert head.endswith(b"</dv>\n\x00") or b"</dv>" in head
    (tmp_path / "events_only.aedat4").write_bytes(head.replace(b">FRME<", b">EVTS<"))
    (tmp_path / "no_frames.aedat4").write_bytes(head)
    assert cli(["calibrate", "--chequerboard", str(tmp_path / "events_only.aedat4"), *argv]) == 2
    assert "no frame stream in this AEDAT4 file" in capsys.readouterr().err
    assert cli(["calibrate", "--chequerboard", str(tmp_path / "no_frames.aedat4"), *argv]) == 2
    assert "frame stream has no frames" in capsys.readouterr().err


@needs_aedat
def test_import_frames_then_calibrate_from_them(tmp_path, capsys):
    rec = DATA / "aestream__davis.aedat4"
    scene = tmp_path / "scene"
    assert cli(["import", str(rec), "--out", str(scene), "--frames"]) == 0
    lines = (scene / "frames" / "timestamps.txt").read_text().splitlines()
    rows = [ln.split() for ln in lines if not ln.startswith("#")]
    assert [r[0] for r in rows] == ["000000.png", "000001.png", "000002.png"]
    assert [int(r[1]) for r in rows] == [f.t_us for f in iter_aedat4_frames(rec)]
    import imageio.v3 as iio

    assert iio.imread(scene / "frames" / "000001.png").shape == (260, 346)
    assert json.loads((scene / "import.json").read_text())["frames"] == 3
    capsys.readouterr()
    argv = ["--board", "9x6", "--square", "0.04", "--out", str(tmp_path / "c.json")]
    assert cli(["calibrate", "--chequerboard", str(scene / "frames"), *argv]) == 2
    assert "not found in any of 3 frames" in capsys.readouterr().err
