"""Stack pose-study image grids into one picture, a labelled row each.

    python benchmarks/results/cpu_s55/scripts/stack_grids.py OUT.png LABEL=GRID.png ...

Rows are padded to the widest; an existing OUT.png is refused (nothing written).
"""

import sys
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw


def main(argv: list[str]) -> int:
    if len(argv) < 2 or Path(argv[0]).exists() or not all("=" in a for a in argv[1:]):
        print(
            "stack_grids: error: usage: stack_grids.py NEW.png LABEL=GRID.png ...", file=sys.stderr
        )
        return 2
    rows = []
    for item in argv[1:]:
        label, path = item.split("=", 1)
        img = Image.open(path).convert("RGB")
        band = Image.new("RGB", (img.width, 18), "white")
        ImageDraw.Draw(band).text((4, 3), label, fill="black")
        rows.append(np.vstack([np.asarray(band), np.asarray(img)]))
    width = max(r.shape[1] for r in rows)
    rows = [np.pad(r, ((0, 0), (0, width - r.shape[1]), (0, 0)), constant_values=255) for r in rows]
    Image.fromarray(np.vstack(rows)).save(argv[0])
    print(argv[0])
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
