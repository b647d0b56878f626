"""Bad input, table-driven: every row runs `fastenerf.cli.main` on a tiny scene or run and
expects an exit code, one stderr line holding a message fragment (never a traceback), and the
files it names still there, byte for byte.

A row: (input class, argv, setup, expected exit code, message fragment, files that must
survive). argv and the paths take placeholders: {tmp} (the test's folder), {scene} (a copy
of the tiny scene), {run} (a copy of a tiny trained run), {ro} (a folder that cannot be
written), {en} (a small EventNeRF folder), {aedat} (the real recordings, where present).
A fragment "a|b" matches either. Rows that need another engineer's part are marked
xfail(strict=True) with the part's owner, so that they flip to passing when it is merged.
"""

from __future__ import annotations

import hashlib
import json
import os
import shlex
import shutil
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
from conftest import find_aedat_dir

from fastenerf.cli import main

AEDAT = find_aedat_dir()
MEM = {"FASTENERF_MEMORY_LIMIT": "4G"}  # a stated cap: the refusals do not depend on the host
VANILLA = '{"depth": 2, "width": 32, "pos_freqs": 4, "dir_freqs": 2, "n_coarse": 8, "n_fine": 8}'


@dataclass
class Case:
    """One bad input (see the module docstring)."""

    input_class: str
    argv: list[str]
    setup: Callable[[Path], None] | None
    code: int
    message: str
    keep: tuple[str, ...] = ()
    env: dict[str, str] = field(default_factory=dict)


# ---------------------------------------------------------------------------- set-ups


def notes_folder(name: str = "d") -> Callable[[Path], None]:
    def setup(tmp: Path) -> None:
        (tmp / name).mkdir()
        (tmp / name / "notes.txt").write_text("x\n")

    return setup


def a_file(name: str, text: str = "mine\n") -> Callable[[Path], None]:
    def setup(tmp: Path) -> None:
        (tmp / name).write_text(text)

    return setup


def frames_file(tmp: Path) -> None:
    frames = np.random.default_rng(0).uniform(0.1, 1, (4, 6, 8, 3)).astype(np.float32)
    np.savez(tmp / "frames.npz", frames=frames, t=np.arange(4) * 1e-3)


def poses_file(tmp: Path) -> None:
    from fastenerf.config import TrajectoryConfig
    from fastenerf.data.calibrate import synthetic_poses

    t, c2w = synthetic_poses(TrajectoryConfig(radius=1.0), 24)
    np.savez(tmp / "poses.npz", c2w=c2w, t=t)


