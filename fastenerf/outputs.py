"""Where commands write: one policy for every output path, checked before any work starts.

Every command that writes calls `claim_output(path, KIND, force=...)` at the very start of
its `run()`, before it reads its inputs or computes anything. The call

- refuses a path that exists but is not this command's own kind of output (an `InputError`,
  one line, exit 2), unless `force` (`--force`): a folder of notes is never replaced by a
  scene, a frames file never by an events file, a run folder never by a render;
- always refuses a file where a folder is needed and a folder where a file is needed
  (`--force` does not turn one into the other);
- checks that the path can be written: the nearest existing ancestor is a folder in which a
  probe file can be created (so a read-only or missing-permission `--out` fails here, not
  after the work), and an existing folder that is written into (not replaced) is writable.

Nothing is written by the check except that probe (created and removed at once); missing
parent folders are created only by the writers, when the output is written.

How a command recognises its own kind of output (`OutputKind.recognise`):

| kind        | a folder / file is this kind when                                           |
| ----------- | --------------------------------------------------------------------------- |
| scene       | folder with `scene.json`, or an EventNeRF folder (`train/events/`, or       |
|             | `fastenerf_scene.json`)                                                     |
| run         | folder with `checkpoint.pt`, or a `config.json` holding a "train" section   |
| render      | folder with `rgb/` or `depth/` frames, or `video.mp4` / `video.gif`         |
| eval        | folder with `sheet.png`, or holding only NNNN.png images                    |
| demo        | folder with `scene/`, `run/` or `orbit/` of those kinds                     |
| bench       | folder with `runs/` or the benchmark's `<name>.json`                        |
| events      | `.npz` holding arrays x, y, t, p, or `.h5` with them                        |
| mesh        | file named `.ply`, `.glb` or `.obj`                                         |
| image       | file named `.png`, `.jpg`, `.jpeg` or `.gif`                                |
| calibration | JSON object with "trajectory" and "solver" (what `calibrate` writes)        |
| threshold   | JSON object with "ratio", "n_pos", "n_neg" (`calibrate --threshold-ratio`)  |

An empty folder is every folder kind. Outputs of the same kind are replaced atomically by
the writers (`fastenerf.io.atomic_dir` / `atomic_path`): scene folders whole (so an old
`test/` never survives an import or a synth), files by rename.
"""

from __future__ import annotations

import json
import os
import re
import tempfile
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from .errors import InputError


@dataclass(frozen=True)
class OutputKind:
    """An output's kind: `name` for messages, folder or file, and how to recognise one."""

    name: str
    is_dir: bool
    recognise: Callable[[Path], bool]
    replaced_whole: bool = True  # written by replacing the path, not into an existing folder


def claim_output(
    path: str | os.PathLike,
    kind: OutputKind,
    *,
    force: bool | None = False,
    flag: str = "--out",
) -> Path:
    """Check that `kind` may be written at `path` (see the module docstring); return the path.

    force: the command's --force (None: the command has no --force, e.g. `train`, whose run
    folders are continued with --resume, never replaced); flag: the option that named the
    path, for the messages ("--out", "--png", ...).
    Raises `InputError` (one line, naming the path and what to do) when it may not.
    """
    p = Path(path)
    if str(path) == "" or p.name in ("", ".", ".."):
        raise InputError(f"{flag} {str(path)!r}: give a {kind.name} path, not a bare folder name")
    if p.is_symlink() and not p.exists():
        raise InputError(f"{flag} {p}: is a broken symbolic link")
    if p.exists():
        _check_existing(p, kind, force, flag)
    _check_writable(p, kind, flag)
    return p


def _check_existing(p: Path, kind: OutputKind, force: bool | None, flag: str) -> None:
    a = "an" if kind.name[0] in "aeiou" else "a"
    if kind.is_dir and not p.is_dir():
        raise InputError(
            f"{flag} {p}: is a file, but {a} {kind.name} is a folder; choose another path"
        )
    if not kind.is_dir and p.is_dir():
        raise InputError(
            f"{flag} {p}: is a folder, but {a} {kind.name} is a file; choose another path"
        )
    if force or kind.recognise(p):
        return
    what = "a folder" if kind.is_dir else "a file"
    verb = "replace it" if kind.replaced_whole else "write into it"
    fix = "choose another path" + ("" if force is None else f" or pass --force to {verb}")
    raise InputError(f"{flag} {p}: exists and is {what} that is not {a} {kind.name}; {fix}")


