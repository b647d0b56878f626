"""PSNR at 3000 steps (CPU preset, 0°) per scene against the longest event window:
python benchmarks/results/cpu_windows_s34/scripts/plot.py"""

import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

D = Path(__file__).resolve().parents[1]
RUNS = {15: "{s}_0d", 30: "{s}_0w30", 60: "{s}_0w60"}


def psnr(name: str):
    f = D / name / "pose-error.json"
    if not f.is_file():
        return None
    rows = json.loads(f.read_text())["levels"]
    return rows[0]["psnr"]


fig, ax = plt.subplots(figsize=(6.4, 4.2))
for s in ("blocks", "plant", "shiny", "lattice", "toyset"):
    pts = [
        (w, psnr(p.format(s=s) if s != "shiny" or w != 15 else "shiny_0")) for w, p in RUNS.items()
    ]
    pts = [(w, v) for w, v in pts if v is not None]
    ax.plot([w for w, _ in pts], [v for _, v in pts], "o-", label=s)
ax.set_xlabel("win_max (views of a 300-view loop; default 15)")
ax.set_ylabel("PSNR at 3000 steps (dB, colour-corrected)")
ax.set_xticks([15, 30, 60])
ax.grid(alpha=0.3)
ax.legend()
ax.set_title("Longest event window, CPU preset, 0°, 173×130 (2-core CPU)")
fig.tight_layout()
fig.savefig(D / "windows_cpu.png", dpi=110)
print(D / "windows_cpu.png")