def cut_recording(tmp: Path) -> None:
    raw = (AEDAT / "aestream__davis.aedat4").read_bytes()
    (tmp / "cut.aedat4").write_bytes(raw[: len(raw) // 2])


def edit_events(fn: Callable[[dict], dict]) -> Callable[[Path], None]:
    """Rewrite {scene}/events.npz with fn(arrays)."""

    def setup(tmp: Path) -> None:
        path = tmp / "scene" / "events.npz"
        with np.load(path) as z:
            arrays = {k: z[k] for k in z.files}
        np.savez(path, **fn(arrays))

    return setup


def truncate(rel: str) -> Callable[[Path], None]:
    def setup(tmp: Path) -> None:
        raw = (tmp / rel).read_bytes()
        (tmp / rel).write_bytes(raw[: len(raw) // 2])

    return setup


def edit_scene_json(**changes) -> Callable[[Path], None]:
    def setup(tmp: Path) -> None:
        path = tmp / "scene" / "scene.json"
        d = json.loads(path.read_text())
        for k, v in changes.items():
            target, key = d, k.split(".")
            for part in key[:-1]:
                target = target[part]
            target[key[-1]] = v
        path.write_text(json.dumps(d))

    return setup


def remove_view(*subs: str, name: str = "r_00003") -> Callable[[Path], None]:
    def setup(tmp: Path) -> None:
        for sub in subs:
            for f in (tmp / "en" / "train" / sub).glob(f"{name}.*"):
                f.unlink()

    return setup


def unsorted(a: dict) -> dict:
    a["t"] = a["t"].copy()
    a["t"][[3, 4]] = a["t"][[4, 3]] + np.array([0, 1])  # t[3] > t[4]
    return a


def outside(a: dict) -> dict:
    a["x"] = a["x"].astype(np.int64)
    a["x"][5] = 10_000
    return a


def nan_t(a: dict) -> dict:
    a["t"] = a["t"].astype(np.float64)
    a["t"][7] = np.nan
    return a


def empty(a: dict) -> dict:
    return {**a, **{k: a[k][:0] for k in ("x", "y", "t", "p")}}


def chain(*setups: Callable[[Path], None]) -> Callable[[Path], None]:
    def setup(tmp: Path) -> None:
        for s in setups:
            s(tmp)

    return setup


def many_folder(tmp: Path) -> None:
    """A train-many folder holding a run of the job `train-many {run}` plans (run-ngp)."""
    (tmp / "runs" / "run-ngp").mkdir(parents=True)
    (tmp / "runs" / "run-ngp" / "checkpoint.pt").write_bytes(b"not read")


# ---------------------------------------------------------------------------- the table


def needs(who: str, run: bool = True):
    return pytest.mark.xfail(strict=True, run=run, reason=f"needs {who}")


def R(id, what, cmd, setup, code, message, keep="", env=None, marks=()):  # noqa: N802
    """A row: cmd is the command line (shell quoting), keep the paths that must survive."""
    case = Case(what, shlex.split(cmd), setup, code, message, tuple(keep.split()), env or {})
    return pytest.param(case, marks=marks, id=id)


SYNTH = "synth --scene blocks --frames 20 --size 40x30"
TINY = "--backend vanilla --device cpu --rays 64 --no-progress"
TRAIN = "train {scene} --out {tmp}/r --steps 1 " + TINY
NGP = "train {scene} --out {tmp}/r --steps 1 --backend ngp --device cpu --no-progress"
NO_DISPLAY = {"DISPLAY": "", "WAYLAND_DISPLAY": ""}
CENTER_2 = edit_scene_json(**{"trajectory.center": [0.0, 0.0]})

# fmt: off
OUTPUT_ROWS = [
    R("synth-into-notes-folder", "output: existing non-scene folder",
      SYNTH + " --out {tmp}/d", notes_folder(), 2, "not a scene folder", "d/notes.txt"),
    R("synth-onto-file", "output: file where a folder goes",
      SYNTH + " --out {tmp}/f", a_file("f"), 2, "is a file, but a scene folder is a folder", "f"),
    R("synth-below-file", "output: below a file",
      SYNTH + " --out {tmp}/f/sub", a_file("f"), 2, "is a file, not a folder", "f"),
    R("synth-read-only", "output: read-only",
      SYNTH + " --out {ro}/scene", None, 2, "cannot write in"),
    R("simulate-onto-its-frames", "output: the input file as output",
      "simulate --frames {tmp}/frames.npz --out {tmp}/frames.npz", frames_file,
      2, "not an events file", "frames.npz"),
    R("simulate-read-only", "output: read-only",
      "simulate --frames {tmp}/frames.npz --out {ro}/e.npz", frames_file,
      2, "cannot write in", "frames.npz"),
    R("import-into-notes-folder", "output: existing non-scene folder (before reading)",
      "import {tmp}/missing.aedat4 --out {tmp}/d", notes_folder(),
      2, "not a scene folder", "d/notes.txt"),
    R("import-read-only", "output: read-only",
      "import {tmp}/missing.aedat4 --out {ro}/s", None, 2, "cannot write in"),
    R("import-onto-file", "output: file where a folder goes",
      "import {tmp}/missing.aedat4 --out {tmp}/f", a_file("f"), 2, "is a file", "f"),
    R("calibrate-onto-scene-json", "output: another command's file",
      "calibrate {tmp}/missing.npz --out {scene}/scene.json", None,
      2, "not a calibration file", "scene/scene.json"),
    R("calibrate-read-only", "output: read-only (before the fit)",
      "calibrate {tmp}/missing.npz --out {ro}/c.json", None, 2, "cannot write in"),
    R("calibrate-plot-onto-folder", "output: folder where a file goes",
      "calibrate {tmp}/poses.npz --out {tmp}/c.json --plot {tmp}/d",
      chain(poses_file, notes_folder()), 2, "--plot", "d/notes.txt"),
    R("calibrate-scene-not-a-scene", "output: --scene is not a scene",
      "calibrate {tmp}/poses.npz --out {tmp}/c.json --scene {tmp}/d",
      chain(poses_file, notes_folder()), 2, "no scene.json here", "d/notes.txt"),
    R("train-into-notes-folder", "output: existing non-run folder",
      TRAIN.replace("{tmp}/r", "{tmp}/d"), notes_folder(),
      2, "not a training run folder", "d/notes.txt"),
    R("train-into-its-scene", "output: the input scene as output",
      TRAIN.replace("{tmp}/r", "{scene}"), None,
      2, "not a training run folder", "scene/scene.json scene/events.npz"),
    R("train-read-only", "output: read-only",
      TRAIN.replace("{tmp}/r", "{ro}/r"), None, 2, "cannot write in"),
    R("train-over-a-run", "output: existing run without --resume",
      TRAIN.replace("{tmp}/r", "{run}"), None,
      2, "already holds a training run", "run/checkpoint.pt run/config.json"),
    R("train-many-into-notes-folder", "output: existing folder of another kind",
      "train-many {scene} --out {tmp}/d --steps 1 " + TINY.replace("--backend", "--backends"),
      notes_folder(), 2, "not a train_many benchmark folder", "d/notes.txt"),
    R("train-many-missing-scene", "input: a scene folder that is not there",
      "train-many {scene} {tmp}/nope --out {tmp}/m --steps 1 --no-progress", None,
      2, "no such scene folder"),
    R("train-many-over-its-runs", "output: existing runs without --resume",
      "train-many {run} --out {tmp} --steps 1 --no-progress", many_folder,
      2, "already holds a training run", "runs/run-ngp/checkpoint.pt"),
    R("eval-into-notes-folder", "output: existing non-eval folder",
      "eval {run} --out {tmp}/d", notes_folder(), 2, "not an eval folder", "d/notes.txt"),
    R("eval-read-only", "output: read-only",
      "eval {run} --out {ro}/ev", None, 2, "cannot write in"),
    R("render-into-its-run", "output: the run folder as render output",
      "render {run} --out {run}", None,
      2, "not a render folder", "run/checkpoint.pt run/config.json"),
    R("render-read-only", "output: read-only",
      "render {run} --out {ro}/r", None, 2, "cannot write in"),
    R("mesh-read-only", "output: read-only (before loading the run)",
      "mesh {tmp}/no-run --out {ro}/m.ply", None, 2, "cannot write in"),
    R("mesh-onto-folder", "output: folder where a file goes",
      "mesh {run} --out {tmp}/d.ply", notes_folder("d.ply"),
      2, "is a folder, but a mesh file is a file", "d.ply/notes.txt"),
    R("mesh-png-onto-notes", "output: another kind of file",
      "mesh {run} --out {tmp}/m.ply --png {tmp}/notes.txt", a_file("notes.txt"),
      2, "not an image file", "notes.txt"),
    R("demo-into-notes-folder", "output: existing non-demo folder",
      "demo --out {tmp}/d", notes_folder(), 2, "not a demo folder", "d/notes.txt"),
    R("view-snapshot-onto-folder", "output: folder where a file goes",
      "view {run} --snapshot {tmp}/d", notes_folder(),
      2, "is a folder, but an image file is a file", "d/notes.txt"),
    R("view-without-display", "environment: no display",
      "view {run}", None, 2, "no display", env=NO_DISPLAY),
    R("bench-into-notes-folder", "output: existing non-benchmark folder",
      "bench knobs --out {tmp}/d", notes_folder(),
      2, "not a knobs benchmark folder", "d/notes.txt"),
    R("simulate-onto-folder", "output: folder where a file goes",
      "simulate --frames {tmp}/frames.npz --out {tmp}/d", chain(frames_file, notes_folder()),
      2, "is a folder, but an events file is a file", "d/notes.txt frames.npz"),
    R("train-onto-file", "output: file where a folder goes",
      TRAIN.replace("{tmp}/r", "{tmp}/f"), a_file("f"), 2, "is a file", "f"),
    R("eval-onto-file", "output: file where a folder goes",
      "eval {run} --out {tmp}/f", a_file("f"), 2, "is a file", "f"),
    R("render-onto-file", "output: file where a folder goes",
      "render {run} --out {tmp}/f", a_file("f"), 2, "is a file", "f"),
    R("demo-onto-file", "output: file where a folder goes",
      "demo --out {tmp}/f", a_file("f"), 2, "is a file", "f"),
    R("demo-read-only", "output: read-only", "demo --out {ro}/demo", None, 2, "cannot write in"),
    R("perturb-onto-notes-folder", "output: folder where a file goes",
      "perturb noise {scene} --fraction 0.05 --out {tmp}/d", notes_folder(),
      2, "must be a .npz file", "d/notes.txt"),
    R("bench-onto-file", "output: file where a folder goes",
      "bench kernels --out {tmp}/f", a_file("f"), 2, "is a file", "f"),
    R("view-snapshot-read-only", "output: read-only",
      "view {run} --snapshot {ro}/v.png", None, 2, "cannot write in"),
    R("eval-out-keeps-run-metrics", "output: eval --out elsewhere leaves RUN/metrics.json",
      "eval {run} --out {tmp}/ev --views 1 --scale 0.25 --no-progress",
      a_file("run/metrics.json", '{"mine": 1}'), 0, "", "run/metrics.json"),
]

MEMORY_ROWS = [
    R("synth-2000-frames-4096", "memory: synth frames",
      "synth --scene blocks --frames 2000 --size 4096x4096 --out {tmp}/big", None,
      2, "2000 frames at 4096x4096 needs at least", env=MEM),
    R("scene-n-views-1e12", "memory: n_views",
      "info {scene}", edit_scene_json(n_views=10**12),
      2, "n_views 1,000,000,000,000 needs at least"),
    R("mesh-resolution-100000", "memory: mesh grid",
      "mesh {run} --out {tmp}/m.ply --resolution 100000", None,
      2, "mesh --resolution 100000"),
    R("eval-scale-1000", "memory: eval scale",
      "eval {run} --scale 1000", None, 2, "eval --scale 1000", env=MEM),
    R("render-scale-1000", "memory: render scale",
      "render {run} --out {tmp}/r --scale 1000", None, 2, "render --scale 1000", env=MEM),
    R("render-orbit-1e8", "memory: render frames",
      "render {run} --out {tmp}/r --orbit 100000000", None, 2, "needs at least", env=MEM),
    R("train-rays-1e8", "flag: --rays beyond its range",
      TRAIN.replace("--rays 64", "--rays 100000000"), None, 2, "rays_per_step", env=MEM),
    R("train-rays-memory", "memory: ray batch",
      TRAIN.replace("--rays 64", "--rays 1000000"), None, 2, "--rays 1,000,000", env=MEM),
]

CONFIG_ROWS = [
    R("train-device-tpu", "flag: --device", TRAIN + " --device tpu", None, 2, "tpu"),
    R("train-seed-negative", "flag: --seed", TRAIN + " --seed -1", None, 2, "seed"),
    R("train-minutes-inf", "flag: --minutes", TRAIN.replace("--steps 1", "--minutes inf"),
      None, 2, "minutes"),
    R("train-minutes-0", "flag: --minutes", TRAIN.replace("--steps 1", "--minutes 0"),
      None, 2, "minutes"),
    R("train-steps-0", "flag: --steps", TRAIN.replace("--steps 1", "--steps 0"),
      None, 2, "steps"),
    R("train-lr-1e30", "diverging run",
      TRAIN.replace("--steps 1", "--steps 3") + f" --lr 1e30 --options '{VANILLA}'",
      None, 2, "lr|finite|NaN"),
    R("options-hidden-negative", "option", NGP + """ --options '{"hidden": -1}'""",
      None, 2, "hidden"),
    R("options-depth-negative", "option", TRAIN + """ --options '{"depth": -1}'""",
      None, 2, "depth"),
    R("options-log2-table-40", "option", NGP + """ --options '{"log2_table_size": 40}'""",
      None, 2, "log2_table_size"),
    R("options-cone-angle-negative", "option", NGP + """ --options '{"cone_angle": -5}'""",
      None, 2, "cone_angle"),
    R("scene-center-2-entries-info", "scene.json shape", "info {scene}", CENTER_2,
      2, "trajectory.center"),
    R("scene-center-2-entries-train", "scene.json shape", TRAIN, CENTER_2,
      2, "trajectory.center"),
]

FILE_ROWS = [
    R("events-truncated", "events: truncated", "info {scene}", truncate("scene/events.npz"),
      2, "truncated or corrupt"),
    R("events-unsorted", "events: unsorted", "info {scene}", edit_events(unsorted),
      2, "timestamps are not sorted"),
    R("events-out-of-sensor", "events: out of the sensor", "info {scene}", edit_events(outside),
      2, "is outside the 64x48 sensor"),
    R("events-nan", "events: NaN", "info {scene}", edit_events(nan_t), 2, "'t' is NaN or inf"),
    R("events-empty", "events: empty", "info {scene}", edit_events(empty), 2, "has no events"),
    R("events-truncated-train", "events: truncated", TRAIN, truncate("scene/events.npz"),
      2, "truncated or corrupt"),
    R("scene-json-broken", "scene.json: not JSON", "info {scene}",
      a_file("scene/scene.json", "{oops"), 2, "not valid JSON"),
    R("scene-missing", "scene: missing", TRAIN, lambda tmp: shutil.rmtree(tmp / "scene"),
      2, "no such|not found|does not exist"),
    R("checkpoint-truncated", "checkpoint: truncated", "eval {run} --no-progress",
      truncate("run/checkpoint.pt"), 2, "corrupt or truncated"),
    R("checkpoint-garbage", "checkpoint: not one", "render {run} --out {tmp}/r --orbit 1",
      a_file("run/checkpoint.pt", "hello"), 2, "checkpoint"),
    R("resume-without-checkpoint", "checkpoint: --resume without one",
      TRAIN.replace("{tmp}/r", "{tmp}/d") + " --resume", lambda tmp: (tmp / "d").mkdir(),
      2, "no checkpoint.pt to resume from"),
    R("render-bad-path", "camera path: not matrices",
      "render {run} --out {tmp}/r --path {tmp}/p.json", a_file("p.json", "[1, 2, 3]"),
      2, "list of 4x4 matrices"),
    R("aedat-junk", "AEDAT4: not one", "import {tmp}/junk.aedat4 --out {tmp}/s",
      a_file("junk.aedat4", "not an aedat file" * 10), 2, "not a readable AEDAT4"),
    R("aedat-missing", "AEDAT4: missing", "import {tmp}/missing.aedat4 --out {tmp}/s",
      None, 2, "no such"),
    R("eventnerf-pose-removed", "EventNeRF: a pose file removed", "info {en}",
      remove_view("pose"), 2, "intrinsics/r_00003.txt has no pose/r_00003.txt"),
    R("eventnerf-rgb-removed", "EventNeRF: an image removed", "info {en}",
      remove_view("rgb"), 2, "pose/r_00003.txt has no rgb/r_00003.*"),
    R("eventnerf-view-removed", "EventNeRF: a whole view removed", "info {en}",
      remove_view("pose", "intrinsics", "rgb"),
      0, "1 view(s) missing from the sequence r_00000..r_00009: r_00003"),
    R("argparse-frames-not-int", "argument: not a number",
      "synth --scene blocks --out {tmp}/s --frames many", None, 2, "invalid int value"),
]
if AEDAT is not None:
    FILE_ROWS += [
        R("aedat-truncated", "AEDAT4: truncated", "import {tmp}/cut.aedat4 --out {tmp}/s",
          cut_recording, 2, "truncated or corrupt"),
        R("aedat-no-events", "AEDAT4: no event stream",
          "import {aedat}/aedat__test_data_gray16.aedat4 --out {tmp}/s", None,
          2, "no event stream"),
    ]
# fmt: on

ROWS = OUTPUT_ROWS + MEMORY_ROWS + CONFIG_ROWS + FILE_ROWS


# ---------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="session")
def tiny_run(tiny_scene, tmp_path_factory):
    """A run folder trained for 2 vanilla steps on the tiny scene."""
    run = tmp_path_factory.mktemp("bad-input") / "run"
    argv = ["train", str(tiny_scene), "--out", str(run), "--steps", "2", "--options", VANILLA]
    assert main(argv + TINY.split()) == 0
    return run


def _writable(folder: Path) -> bool:
    try:
        tempfile.TemporaryFile(dir=folder).close()
        return True
    except OSError:
        return False


@pytest.fixture(scope="session")
def readonly_dir(tmp_path_factory):
    """A folder nobody can create files in: chmod 555, or /sys where that does not stop us
    (root ignores permissions)."""
    d = tmp_path_factory.mktemp("ro")
    d.chmod(0o555)
    try:
        for cand in (d, Path("/sys")):
            if cand.is_dir() and not _writable(cand):
                yield cand
                return
        pytest.skip("no read-only folder here (root, and /sys is writable)")
    finally:
        d.chmod(0o755)


def write_eventnerf(root: Path, n: int = 10) -> None:
    """A small EventNeRF folder (their layout): n views, frame-index times, no test split."""
    from fastenerf.config import TrajectoryConfig
    from fastenerf.data.rig import Turntable

    rng = np.random.default_rng(1)
    s = root / "train"
    for sub in ("events", "pose", "intrinsics", "rgb"):
        (s / sub).mkdir(parents=True)
    m = 400
    t = np.sort(rng.integers(0, n, m))
    t[-1] = n - 1
    np.savez(
        s / "events" / "e.npz",
        x=rng.integers(0, 346, m),
        y=rng.integers(0, 260, m),
        t=t,
        p=rng.choice([-1, 1], m),
    )
    c2w = Turntable(TrajectoryConfig(radius=0.9, period_us=n))(np.arange(n))
    K = [[280.0, 0, 170.5, 0], [0, 281.0, 131.5, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
    png = root / "p.png"
    import imageio.v3 as iio

    iio.imwrite(png, np.zeros((4, 4, 3), np.uint8))
    for i in range(n):
        np.savetxt(s / "pose" / f"r_{i:05d}.txt", c2w[i])
        np.savetxt(s / "intrinsics" / f"r_{i:05d}.txt", K)
        shutil.copy(png, s / "rgb" / f"r_{i:05d}.png")
    png.unlink()


@pytest.fixture
def place(tmp_path, tiny_scene, request):
    """The placeholders of the table for this test (copies made only when a row names them)."""

    def make(argv: list[str], setup) -> dict[str, str]:
        text = " ".join(argv)
        p = {"tmp": str(tmp_path)}
        if "{scene}" in text or "{run}" in text or setup is not None:
            shutil.copytree(tiny_scene, tmp_path / "scene")
            p["scene"] = str(tmp_path / "scene")
        if "{run}" in text:
            run = request.getfixturevalue("tiny_run")
            shutil.copytree(run, tmp_path / "run")
            p["run"] = str(tmp_path / "run")
        if "{ro}" in text:
            p["ro"] = str(request.getfixturevalue("readonly_dir"))
        if "{en}" in text:
            write_eventnerf(tmp_path / "en")
            p["en"] = str(tmp_path / "en")
        if "{aedat}" in text:
            p["aedat"] = str(AEDAT)
        return p

    return make


def digest(path: Path) -> dict[str, str]:
    """sha1 of a file, or of every file under a folder, by relative path."""
    files = [path] if path.is_file() else sorted(f for f in path.rglob("*") if f.is_file())
    return {
        str(f.relative_to(path.parent)): hashlib.sha1(f.read_bytes()).hexdigest() for f in files
    }


def fill(arg: str, places: dict[str, str]) -> str:
    """arg with its {name} placeholders filled (JSON braces in --options left alone)."""
    for k, v in places.items():
        arg = arg.replace("{" + k + "}", v)
    return arg


def run_cli(argv: list[str], capsys) -> tuple[int, str, str]:
    try:
        code = main(argv)
    except SystemExit as e:  # argparse's own errors
        code = e.code
    out, err = capsys.readouterr()
    return code, out, err


def error_lines(err: str) -> list[str]:
    """stderr without warnings and progress bars."""
    lines = [ln for ln in err.splitlines() if ln.strip()]
    return [ln for ln in lines if ": warning:" not in ln and not ln.startswith(" ")]


@pytest.mark.parametrize(
    "argv",
    [
        ["train", "SCENE", "--out", "RUN", "--refine-gauge", "bogus"],
        ["train", "SCENE", "--out", "RUN", "--smooth-order", "two"],
        ["train", "SCENE"],  # --out missing
        ["no-such-command"],
    ],
)
def test_argparse_errors_are_one_line(argv, tmp_path, capsys):
    """A bad choice, a bad number or a missing argument: one line, exit 2, no usage block."""
    code, _, err = run_cli([a.replace("RUN", str(tmp_path / "run")) for a in argv], capsys)
    lines = [ln for ln in err.splitlines() if ln.strip() and ": warning:" not in ln]
    assert code == 2 and len(lines) == 1 and ": error: " in lines[0], err
    assert not (tmp_path / "run").exists()


# ---------------------------------------------------------------------------- the tests


@pytest.mark.parametrize("case", ROWS)
def test_bad_input(case: Case, place, tmp_path, capsys, monkeypatch):
    for k, v in case.env.items():
        monkeypatch.setenv(k, v)
    monkeypatch.setenv("FASTENERF_PROGRESS", "0")
    places = place(case.argv, case.setup)
    if case.setup is not None:
        case.setup(tmp_path)
    before = {k: v for rel in case.keep for k, v in digest(tmp_path / rel).items()}
    argv = [fill(a, places) for a in case.argv]
    code, out, err = run_cli(argv, capsys)
    assert "Traceback" not in err
    lines = error_lines(err)
    fragments = case.message.split("|")
    if case.code == 0:
        assert code == 0, err
        assert all(not ln.startswith("fastenerf") for ln in lines), err  # no error line
        if case.message:
            assert any(f in err for f in fragments), err
    else:
        assert code == case.code, f"exit {code}; stderr: {err}"
        assert len(lines) == 1, f"not one line: {err!r}"
        assert lines[0].startswith(f"fastenerf {argv[0]}: error: "), lines[0]
        assert any(f in lines[0] for f in fragments), lines[0]
    after = {}
    for rel in case.keep:
        assert (tmp_path / rel).exists(), f"{rel} is gone"
        after.update(digest(tmp_path / rel))
    assert after == before, "a kept file changed"


def test_rows_cover_every_command_that_writes():
    from fastenerf.cli import COMMANDS

    named = {c.values[0].argv[0] for c in ROWS}
    assert set(COMMANDS) <= named | {"info"} and "info" in named


# ---------------------------------------------------------------------------- data loss


def test_synth_replaces_a_scene_folder_whole(tmp_path, capsys, monkeypatch):
    """Its own kind of output is replaced (no stale file of the old scene survives); --force
    replaces a foreign folder only when asked."""
    monkeypatch.setenv("FASTENERF_PROGRESS", "0")
    out = tmp_path / "s"
    synth = ["synth", "--scene", "blocks", "--frames", "4", "--size", "16x12", "--out"]
    assert main([*synth, str(out)]) == 0
    (out / "stale.txt").write_text("old scene\n")
    assert main([*synth, str(out)]) == 0
    assert (out / "scene.json").is_file() and not (out / "stale.txt").exists()
    notes = tmp_path / "d"
    notes.mkdir()
    (notes / "notes.txt").write_text("x\n")
    argv = [*synth, str(notes)]
    assert main(argv) == 2 and (notes / "notes.txt").read_text() == "x\n"
    assert main([*argv, "--force"]) == 0
    assert (notes / "scene.json").is_file() and not (notes / "notes.txt").exists()
    capsys.readouterr()


def test_simulate_replaces_its_events_file(tmp_path, monkeypatch):
    monkeypatch.setenv("FASTENERF_PROGRESS", "0")
    frames_file(tmp_path)
    argv = ["simulate", "--frames", str(tmp_path / "frames.npz"), "--out", str(tmp_path / "e.npz")]
    assert main(argv) == 0
    assert main([*argv, "--threshold", "0.1"]) == 0  # an events file: replaced
    with np.load(tmp_path / "e.npz") as z:
        assert float(z["pos_threshold"]) == pytest.approx(0.1)


@pytest.mark.skipif(AEDAT is None, reason="real AEDAT4 recordings not found (see conftest)")
def test_import_into_an_existing_scene_drops_its_old_test_views(tiny_scene, tmp_path, capsys):
    out = tmp_path / "scene"
    shutil.copytree(tiny_scene, out)
    assert (out / "test" / "poses.npz").is_file()
    assert main(["import", str(AEDAT / "aedat__test_data.aedat4"), "--out", str(out)]) == 0
    assert (out / "scene.json").is_file() and (out / "import.json").is_file()
    assert not (out / "test").exists()  # the old scene's ground truth is gone with it
    capsys.readouterr()


def test_claim_output_kinds(tmp_path):
    """The recognisers: each kind accepts its own outputs and an empty folder only."""
    from fastenerf import outputs as o
    from fastenerf.errors import InputError

    (tmp_path / "empty").mkdir()
    for kind in (o.SCENE, o.RUN, o.RENDER, o.EVAL, o.DEMO):
        o.claim_output(tmp_path / "empty", kind)
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text('{"train": {}}')
    o.claim_output(run, o.RUN)
    with pytest.raises(InputError, match="not a scene folder"):
        o.claim_output(run, o.SCENE)
    ev = tmp_path / "ev"
    ev.mkdir()
    (ev / "0003.png").write_bytes(b"")
    o.claim_output(ev, o.EVAL)
    (ev / "mine.txt").write_text("x")
    with pytest.raises(InputError, match="not an eval folder"):
        o.claim_output(ev, o.EVAL)
    np.savez(tmp_path / "e.npz", x=[1], y=[1], t=[1], p=[1])
    o.claim_output(tmp_path / "e.npz", o.EVENTS)
    (tmp_path / "c.json").write_text('{"trajectory": {}, "solver": {}}')
    o.claim_output(tmp_path / "c.json", o.CALIBRATION)
    with pytest.raises(InputError, match="not a training run folder; choose another path$"):
        o.claim_output(ev, o.RUN, force=None)  # no --force to suggest
    with pytest.raises(InputError, match="give a scene folder path"):
        o.claim_output(".", o.SCENE)
    assert not list(tmp_path.glob(".fastenerf-probe*"))  # the probe leaves nothing


def test_memory_check_names_estimate_and_limit(monkeypatch):
    from fastenerf.errors import InputError
    from fastenerf.memory import check_memory, check_ray_batch, format_bytes, parse_bytes

    assert parse_bytes("8G") == 8 << 30 and parse_bytes("1.5K") == 1536
    assert format_bytes(8e12) == "7.28 TiB"
    monkeypatch.setenv("FASTENERF_MEMORY_LIMIT", "1M")
    check_memory(1000, "small")
    with pytest.raises(InputError, match=r"big needs at least 2.00 MiB .* 1.00 MiB cap"):
        check_memory(2 << 20, "big")
    with pytest.raises(InputError, match="--rays 1,000,000"):
        check_ray_batch(1_000_000, 64, 32)
    monkeypatch.setenv("FASTENERF_MEMORY_LIMIT", "lots")
    with pytest.raises(InputError, match="FASTENERF_MEMORY_LIMIT='lots'"):
        check_memory(1, "x")


def test_progress_bars_are_quiet_off_a_terminal(capsys, monkeypatch):
    from fastenerf.progress import bars_wanted, progress_bar

    monkeypatch.delenv("FASTENERF_PROGRESS", raising=False)
    assert not bars_wanted()  # pytest captures stderr: not a terminal
    for _ in progress_bar(range(50), desc="x"):
        pass
    assert capsys.readouterr().err == ""
    monkeypatch.setenv("FASTENERF_PROGRESS", "1")
    assert bars_wanted() and not bars_wanted(enabled=False)
    assert os.environ["FASTENERF_PROGRESS"] == "1"
