"""ms per step between a run's curve points (training clock), and the compaction share at each:
where in a 60 s run the step time goes.

    python benchmarks/results/h200_s39/scripts/segments.py RUN_DIR [RUN_DIR ...]

RUN_DIR: an error_vs_time run folder (its error_vs_time.json). Prints one line per run.
"""

import json
import sys
from itertools import pairwise
from pathlib import Path

EDGES = (1, 5, 12, 30, 60)  # segment edges, curve target seconds


def main(argv: list[str]) -> int:
    if not argv:
        print("segments.py: error: usage: segments.py RUN_DIR [RUN_DIR ...]", file=sys.stderr)
        return 2
    rows = []
    for run in argv:  # every run read before anything is printed
        f = Path(run) / "error_vs_time.json"
        try:
            by = {round(p["target_s"]): p for p in json.loads(f.read_text())["points"]}
            ms = [
                1000 * (by[b]["train_s"] - by[a]["train_s"]) / (by[b]["step"] - by[a]["step"])
                for a, b in pairwise(EDGES)
            ]
        except (OSError, ValueError, KeyError, ZeroDivisionError) as e:
            why = f"no point at {e} s" if isinstance(e, KeyError) else str(e)
            print(f"segments.py: error: {f}: {why}", file=sys.stderr)
            return 2
        on = next((t for t in sorted(by) if by[t].get("compacted_share", 0) >= 0.5), None)
        name = "/".join(Path(run).parts[-2:])
        rows.append(f"| {name} | " + " | ".join(f"{m:.2f}" for m in ms) + f" | {on} s |")
    print("| run | " + " | ".join(f"{a}-{b} s" for a, b in pairwise(EDGES)) + " | on at |")
    print("|---|" + "---:|" * len(EDGES))
    print("\n".join(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