def _check_writable(p: Path, kind: OutputKind, flag: str) -> None:
    target = p.resolve()
    if p.is_dir() and not kind.replaced_whole:
        _probe(target, p, flag)  # written into: the folder itself must take new files
        return
    anc = target.parent  # where the temporary sibling is made and renamed from
    while not anc.exists():
        anc = anc.parent
    if not anc.is_dir():
        raise InputError(f"{flag} {p}: cannot be created: {anc} is a file, not a folder")
    _probe(anc, p, flag)


def _probe(folder: Path, p: Path, flag: str) -> None:
    try:
        fd, tmp = tempfile.mkstemp(prefix=".fastenerf-probe.", dir=folder)
    except OSError as e:
        raise InputError(
            f"{flag} {p}: cannot write in {folder} ({e.strerror or e}); choose a writable path"
        ) from None
    os.close(fd)
    os.unlink(tmp)


# ---------------------------------------------------------------------------- recognisers


def _is_empty_dir(p: Path) -> bool:
    return p.is_dir() and not any(p.iterdir())


def _scene(p: Path) -> bool:
    return (
        _is_empty_dir(p)
        or (p / "scene.json").is_file()
        or (p / "fastenerf_scene.json").is_file()
        or (p / "train" / "events").is_dir()
    )


def _run(p: Path) -> bool:
    if _is_empty_dir(p) or (p / "checkpoint.pt").is_file():
        return True
    return "train" in _json_object(p / "config.json")


def _render(p: Path) -> bool:
    return (
        _is_empty_dir(p)
        or (p / "rgb").is_dir()
        or (p / "depth").is_dir()
        or any((p / f"video{s}").is_file() for s in (".mp4", ".gif"))
    )


_NUMBERED_PNG = re.compile(r"\d+\.png")


def _eval(p: Path) -> bool:
    if _is_empty_dir(p) or (p / "sheet.png").is_file():
        return True
    return all(_NUMBERED_PNG.fullmatch(c.name) for c in p.iterdir() if not c.name.startswith("."))


def _demo(p: Path) -> bool:
    subs = [(p / "scene", _scene), (p / "run", _run), (p / "orbit", _render)]
    present = [(s, f) for s, f in subs if s.exists()]
    if _is_empty_dir(p):
        return True
    return bool(present) and all(s.is_dir() and f(s) for s, f in present)


def _events(p: Path) -> bool:
    if p.suffix == ".npz":
        try:
            with zipfile.ZipFile(p) as z:
                names = {n.removesuffix(".npy") for n in z.namelist()}
        except (zipfile.BadZipFile, OSError):
            return False
        return {"x", "y", "t", "p"} <= names
    if p.suffix in (".h5", ".hdf5"):
        try:
            import h5py

            with h5py.File(p, "r") as f:
                g = f["events"] if "events" in f else f
                return all(k in g for k in ("x", "y", "t", "p"))
        except (OSError, KeyError, ValueError):
            return False
    return False


def _calibration(p: Path) -> bool:
    d = _json_object(p)
    return "trajectory" in d and "solver" in d


def _threshold_ratio(p: Path) -> bool:
    d = _json_object(p)
    return "ratio" in d and "n_pos" in d and "n_neg" in d


def _json_object(path: Path) -> dict:
    try:
        d = json.loads(path.read_text())
    except (OSError, ValueError, UnicodeDecodeError):
        return {}
    return d if isinstance(d, dict) else {}


def _suffix(*suffixes: str) -> Callable[[Path], bool]:
    return lambda p: p.suffix.lower() in suffixes


def bench_kind(name: str) -> OutputKind:
    """A benchmark's output folder: `runs/` or `<name>.json` (name: module, e.g. "knobs")."""
    return OutputKind(
        f"{name} benchmark folder",
        True,
        lambda p: _is_empty_dir(p) or (p / "runs").is_dir() or (p / f"{name}.json").is_file(),
        replaced_whole=False,
    )


SCENE = OutputKind("scene folder", True, _scene)
SCENE_UPDATE = OutputKind("scene folder", True, _scene, replaced_whole=False)  # files rewritten
RUN = OutputKind("training run folder", True, _run, replaced_whole=False)
RENDER = OutputKind("render folder", True, _render, replaced_whole=False)
EVAL = OutputKind("eval folder", True, _eval, replaced_whole=False)
DEMO = OutputKind("demo folder", True, _demo, replaced_whole=False)
EVENTS = OutputKind("events file", False, _events)
MESH = OutputKind("mesh file", False, _suffix(".ply", ".glb", ".obj"))
IMAGE = OutputKind("image file", False, _suffix(".png", ".jpg", ".jpeg", ".gif"))
CALIBRATION = OutputKind("calibration file", False, _calibration)
THRESHOLD_RATIO = OutputKind("threshold-ratio file", False, _threshold_ratio)
