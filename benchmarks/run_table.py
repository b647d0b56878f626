"""A Markdown table of several error-vs-time outputs, one row per run: what RESULTS.md's
per-lease tables hold.

    python -m benchmarks.run_table DIR [DIR ...] [--at 5 10 15 30 60] [--base NAME]
        [--out TABLE.md]

DIR is an `error_vs_time` output folder (its error_vs_time.json; the first run in it), or
LABEL=DIR. Without a label a row is named by the folder's last two parts, SCENE/NAME as
`benchmarks/gpu_runs60.sh` lays its runs out. Columns:
- PSNR (dB) at each `--at` time: the evaluation scheduled at that training time, "—" if none;
- Δ: the last PSNR minus that of the row `SCENE/BASE` of the same scene (`--base`, e.g.
  none0: the clean run), where there is one;
- ms/step: training seconds over steps (warm-up and evaluations excluded);
- trained / marched: samples per step at the last evaluation, millions (marched only where
  compaction ran and the run records it);
- slots: the slots (padding included) of the fixed-capacity buffer the field trained on at
  the last evaluation, millions (runs that record it);
- captures: the CUDA graphs the run had captured by its last evaluation (one more at every
  change of a buffer's capacity; runs that record it), and "(N back)" where N key changes
  replayed kept graphs instead (`graph_keys`);
- compacting: the share of the last evaluation interval's steps that compacted;
- error left: rotation error the poses still have (°, perturbed runs);
- jitter: its part that changes from one pose to the next (°, `pose_refine.pose_jitter_deg`:
  about the error itself where each pose's is its own, ~0 where it is smooth along the path;
  runs from before the forty-fourth session have none);
- largest turn: the largest correction any pose row had at the end (°, refined runs): a row
  that ran away stands out (gpu_s53's lattice at 1°: 9.5° where the rest stay under 0.7°);
- settled: the budget fraction at which the windows lengthened (`refine_settle_px`; ↺: the
  field started afresh there, `refine_restart`), from
  the run's config.json.
With --phases, where a run's step time goes instead: ms per step between consecutive --at
times' curve points (e.g. `--phases --at 1 5 12 30 60`), the first point from which most
steps compacted, and the compaction switch's last reading of the share of marched samples
compositing used (runs that record it).
Printed, or written atomically to --out (an existing file is refused; nothing is lost).
"""

from __future__ import annotations

import argparse
import json
import math
from itertools import pairwise
from pathlib import Path
from typing import Any

from fastenerf.errors import InputError, require

from .cli import benchmark_main, check_table_out, print_or_write_table

DASH = "—"


def load_run(folder: str | Path) -> dict[str, Any]:
    """The first run of `folder`/error_vs_time.json, with `settled_at` (None if it never
    lengthened its windows) from its run folder's config.json where there is one."""
    path = Path(folder) / "error_vs_time.json"
    if not path.is_file():
        raise InputError(f"{path}: no error_vs_time.json here")
    try:
        runs = json.loads(path.read_text()).get("runs") or []
    except (json.JSONDecodeError, AttributeError) as e:
        raise InputError(f"{path}: not an error_vs_time result ({e})") from None
    if not runs or not runs[0].get("points"):
        raise InputError(f"{path}: no run with evaluation points in it")
    run = dict(runs[0])
    run["settled_at"] = None
    for conf in sorted(Path(folder).glob("runs/*/config.json"))[:1]:
        try:
            saved = json.loads(conf.read_text())
            calib = saved.get("self_calibration") or {}
        except (json.JSONDecodeError, AttributeError) as e:
            raise InputError(f"{conf}: not a run's config.json ({e})") from None
        run["settled_at"] = (calib.get("poses") or {}).get("settled_at")
        restart = saved.get("field_restart") or {}  # made, or declined (no restarts)
        run["restarted_at"] = restart.get("progress") if restart.get("restarts") else None
    return run


def parse_item(item: str) -> tuple[str, str]:
    """'LABEL=DIR' or 'DIR' -> (label, dir); a bare DIR is labelled by its last two parts."""
    label, eq, folder = item.rpartition("=")
    if not eq:
        parts = Path(item.rstrip("/")).parts
        return "/".join(parts[-2:]), item
    if not label or not folder:
        raise InputError(f"{item!r}: expected DIR or LABEL=DIR")
    return label, folder


def _num(v: Any, fmt: str) -> str:
    ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
    return format(v, fmt) if ok else DASH


