"""The command-line entry every benchmark shares: parse, run, one-line errors."""

from __future__ import annotations

import argparse
import shutil
import sys
from collections.abc import Callable
from pathlib import Path

from fastenerf.errors import FastenerfError, InputError, require
from fastenerf.io import atomic_path
from fastenerf.outputs import OutputKind, claim_output

# A benchmark's --out folder: written into (its own files replaced one by one), never
# replaced whole, so any folder is one; a file there, or an unwritable place, is refused.
BENCH_FOLDER = OutputKind("benchmark output folder", True, lambda p: True, replaced_whole=False)
# A benchmark's results as one JSON file (`--out` / `--json` FILE.json).
JSON_FILE = OutputKind("JSON file", False, lambda p: p.suffix.lower() == ".json")


def benchmark_main(
    name: str,
    doc: str,
    add_arguments: Callable[[argparse.ArgumentParser], None],
    run: Callable[[argparse.Namespace], int],
    argv: list[str] | None = None,
    prog: str | None = None,
    out_folder: bool = False,
) -> int:
    """Parse `argv` with the benchmark's arguments and run it; a FastenerfError (bad input)
    prints one line "NAME: error: ..." and returns 2. `doc`: the module docstring (its first
    paragraph is the help text); out_folder: `--out` names a folder the benchmark writes into,
    checked before any work (`fastenerf.outputs.claim_output`)."""
    p = argparse.ArgumentParser(
        prog=prog or f"python -m benchmarks.{name}", description=doc.split("\n\n")[0]
    )
    add_arguments(p)
    args = p.parse_args(argv)
    out = getattr(args, "out", None)
    fresh = first_missing(Path(out)) if out else None
    try:
        if out_folder and out:
            claim_output(out, BENCH_FOLDER)
        return run(args)
    except FastenerfError as e:
        if fresh is not None:
            drop_if_empty(fresh)
        print(f"{name}: error: {e}", file=sys.stderr)
        return 2


def first_missing(path: Path) -> Path | None:
    """The outermost folder of `path` that does not exist yet (`path` itself at most), or
    None when `path` exists: what a run making `path` would create."""
    path, top = path.absolute(), None
    while not path.exists() and path != path.parent:
        path, top = path.parent, path
    return top


def drop_if_empty(folder: Path) -> None:
    """Remove `folder` (made by a run that was then refused) if no file was written in it:
    bad input leaves nothing behind, and a folder holding any file is kept."""
    if folder.is_dir() and not folder.is_symlink():
        if not any(not p.is_dir() or p.is_symlink() for p in folder.rglob("*")):
            shutil.rmtree(folder)


def add_run_arguments(p: argparse.ArgumentParser, out: str) -> None:
    """The options every device benchmark takes: --device, --out (default `out`), --commit
    (recorded; the device machine's copy of the tree has no .git) and --quiet."""
    p.add_argument("--device", default="auto", help="cuda, cuda:N, cpu or auto")
    p.add_argument("--out", default=out, help="output folder")
    p.add_argument("--commit", default=None, help="git commit to record")
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def check_table_out(out: str | None) -> None:
    """Refuse a Markdown table's --out before any work: it must be a new .md file."""
    if out is not None:
        path = Path(out)
        require(path.suffix.lower() == ".md", f"{path}: the table is a .md file")
        require(not path.exists(), f"{path} exists: give a new file (nothing was written)")


def print_or_write_table(text: str, out: str | None, quiet: bool = False) -> int:
    """Print `text`, or write it atomically to `out` (checked by `check_table_out`) and
    print its name (not when quiet). Returns 0."""
    if out is None:
        print(text, end="")
        return 0
    try:
        with atomic_path(out) as tmp:
            tmp.write_text(text)
    except OSError as e:
        raise InputError(f"{out}: cannot be written ({e.strerror or e})") from None
    if not quiet:
        print(out)
    return 0
