"""The pose-sensitivity curves (pose_sensitivity.py's JSON lines) against the 2° runs' gaps.
Usage: python benchmarks/results/h200_s35/scripts/plot_sensitivity.py (from any folder)"""

import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[4]  # the repository
sys.path.insert(0, str(ROOT))
from benchmarks.plots import plt, save_figure  # noqa: E402  (needs ROOT on the path)

HERE = ROOT / "benchmarks/results"
CURVES = {  # label: (file, colour)
    "lattice, H200 (0°: 38.61 dB)": (HERE / "h200_s35/lattice_sensitivity.jsonl", "C0"),
    "lattice173, CPU (30.23 dB)": (HERE / "cpu_s35/lattice173_sensitivity.jsonl", "C1"),
    "shiny173, CPU (29.87 dB)": (HERE / "cpu_s35/shiny173_sensitivity.jsonl", "C2"),
}
# 2° runs with the prior and refinement: (mean pose error left, PSNR against the 0° run).
RUNS = {
    "lattice 2°, H100 60 s": (0.0181, 36.36 - 38.63, "C0"),
    "shiny 2°, H100 60 s": (0.0806, 30.91 - 34.30, "C3"),
    "lattice173 2°, CPU 3000 steps": (0.2148, 25.88 - 29.96, "C1"),
    "shiny173 2°, CPU 3000 steps": (0.2510, 26.65 - 29.50, "C2"),
}

missing = [str(path) for path, _ in CURVES.values() if not path.is_file()]
if missing:
    print(
        f"plot_sensitivity.py: error: {missing[0]}: no such file",
        file=sys.stderr,
    )
    sys.exit(2)

fig, ax = plt.subplots(figsize=(7, 4.5))
for label, (path, colour) in CURVES.items():
    rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    base = next(r["psnr"] for r in rows if r["deg"] == 0)
    pts = [(r["deg"], r["psnr"] - base) for r in rows if r["deg"] > 0]
    ax.plot(*zip(*pts, strict=True), "o-", color=colour, label=f"test views turned: {label}")
for label, (deg, gap, colour) in RUNS.items():
    ax.plot([deg], [gap], "*", ms=14, color=colour, label=f"{label} (error left, gap)")
ax.set_xscale("log")
ax.set_xlabel("pose error (°; one px = 0.12° at 346×260, 0.24° at 173×130)")
ax.set_ylabel("PSNR change (dB)")
ax.axhline(-2, color="grey", lw=0.8, ls="--")
ax.grid(True, which="both", alpha=0.3)
ax.legend(fontsize=7)
ax.set_title("What a pose error costs, against what the 2° runs leave")
save_figure(fig, HERE / "h200_s35/pose_sensitivity.png")
