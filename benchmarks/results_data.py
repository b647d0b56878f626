"""Run data of `benchmarks/results/` kept packed: each results folder's JSON, JSON lines and
logs live in its own `data.tar.xz` (git ignores them unpacked).

    python -m benchmarks.results_data unpack [FOLDER ...]   # restore them in place
    python -m benchmarks.results_data pack FOLDER ...       # (re)pack a folder's data
    python -m benchmarks.results_data list [FOLDER ...]     # what each archive holds

The device machine is sent the whole working tree with every call (64 MiB in all), and the
results' run data was most of it (23 MB of JSON, 1.6 MB packed): packed, each call has room for
larger Warp pieces and whole scenes. Tables, READMEs, plots and scripts stay unpacked; the
tools that read run folders (`benchmarks.run_table`, `compare_runs`, `capacity_replay`) need
`unpack` first. FOLDER is a folder under benchmarks/results (default: every one with an
archive).

`pack` adds the folder's data files on disk to what its archive already holds (a file on
disk replaces the archived one of the same path) and writes the archive atomically; the files
stay on disk. `unpack` never replaces a file on disk that differs from the archive's (one
line, exit code 2, nothing written); `--force` does.
"""

from __future__ import annotations

import argparse
import io
import os
import sys
import tarfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent / "results"
ARCHIVE = "data.tar.xz"
SUFFIXES = (".json", ".jsonl", ".log")


class DataError(Exception):
    """Bad input: reported as one line, exit code 2."""


def data_files(folder: Path) -> dict[str, Path]:
    """The folder's run data on disk: {path relative to folder (posix): file}."""
    return {
        p.relative_to(folder).as_posix(): p
        for p in sorted(folder.rglob("*"))
        if p.is_file() and p.suffix in SUFFIXES and not p.is_symlink()
    }


def _safe(name: str, archive: Path) -> str:
    parts = Path(name).parts
    if Path(name).is_absolute() or ".." in parts or not parts:
        raise DataError(f"{archive}: member {name!r} would land outside its folder")
    return name


def read_archive(archive: Path) -> dict[str, bytes]:
    """{member path: content} of a data archive (regular files only, checked paths)."""
    try:
        with tarfile.open(archive, "r:xz") as tar:
            out = {}
            for m in tar.getmembers():
                if not m.isfile():
                    raise DataError(f"{archive}: member {m.name!r} is not a regular file")
                out[_safe(m.name, archive)] = tar.extractfile(m).read()
            return out
    except (tarfile.TarError, OSError, EOFError) as e:
        raise DataError(f"{archive}: not a readable .tar.xz ({e})") from None


def _write_atomic(path: Path, data: bytes) -> None:
    """data to path through a new file beside it (open's mode and umask) and a rename."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "xb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def pack(folder: Path) -> int:
    """Write folder/data.tar.xz: the archive's members plus the data files on disk (disk
    wins), sorted, with fixed metadata (the same files give the same bytes). Returns members."""
    archive = folder / ARCHIVE
    members = read_archive(archive) if archive.exists() else {}
    for name, p in data_files(folder).items():
        members[name] = p.read_bytes()
    if not members:
        raise DataError(f"{folder}: no {', '.join(SUFFIXES)} files to pack")
    write_archive(archive, members)
    return len(members)


def write_archive(archive: Path, members: dict[str, bytes]) -> None:
    """members ({path: content}) as a .tar.xz, sorted, fixed metadata, written atomically."""
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:xz", preset=9) as tar:
        for name in sorted(members):
            info = tarfile.TarInfo(name)
            info.size, info.mode, info.mtime = len(members[name]), 0o644, 0
            tar.addfile(info, io.BytesIO(members[name]))
    _write_atomic(archive, buf.getvalue())


def unpack(folder: Path, force: bool = False) -> int:
    """Restore folder/data.tar.xz's files in place; returns how many were written."""
    members = read_archive(folder / ARCHIVE)
    if not force:
        for name, data in members.items():
            p = folder / name
            if p.exists() and p.read_bytes() != data:
                raise DataError(f"{p}: differs from {folder / ARCHIVE}'s (--force replaces it)")
    n = 0
    for name, data in members.items():
        p = folder / name
        if p.exists() and p.read_bytes() == data:
            continue
        p.parent.mkdir(parents=True, exist_ok=True)
        _write_atomic(p, data)
        n += 1
    return n


def folders(names: list[str], root: Path) -> list[Path]:
    """The folders named (under root, or as given), else every folder of root with an archive."""
    if not names:
        return sorted(p.parent for p in root.glob(f"*/{ARCHIVE}"))
    out = []
    for n in names:
        p = Path(n) if Path(n).is_dir() else root / n
        if not p.is_dir():
            raise DataError(f"{n}: not a folder (nor one under {root})")
        out.append(p)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m benchmarks.results_data", description=__doc__.split("\n\n")[0]
    )
    ap.add_argument("action", choices=["pack", "unpack", "list"])
    ap.add_argument("folders", nargs="*", help="results folders (default: every archived one)")
    ap.add_argument("--force", action="store_true", help="unpack over differing files")
    ap.add_argument("--root", default=str(ROOT), help=argparse.SUPPRESS)
    a = ap.parse_intermixed_args(argv)
    try:
        if a.action == "pack" and not a.folders:
            raise DataError("pack: name the folders to pack")
        for f in folders(a.folders, Path(a.root)):
            if a.action == "pack":
                print(f"{f}: {pack(f)} files in {ARCHIVE}")
            elif a.action == "unpack":
                print(f"{f}: {unpack(f, a.force)} files written")
            else:
                if not (f / ARCHIVE).exists():
                    raise DataError(f"{f}: no {ARCHIVE}")
                for name in sorted(read_archive(f / ARCHIVE)):
                    print(f / name)
    except DataError as e:
        print(f"results_data: error: {e}", file=sys.stderr)
        return 2
    except OSError as e:  # a folder that cannot be written, a path that is no file, ...
        print(f"results_data: error: {e.filename or ''}: {e.strerror or e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
