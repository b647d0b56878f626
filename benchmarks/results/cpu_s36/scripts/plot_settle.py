"""How far the pose corrections move per 5 % of the budget (the --refine-settle-px test)
against training progress, for the CPU runs at 0° and 2° that never lengthened their windows.

    python benchmarks/results/cpu_s36/scripts/plot_settle.py   (from any folder)

Reads ../obs_0/metrics.jsonl and ../obs_2/metrics.jsonl next to this script and writes
../pose_settle.png; the two tolerances tried (0.3 and 0.1 px) are drawn as lines. A missing
input ends with one line and exit code 2 before anything is written.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent.parent
RUNS = {"0° (true poses)": "obs_0", "2° (after the prior: 0.28°)": "obs_2"}
TOLERANCES = (0.3, 0.1)


def series(run: str) -> tuple[list[float], list[float], list[float]]:
    """(progress, pose_settle_px, pose_error_deg) at each change of pose_settle_px."""
    path = HERE / run / "metrics.jsonl"
    steps = json.loads((HERE / run / "config.json").read_text())["train"]["steps"]
    prog, moved, err, last = [], [], [], None
    for line in path.read_text().splitlines():
        row = json.loads(line)
        v = row.get("pose_settle_px")
        if v is not None and v != last:
            last = v
            prog.append(row["step"] / steps)
            moved.append(v)
            err.append(row.get("pose_error_deg") or float("nan"))
    return prog, moved, err


def main() -> int:
    for run in RUNS.values():
        for name in ("metrics.jsonl", "config.json"):
            if not (HERE / run / name).is_file():
                print(f"plot_settle.py: error: {HERE / run / name} is missing", file=sys.stderr)
                return 2
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from fastenerf.io import atomic_path

    fig, ax = plt.subplots(figsize=(7, 4.4))
    for label, run in RUNS.items():
        prog, moved, _ = series(run)
        ax.plot(prog, moved, marker="o", ms=3, label=label)
    for tol in TOLERANCES:
        ax.axhline(tol, ls="--", lw=0.8, color="grey")
        ax.text(0.99, tol, f"{tol} px", ha="right", va="bottom", fontsize=8, color="grey")
    ax.set_yscale("log")
    ax.set_xlabel("training progress (fraction of the 3000-step budget)")
    ax.set_ylabel("RMS movement of the corrections per 5 % (px)")
    title = "lattice173 on the CPU, W 15 throughout: what --refine-settle-px compares"
    ax.set_title(title, fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    out = HERE / "pose_settle.png"
    with atomic_path(out) as tmp:
        fig.savefig(tmp, dpi=120, bbox_inches="tight", format="png")
    print(out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
