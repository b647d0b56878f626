"""`fastenerf <command>`: parses arguments and calls library functions.

Each command lives in `fastenerf/commands/<name>.py` with `HELP`, `add_arguments(parser)`
and `run(args) -> int`; heavy imports (torch, warp, GL) happen inside `run` so that
`--help` is instant. A `FastenerfError` is printed as one line and exits 2.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import warnings

from .errors import FastenerfError

COMMANDS = [
    "synth",
    "simulate",
    "info",
    "train",
    "train-many",
    "eval",
    "render",
    "mesh",
    "view",
    "bench",
    "calibrate",
    "import",
    "demo",
    "perturb",
]


def _module_name(name: str) -> str:
    return f"fastenerf.commands.{name.replace('import', 'import_').replace('-', '_')}"


def _module(name: str):
    return importlib.import_module(_module_name(name))


class OneLineParser(argparse.ArgumentParser):
    """argparse, but a bad argument is one line ("fastenerf CMD: error: ...") and exit 2,
    not the usage block first: the house rule for bad input. `--help` has the usage."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog="fastenerf",
        description="Radiance fields from a single (colour) event camera, trained fast.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        try:
            mod = _module(name)
        except ModuleNotFoundError as e:
            if e.name != _module_name(name):
                raise
            continue  # command not built yet
        p = sub.add_parser(name, help=mod.HELP, description=mod.HELP)
        mod.add_arguments(p)
        p.set_defaults(_run=mod.run)
    return parser


def _one_line_warning(command: str):
    """Warnings as one line each ("fastenerf CMD: warning: ..."), without the source line."""

    def show(message, category, filename, lineno, file=None, line=None):
        text = str(message).splitlines()[0] if str(message) else category.__name__
        print(f"fastenerf {command}: warning: {text}", file=file or sys.stderr)

    return show


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "_run", None):
        parser.print_help()
        return 2
    try:
        with warnings.catch_warnings():
            warnings.showwarning = _one_line_warning(args.command)
            return int(args._run(args) or 0)
    except FastenerfError as e:
        print(f"fastenerf {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"fastenerf {args.command}: interrupted", file=sys.stderr)
        return 130


def console_main() -> None:
    """The `fastenerf` executable (and `python -m fastenerf.cli`): `main`, then exit.

    A torchrun rank that has left its gloo group exits at once (`os._exit`, after flushing),
    without the interpreter's teardown: there, now and then, a gloo thread still joinable is
    destroyed and the rank aborts in C++ ("terminate called without an active exception",
    SIGABRT) after its work is done and written. Every output is on disk by then (written
    atomically), so nothing the teardown would do is lost."""
    code = main()
    from .distributed import left_a_group

    if left_a_group():
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    sys.exit(code)


if __name__ == "__main__":
    console_main()