def row(label: str, run: dict, at: list[float], base: dict | None) -> list[str]:
    """One table row (strings) of `run` (`load_run`), Δ against `base` (or None)."""
    pts = run["points"]
    by_target = {round(float(p.get("target_s", -1)), 3): p for p in pts}
    last = pts[-1]
    cells = [label]
    cells += [_num(by_target.get(round(t, 3), {}).get("psnr"), ".2f") for t in at]
    delta = None if base is None else last.get("psnr", math.nan) - base["points"][-1]["psnr"]
    cells.append(_num(delta, "+.2f"))
    steps, train_s = run.get("step") or last.get("step"), run.get("train_s") or last["train_s"]
    cells.append(_num(1000.0 * train_s / steps if steps else None, ".2f"))
    trained, marched = last.get("samples_per_step"), last.get("marched_per_step")
    cells.append(_num(None if trained is None else trained / 1e6, ".2f"))
    cells.append(_num(None if marched is None else marched / 1e6, ".2f"))
    slots = last.get("trained_slots")
    cells.append(_num(None if slots is None else slots / 1e6, ".2f"))
    captures, back = _num(last.get("graph_captures"), "d"), last.get("graph_returns")
    cells.append(f"{captures} ({back} back)" if back else captures)
    cells.append(_num(last.get("compacted_share"), ".2f"))
    pose = ("pose_error_deg", ".3f"), ("pose_jitter_deg", ".3f"), ("pose_correction_max_deg", ".2f")
    for key, fmt in pose:
        v = last.get(key)
        cells.append(DASH if v is None else f"{v:{fmt}}°")
    restart = run.get("restarted_at")  # refine_restart's new field
    cells.append(_num(run.get("settled_at"), ".0%") + ("" if restart is None else " ↺"))
    return cells


def phase_row(label: str, run: dict, at: list[float]) -> list[str]:
    """One --phases row of `run`: ms per step between the points at consecutive `at` times
    ("—" where a point is missing), where compaction came on, the last compositing share."""
    by_target = {round(float(p.get("target_s", -1)), 3): p for p in run["points"]}
    cells = [label]
    for a, b in pairwise(at):
        pa, pb = by_target.get(round(a, 3)), by_target.get(round(b, 3))
        ms = None
        if pa and pb and pb.get("step", 0) > pa.get("step", 0):
            ms = 1000.0 * (pb["train_s"] - pa["train_s"]) / (pb["step"] - pa["step"])
        cells.append(_num(ms, ".2f"))
    on = next((p for p in run["points"] if (p.get("compacted_share") or 0) >= 0.5), None)
    cells.append(DASH if on is None else f"{on['target_s']:g} s")
    cells.append(_num(run["points"][-1].get("compositing_share"), ".2f"))
    return cells


def table(items: list[str], at: list[float], base: str | None = None, phases: bool = False) -> str:
    """The Markdown table of `items` ('[LABEL=]DIR'), every folder read before any row."""
    parsed = [parse_item(i) for i in items]
    runs = [load_run(folder) for _, folder in parsed]
    by_label = dict(zip((label for label, _ in parsed), runs, strict=True))
    if phases:
        head = ["run", *[f"{a:g}–{b:g} s" for a, b in pairwise(at)], "compacting from", "share"]
    else:
        head = ["run", *[f"{t:g} s" for t in at], "Δ", "ms/step", "trained M", "marched M"]
        head += ["slots M", "captures", "compacting", "error left", "jitter", "largest turn"]
        head.append("settled")
    lines = ["| " + " | ".join(head) + " |", "|---|" + "---:|" * (len(head) - 1)]
    for (label, _), run in zip(parsed, runs, strict=True):
        if phases:
            lines.append("| " + " | ".join(phase_row(label, run, at)) + " |")
            continue
        ref = None
        if base is not None and "/" in label:
            ref = by_label.get(label.rsplit("/", 1)[0] + "/" + base)
        lines.append("| " + " | ".join(row(label, run, at, ref)) + " |")
    return "\n".join(lines) + "\n"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("items", nargs="+", metavar="[LABEL=]DIR")
    p.add_argument("--at", nargs="+", type=float, default=[5, 10, 15, 30, 60],
                   help="training times (s) whose PSNR is shown")  # fmt: skip
    p.add_argument("--base", default=None, help="the NAME whose row of each scene Δ is against")
    p.add_argument("--phases", action="store_true",
                   help="ms per step between the --at times' points instead")  # fmt: skip
    p.add_argument("--out", default=None, help="Markdown file to write (default: print)")


def run(args: argparse.Namespace) -> int:
    require(all(t > 0 and math.isfinite(t) for t in args.at), "--at: times must be > 0")
    require(not args.phases or len(args.at) >= 2, "--phases needs two --at times or more")
    require(not (args.phases and args.base), "--base gives Δ, which --phases has none of")
    check_table_out(args.out)
    return print_or_write_table(table(args.items, args.at, args.base, args.phases), args.out)


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    return benchmark_main("run_table", __doc__, add_arguments, run, argv, prog)


if __name__ == "__main__":
    raise SystemExit(main())
