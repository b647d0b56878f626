"""`fastenerf bench error-vs-time|knobs|kernels|step-time|study|toyset|prior-residual ...`: run a
benchmark of the repo's benchmarks/ folder.

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
    "step time of option variants, robustness studies (pose error, mount error, noise, "
    "ablation), the mesh scene defaults are measured on (toyset), the pose error the motion "
    "prior leaves (prior-residual)"
)

BENCHMARKS = {
    "error-vs-time": "benchmarks.error_vs_time",
    "knobs": "benchmarks.knobs",
    "kernels": "benchmarks.kernels",
    "step-time": "benchmarks.step_time",
    "study": "benchmarks.study",
    "toyset": "benchmarks.toyset",
    "prior-residual": "benchmarks.prior_residual",
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--force",
        action="store_true",
        help="let the benchmark write into an --out that is not a benchmark folder "
        "(give it before NAME)",
    )
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


def bench_out(argv: list[str]) -> str | None:
    """The --out a benchmark's arguments name (None: the benchmark's default)."""
    for i, a in enumerate(argv):
        if a == "--out" and i + 1 < len(argv):
            return argv[i + 1]
        if a.startswith("--out="):
            return a.split("=", 1)[1]
    return None


def run(args: argparse.Namespace) -> int:
    from ..outputs import bench_kind, claim_output

    out = bench_out(list(args.bench_args))
    if out is not None and "-h" not in args.bench_args and "--help" not in args.bench_args:
        name = BENCHMARKS[args.benchmark].split(".")[-1]
        claim_output(out, bench_kind(name), force=args.force)
    mod = import_benchmark(args.benchmark)
    if not hasattr(mod, "main"):
        from ..errors import InputError

        raise InputError(f"{mod.__name__} has no main(argv)")
    argv = list(args.bench_args)
    if "prog" in inspect.signature(mod.main).parameters:
        return int(mod.main(argv, prog=f"fastenerf bench {args.benchmark}") or 0)
    return int(mod.main(argv) or 0)
