"""Stack pose-study image grids into one picture, a labelled row each.

    python benchmarks/results/cpu_s55/scripts/stack_grids.py OUT.png LABEL=GRID.png ...

Rows are padded to the widest; an existing OUT.png is refused (nothing written).
"""

import sys
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw


def main(argv: list[str]) -> int:
    def fail(why: str) -> int:
        print(f"stack_grids: error: {why}", file=sys.stderr)
        return 2

    if len(argv) < 2 or not all("=" in a for a in argv[1:]):
        return fail("usage: stack_grids.py NEW.png LABEL=GRID.png ...")
    if Path(argv[0]).exists():
        return fail(f"{argv[0]} exists (nothing written)")
    missing = [a.split("=", 1)[1] for a in argv[1:] if not Path(a.split("=", 1)[1]).is_file()]
    if missing:
        return fail(f"{missing[0]} is not a file (nothing written)")
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
