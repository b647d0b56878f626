"""Replay a run's sample-buffer readings through other capacity rules: how many recaptures
and how many slots each rule would have given on the very wants the run saw.

    python -m benchmarks.capacity_replay DIR [DIR ...] [--patience 1 2 4 8] [--out TABLE.md]

DIR is an `error_vs_time` output folder (or LABEL=DIR, as `run_table` takes them) whose
curve points carry `capacity_readings`: the most samples a march wanted between two
occupancy updates, which the marched buffer's capacity followed (`SampleCapacity`). The
wants do not depend on the rule (bar the rays an overflow drops), so the readings replay
exactly through `SampleCapacity.apply` with the run's headroom and shrink share and each
`--patience` (`capacity_shrink_patience`). Per run and patience: capacity changes (each a
CUDA-graph recapture), the turns back among them (a shrink after a growth or the other way),
the mean capacity over the readings against the first patience's, and the readings that
would have overflowed (some march's rays dropped). Printed, or written atomically to
--out (an existing file is refused; nothing is lost).
"""

from __future__ import annotations

import argparse
from itertools import pairwise
from typing import Any

from fastenerf.backends import MarcherOptions
from fastenerf.errors import InputError, require
from fastenerf.fields.capacity import SampleCapacity

from .cli import benchmark_main, check_table_out, print_or_write_table
from .run_table import load_run, parse_item


def readings_of(run: dict[str, Any], where: str) -> list[int]:
    """Every capacity reading of an error_vs_time run, oldest first."""
    got = [p.get("capacity_readings") for p in run["points"]]
    if all(r is None for r in got):
        raise InputError(f"{where}: its points carry no capacity_readings (an older run, or no"
                         " fixed-capacity buffers)")  # fmt: skip
    return [int(w) for r in got if r for w in r]


def replay(readings: list[int], headroom: float, shrink_below: float, patience: int) -> dict:
    """The capacity rule with `patience` over `readings`: changes, turns back, mean
    capacity (slots) and overflowing readings, the first reading sizing it exactly.

    A reading is applied one update after its steps ran (`SampleCapacity.refresh`): the
    steps of reading k ran under the capacity that reading k - 2 left, which is what it
    overflowed or not."""
    cap = SampleCapacity(headroom=headroom, shrink_below=shrink_below, shrink_patience=patience)
    sizes = []
    for w in readings:
        cap.apply(w)
        sizes.append(cap.capacity)
    ups = [b > a for a, b in pairwise(sizes) if b != a]
    return {
        "changes": len(ups),
        "turns": sum(a != b for a, b in pairwise(ups)),
        "mean_slots": sum(sizes) / max(len(sizes), 1),
        "overflows": sum(w > c for w, c in zip(readings[2:], sizes, strict=False)),
    }


def table(items: list[str], patiences: list[int]) -> str:
    head = ["run", "readings", *[f"patience {k}" for k in patiences]]
    lines = [
        "changes (turns back) · mean slots against patience "
        f"{patiences[0]} · readings that overflowed",
        "",
        "| " + " | ".join(head) + " |",
        "|---|---:|" + "---|" * len(patiences),
    ]
    for label, folder in (parse_item(i) for i in items):
        run = load_run(folder)
        readings = readings_of(run, folder)
        # the run's own values where its options set them (flat, as `--set` gives them)
        given = (run.get("train_config") or {}).get("backend_options") or {}
        h = given.get("capacity_headroom", MarcherOptions.capacity_headroom)
        s = given.get("capacity_shrink_below", MarcherOptions.capacity_shrink_below)
        res = [replay(readings, h, s, k) for k in patiences]
        base = res[0]["mean_slots"] or 1.0
        cells = [
            f"{r['changes']} ({r['turns']}) · {r['mean_slots'] / base - 1:+.1%} · {r['overflows']}"
            for r in res
        ]
        lines.append(f"| {label} | {len(readings)} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("items", nargs="+", metavar="[LABEL=]DIR")
    p.add_argument("--patience", nargs="+", type=int, default=[1, 2, 4, 8],
                   help="capacity_shrink_patience values to replay")  # fmt: skip
    p.add_argument("--out", default=None, help="Markdown file to write (default: print)")


def run(args: argparse.Namespace) -> int:
    require(all(1 <= k <= 64 for k in args.patience), "--patience: values in [1, 64]")
    check_table_out(args.out)
    return print_or_write_table(table(args.items, args.patience), args.out)


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    return benchmark_main("capacity_replay", __doc__, add_arguments, run, argv, prog)


if __name__ == "__main__":
    raise SystemExit(main())
