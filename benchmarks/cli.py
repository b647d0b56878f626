"""The command-line entry every benchmark shares: parse, run, one-line errors."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable

from fastenerf.errors import FastenerfError


def benchmark_main(
    name: str,
    doc: str,
    add_arguments: Callable[[argparse.ArgumentParser], None],
    run: Callable[[argparse.Namespace], int],
    argv: list[str] | None = None,
    prog: str | None = None,
) -> int:
    """Parse `argv` with the benchmark's arguments and run it; a FastenerfError (bad input)
    prints one line "NAME: error: ..." and returns 2. `doc`: the module docstring (its first
    paragraph is the help text)."""
    p = argparse.ArgumentParser(
        prog=prog or f"python -m benchmarks.{name}", description=doc.split("\n\n")[0]
    )
    add_arguments(p)
    args = p.parse_args(argv)
    try:
        return run(args)
    except FastenerfError as e:
        print(f"{name}: error: {e}", file=sys.stderr)
        return 2
