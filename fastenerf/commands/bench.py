"""`fastenerf bench error-vs-time|knobs|kernels|study ...`: run a benchmark of the repo's
benchmarks/ folder.

The benchmarks are a plain folder at the repository root (not installed with the package); this
command finds it beside the package when it is not importable, and hands the remaining
arguments to the benchmark's own `main(argv)` (`fastenerf bench knobs --help` shows them).
"""

from __future__ import annotations

import argparse
import importlib
import inspect
import sys
from pathlib import Path

HELP = (
    "benchmarks: error against training time (ngp vs vanilla), ngp accuracy knobs, kernels, "
    "robustness studies (pose error, noise, ablation)"
)

BENCHMARKS = {
    "error-vs-time": "benchmarks.error_vs_time",
    "knobs": "benchmarks.knobs",
    "kernels": "benchmarks.kernels",
    "study": "benchmarks.study",
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("benchmark", choices=sorted(BENCHMARKS), help="which benchmark")
    p.add_argument(
        "bench_args",
        nargs=argparse.REMAINDER,
        help="arguments of the benchmark (see fastenerf bench NAME --help)",
    )


def repo_root() -> Path:
    """The checkout this package was installed from (editable install): benchmarks/ is there."""
    return Path(__file__).resolve().parents[2]


def import_benchmark(name: str):
    """Import `benchmarks.<module>` for `name`, from the repo root if it is not on sys.path."""
    from ..errors import InputError

    module = BENCHMARKS[name]
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as e:
        if e.name not in ("benchmarks", module):
            raise
    root = repo_root()
    if not (root / "benchmarks" / "__init__.py").is_file():
        raise InputError(
            f"benchmarks/ not found beside the package (looked in {root}); run "
            "from a source checkout"
        )
    if str(root) not in sys.path:
        sys.path.insert(0, str(root))
    sys.modules.pop("benchmarks", None)  # a failed import may have cached another package
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as e:
        if e.name != module:
            raise
        raise InputError(
            f"the {name!r} benchmark is not there yet ({root / 'benchmarks'} has no "
            f"{module.split('.')[-1]}.py)"
        ) from None


def run(args: argparse.Namespace) -> int:
    mod = import_benchmark(args.benchmark)
    if not hasattr(mod, "main"):
        from ..errors import InputError

        raise InputError(f"{mod.__name__} has no main(argv)")
    argv = list(args.bench_args)
    if "prog" in inspect.signature(mod.main).parameters:
        return int(mod.main(argv, prog=f"fastenerf bench {args.benchmark}") or 0)
    return int(mod.main(argv) or 0)
